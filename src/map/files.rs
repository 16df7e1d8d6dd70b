//! File-system primitives of the map store: atomic replacement of a file, the advisory write lock
//! of a map directory, names that no other process can pick, and the atomic swap of two
//! directories (`map build --force`).

use crate::error::{Error, Result};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// The lock file in a map directory. It is never deleted: the lock is the OS advisory lock on it
/// (`flock`), which the kernel releases when the holding process exits or dies, so a file left
/// behind by a crash does not block anyone.
pub const LOCK: &str = ".lock";
/// How long a writer waits for another writer's lock before giving up. Writers hold it only to
/// write one segment and the manifest (well under a second); `map compact` holds it while it
/// rewrites the segments that have removed images, which takes minutes on million-image maps.
pub const LOCK_WAIT: Duration = Duration::from_secs(600);
/// Poll interval while waiting for the lock (a blocking `flock` could not time out).
const LOCK_POLL: Duration = Duration::from_millis(20);

thread_local! {
    /// The name prefix of the next write to fail on this thread ([`fail_next_write`]).
    static FAULT: std::cell::Cell<Option<&'static str>> = const { std::cell::Cell::new(None) };
}

/// Test hook: the next [`write_atomic`] on this thread of a file whose name starts with `prefix`
/// (`"segment-"`, `"manifest.json"`, ...) fails after its temporary file is written and before
/// the rename, as a full disk or a crash there would, with an I/O error naming the temporary
/// file. `None` disarms it. Per thread, so tests running in parallel do not see each other's.
#[doc(hidden)]
pub fn fail_next_write(prefix: Option<&'static str>) {
    FAULT.with(|f| f.set(prefix));
}

/// Whether an armed [`fail_next_write`] matches `name` (disarming it).
fn fault_at(name: &str) -> bool {
    FAULT.with(|f| f.get().is_some_and(|p| name.starts_with(p)) && f.take().is_some())
}

/// Writes `bytes` to `dir/name` atomically: temporary file, fsync, rename, directory fsync. Callers
/// hold the map's write lock, so the temporary name is never shared.
pub fn write_atomic(dir: &Path, name: &str, bytes: &[u8]) -> Result<()> {
    let tmp = dir.join(format!(".{name}.tmp"));
    let dst = dir.join(name);
    let mut f = std::fs::File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
    if let Err(e) = f.write_all(bytes).and_then(|()| f.sync_all()) {
        // a full disk: give the space back now (a crash here leaves it to the next writer)
        drop(f);
        let _ = std::fs::remove_file(&tmp);
        return Err(Error::io(&tmp, e));
    }
    drop(f);
    if fault_at(name) {
        return Err(Error::io(&tmp, std::io::Error::other("injected fault: stopped before the rename")));
    }
    std::fs::rename(&tmp, &dst).map_err(|e| Error::io(&dst, e))?;
    sync_dir(dir);
    Ok(())
}

/// Makes a directory's entries (renames, new files) durable; best effort where the platform has
/// no directory fsync.
pub fn sync_dir(dir: &Path) {
    if let Ok(d) = std::fs::File::open(dir) {
        let _ = d.sync_all();
    }
}

/// The exclusive write lock of a map directory, held until dropped (or the process ends).
pub struct WriteLock {
    file: std::fs::File,
}

impl WriteLock {
    /// Takes the lock of `dir` (which must exist), waiting up to [`LOCK_WAIT`] for another
    /// writer; says so on the log once it has waited a second.
    pub fn take(dir: &Path) -> Result<WriteLock> {
        let p = dir.join(LOCK);
        let file = std::fs::OpenOptions::new().create(true).truncate(false).write(true).open(&p).map_err(|e| Error::io(&p, e))?;
        let t = Instant::now();
        let mut said = false;
        let mut file = Some(file);
        loop {
            match WriteLock::try_lock(dir, &mut file)? {
                Some(lock) => return Ok(lock),
                None if t.elapsed() > LOCK_WAIT => {
                    return Err(Error::invalid(
                        format!("map {}", dir.display()),
                        format!("another semlook process has held the write lock {} for more than {} s", p.display(), LOCK_WAIT.as_secs()),
                    ));
                }
                None => {}
            }
            if !said && t.elapsed() > Duration::from_secs(1) {
                log::info!("waiting for another writer of {} (lock {})", dir.display(), p.display());
                said = true;
            }
            std::thread::sleep(LOCK_POLL);
        }
    }

    /// Takes the lock of `dir` (which must exist) if no other writer holds it; `None` if one does.
    pub fn try_take(dir: &Path) -> Result<Option<WriteLock>> {
        let p = dir.join(LOCK);
        let file = std::fs::OpenOptions::new().create(true).truncate(false).write(true).open(&p).map_err(|e| Error::io(&p, e))?;
        WriteLock::try_lock(dir, &mut Some(file))
    }

    /// One try at locking `file`, the lock file of `dir` (taken from the option when locked):
    /// then removes what interrupted writers left.
    fn try_lock(dir: &Path, file: &mut Option<std::fs::File>) -> Result<Option<WriteLock>> {
        let Some(f) = file.as_ref() else { return Ok(None) };
        match fs4::FileExt::try_lock(f) {
            Ok(()) => {
                // temporaries are written only under this lock: any there now is stale
                for stale in leftovers(dir) {
                    let gone = if stale.is_dir() { std::fs::remove_dir_all(&stale) } else { std::fs::remove_file(&stale) };
                    match gone {
                        Ok(()) => log::info!("removed {}, left by an interrupted writer", stale.display()),
                        Err(e) => log::warn!("cannot remove {}, left by an interrupted writer: {e}", stale.display()),
                    }
                }
                Ok(file.take().map(|file| WriteLock { file }))
            }
            Err(fs4::TryLockError::WouldBlock) => Ok(None),
            Err(fs4::TryLockError::Error(e)) => Err(Error::io(dir.join(LOCK), e)),
        }
    }
}

/// Whether a writer holds the write lock of `dir` now (a build that has committed nothing yet
/// holds it from its start: [`super::MapWriter::create`]). Creates no file: a folder without a
/// lock file is not locked. False where it cannot be told.
pub fn is_locked(dir: &Path) -> bool {
    let Ok(file) = std::fs::File::open(dir.join(LOCK)) else { return false };
    match fs4::FileExt::try_lock_shared(&file) {
        Ok(()) => {
            let _ = fs4::FileExt::unlock(&file);
            false
        }
        Err(fs4::TryLockError::WouldBlock) => true,
        Err(fs4::TryLockError::Error(_)) => false,
    }
}

impl Drop for WriteLock {
    fn drop(&mut self) {
        let _ = fs4::FileExt::unlock(&self.file);
    }
}

/// The name prefix of an index build's staging folder in the map folder (`map::index::build`),
/// followed by its process id.
pub const INDEX_STAGING: &str = ".index-staging-";

/// What interrupted writers of map `dir` left: temporary files `.NAME.tmp` in it (written only
/// under the write lock, so stale whenever the lock is free), the staging folders of index builds
/// in it (`.index-staging-PID-...`) and of `build --force` beside it (`.DIR.building-PID-...`)
/// whose process no longer runs (Linux; where that cannot be told, none are listed).
pub fn leftovers(dir: &Path) -> Vec<PathBuf> {
    let dead_pid = |rest: &str| rest.split('-').next().and_then(|p| p.parse::<u32>().ok()).is_some_and(process_is_gone);
    let mut out: Vec<PathBuf> = std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .filter(|e| {
            let (name, kind) = (e.file_name(), e.file_type());
            let Some(n) = name.to_str() else { return false };
            (n.starts_with('.') && n.ends_with(".tmp") && kind.as_ref().is_ok_and(|t| t.is_file()))
                || (n.strip_prefix(INDEX_STAGING).is_some_and(dead_pid) && kind.as_ref().is_ok_and(|t| t.is_dir()))
        })
        .map(|e| e.path())
        .collect();
    if let (Some(name), Some(parent)) = (dir.file_name().and_then(|n| n.to_str()), dir.parent()) {
        let parent = if parent.as_os_str().is_empty() { Path::new(".") } else { parent };
        let prefix = format!(".{name}.building-");
        for e in std::fs::read_dir(parent).into_iter().flatten().flatten() {
            let dead = e
                .file_name()
                .to_str()
                .and_then(|n| n.strip_prefix(&prefix))
                .and_then(|rest| rest.split('-').next()?.parse::<u32>().ok())
                .is_some_and(process_is_gone);
            if dead && e.file_type().is_ok_and(|t| t.is_dir()) {
                out.push(e.path());
            }
        }
    }
    out.sort();
    out
}

/// Whether process `pid` has ended (Linux: no /proc entry). False where it cannot be told.
fn process_is_gone(pid: u32) -> bool {
    cfg!(target_os = "linux") && Path::new("/proc/self").exists() && pid != std::process::id() && !Path::new(&format!("/proc/{pid}")).exists()
}

/// A name no other process picks: `prefix`, this process id, the time in nanoseconds and a
/// counter (for several names within one process).
pub fn unique_suffix() -> String {
    static COUNTER: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos());
    format!("{}-{nanos:x}-{n}", std::process::id())
}

/// A fresh path beside `path` (same folder, so renames stay atomic): `.NAME.what-UNIQUE`.
pub fn sibling(path: &Path, what: &str) -> Result<PathBuf> {
    let name = path.file_name().ok_or_else(|| Error::invalid(format!("path {}", path.display()), "has no final component"))?;
    let parent = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    Ok(parent.join(format!(".{}.{what}-{}", name.to_string_lossy(), unique_suffix())))
}

/// Swaps the directories `a` and `b` (both exist): atomically on Linux (`renameat2` with
/// `RENAME_EXCHANGE`), elsewhere by two renames through a third unique name.
pub fn exchange(a: &Path, b: &Path) -> Result<()> {
    #[cfg(target_os = "linux")]
    {
        use rustix::fs::{renameat_with, RenameFlags, CWD};
        match renameat_with(CWD, a, CWD, b, RenameFlags::EXCHANGE) {
            Ok(()) => return Ok(()),
            // file systems without RENAME_EXCHANGE fall through to the two renames
            Err(e) if e == rustix::io::Errno::INVAL || e == rustix::io::Errno::NOSYS => {}
            Err(e) => return Err(Error::io(a, e.into())),
        }
    }
    let third = sibling(a, "swap")?;
    std::fs::rename(a, &third).map_err(|e| Error::io(a, e))?;
    std::fs::rename(b, a).map_err(|e| Error::io(b, e))?;
    std::fs::rename(&third, b).map_err(|e| Error::io(&third, e))?;
    Ok(())
}
