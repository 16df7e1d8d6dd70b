//! Where a stream's frames come from: a folder of images in name or timestamp order, or images
//! written one after another to a pipe (standard input: `ffmpeg ... -f image2pipe -c:v mjpeg -`
//! turns any video into that, PNG works too).

use super::{Pixels, StreamFrame};
use crate::error::{Error, Result};
use crate::input::FrameSource;
use std::io::Read;
use std::path::{Path, PathBuf};

/// The frames of a folder: its images (png/jpg) in name order, or with `timestamps` in the order
/// of their times (ties by name). The timestamps file has a line `name time` (or `name,time`) per
/// image, times in seconds, `#` lines and a header line without a number ignored; every image of
/// the folder must be listed, and every name listed must be an image there (checked before any
/// frame is read). Label maps, when a folder is given, are `<stem>.png` there.
pub fn folder_frames(images: &Path, labels: Option<&Path>, timestamps: Option<&Path>) -> Result<Vec<StreamFrame>> {
    let files = crate::dataset::image_files(images)?;
    if files.is_empty() {
        return Err(Error::invalid(images.display().to_string(), "no images (png, jpg) in this folder"));
    }
    let name = |p: &Path| p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let stem = |p: &Path| p.file_stem().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let times = match timestamps {
        Some(t) => Some(read_timestamps(t)?),
        None => None,
    };
    let mut frames: Vec<(Option<f64>, String, PathBuf)> = Vec::with_capacity(files.len());
    for f in &files {
        let ts = match &times {
            Some(times) => match times.iter().find(|(n, _)| *n == name(f) || *n == stem(f)) {
                Some(&(_, t)) => Some(t),
                None => {
                    return Err(Error::invalid(timestamps.map(|t| t.display().to_string()).unwrap_or_default(), format!("no time for {}", name(f))))
                }
            },
            None => None,
        };
        frames.push((ts, name(f), f.clone()));
    }
    if let (Some(times), Some(t)) = (&times, timestamps) {
        if let Some((n, _)) = times.iter().find(|(n, _)| !files.iter().any(|f| name(f) == *n || stem(f) == *n)) {
            return Err(Error::invalid(t.display().to_string(), format!("{n:?} is not an image of {}", images.display())));
        }
        frames.sort_by(|a, b| a.0.unwrap_or(0.0).total_cmp(&b.0.unwrap_or(0.0)).then_with(|| a.1.cmp(&b.1)));
    }
    Ok(frames
        .into_iter()
        .map(|(timestamp, _, path)| {
            let id = stem(&path);
            let label = labels.map(|l| l.join(format!("{id}.png")));
            StreamFrame { id, pixels: Pixels::Files(FrameSource { id: stem(&path), image: Some(path), labels: label }), timestamp }
        })
        .collect())
}

/// `name time` lines of a timestamps file (seconds; `#` lines and a header line ignored).
pub fn read_timestamps(path: &Path) -> Result<Vec<(String, f64)>> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let mut out = Vec::new();
    for (k, line) in text.lines().enumerate() {
        let line = line.trim_start_matches('\u{feff}').trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let mut parts = line.split(|c: char| c == ',' || c.is_whitespace()).filter(|s| !s.is_empty());
        let (Some(n), Some(t)) = (parts.next(), parts.next()) else {
            return Err(Error::invalid(path.display().to_string(), format!("line {}: expected `name time`", k + 1)));
        };
        match t.parse::<f64>() {
            Ok(t) if t.is_finite() => out.push((n.to_string(), t)),
            // a header line
            Err(_) if out.is_empty() && k == 0 => {}
            _ => return Err(Error::invalid(path.display().to_string(), format!("line {}: {t:?} is not a time in seconds", k + 1))),
        }
    }
    Ok(out)
}

/// The median step, in seconds, between the times a timestamps file gives `frames` (in their
/// order: the order a map adds them), each found by its image's file name or stem. The times
/// must increase along the frames; two frames at least.
pub fn median_interval(path: &Path, frames: &[FrameSource]) -> Result<f64> {
    let times = read_timestamps(path)?;
    let bad = |r: String| Error::invalid(path.display().to_string(), r);
    let mut at: Vec<(String, f64)> = Vec::with_capacity(frames.len());
    for f in frames {
        let img = f.image.as_deref().ok_or_else(|| bad(format!("frame {:?} has no image file to find its time by", f.id)))?;
        let name = img.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let stem = img.file_stem().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let t = times.iter().find(|(n, _)| *n == name || *n == stem).ok_or_else(|| bad(format!("no time for {name}")))?.1;
        if let Some((prev, last)) = at.last() {
            if t <= *last {
                return Err(bad(format!(
                    "{name} at {t} s does not come after {prev} at {last} s: times must increase in the order the images are added (name order)"
                )));
            }
        }
        at.push((name, t));
    }
    if at.len() < 2 {
        return Err(bad("a frame interval needs the times of two frames at least".into()));
    }
    let mut steps: Vec<f64> = at.windows(2).map(|w| w[1].1 - w[0].1).collect();
    steps.sort_by(f64::total_cmp);
    Ok(steps[steps.len() / 2])
}

/// Most bytes one image of a piped stream may take.
pub const MAX_FRAME_BYTES: usize = 64 << 20;

/// Bytes asked of the reader at a time.
const READ_CHUNK: usize = 1 << 16;

/// Images read one after another from a byte stream (JPEG: segments walked to the end-of-image
/// marker; PNG: chunks to IEND). Bytes that start neither are skipped up to the next image start
/// and reported once as an error, so one damaged frame costs that frame, not the stream.
pub struct ImageStream<R: Read> {
    reader: R,
    /// Bytes read; those before `start` are consumed.
    buf: Vec<u8>,
    start: usize,
    eof: bool,
    /// Bytes consumed so far (for error positions).
    offset: u64,
    name: String,
}

impl<R: Read> ImageStream<R> {
    /// `name` says where the bytes come from in errors (e.g. "standard input").
    pub fn new(reader: R, name: &str) -> ImageStream<R> {
        ImageStream { reader, buf: Vec::new(), start: 0, eof: false, offset: 0, name: name.into() }
    }

    /// Reads until `buf` holds at least `n` bytes (from `start`) or the stream ends; whether it
    /// does. Costs nothing where the bytes are there already: the image walk asks for every
    /// marker (issue 48: a 64 KiB chunk zeroed per call made a piped stream 2-4x slower than the
    /// same files read from a folder).
    fn fill(&mut self, n: usize) -> Result<bool> {
        while self.buf.len() - self.start < n && !self.eof {
            // read straight into the buffer's tail (zeroed once per read, not per call)
            let len = self.buf.len();
            self.buf.resize(len + READ_CHUNK, 0);
            let got = self.reader.read(&mut self.buf[len..]);
            self.buf.truncate(len + *got.as_ref().unwrap_or(&0));
            match got {
                Ok(0) => self.eof = true,
                Ok(_) => {}
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(Error::io(Path::new(&self.name), e)),
            }
        }
        Ok(self.buf.len() - self.start >= n)
    }

    /// The bytes not yet consumed.
    fn rest(&self) -> &[u8] {
        &self.buf[self.start..]
    }

    /// Consumes the next `n` bytes and returns them; the buffer's consumed head is dropped once
    /// it outweighs what is left, so consuming costs no more than reading.
    fn take(&mut self, n: usize) -> Vec<u8> {
        self.offset += n as u64;
        let out = self.buf[self.start..self.start + n].to_vec();
        self.start += n;
        if self.start >= self.buf.len() - self.start {
            self.buf.drain(..self.start);
            self.start = 0;
        }
        out
    }

    fn bad(&self, reason: String) -> Error {
        Error::invalid(format!("{} at byte {}", self.name, self.offset), reason)
    }

    /// The length of the image at the start of the unconsumed bytes, reading more as needed;
    /// `None` where the stream ends inside it.
    fn image_len(&mut self) -> Result<Option<usize>> {
        if self.rest().starts_with(PNG) {
            let mut at = PNG.len();
            loop {
                if !self.fill(at + 8)? {
                    return Ok(None);
                }
                let b = self.rest();
                let len = u32::from_be_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]]) as usize;
                let end = at + 12 + len;
                if end > MAX_FRAME_BYTES {
                    return Err(self.bad(format!("a PNG larger than {} MiB", MAX_FRAME_BYTES >> 20)));
                }
                let iend = &b[at + 4..at + 8] == b"IEND";
                if !self.fill(end)? {
                    return Ok(None);
                }
                at = end;
                if iend {
                    return Ok(Some(at));
                }
            }
        }
        // JPEG: SOI, then marker segments with lengths; after SOS, entropy-coded data up to the
        // next marker (0xFF not followed by 0x00 or a restart marker)
        let mut at = 2;
        loop {
            if at > MAX_FRAME_BYTES {
                return Err(self.bad(format!("a JPEG larger than {} MiB", MAX_FRAME_BYTES >> 20)));
            }
            if !self.fill(at + 2)? {
                return Ok(None);
            }
            if self.rest()[at] != 0xFF {
                return Err(self.bad(format!("JPEG marker expected at offset {at} of the image")));
            }
            let marker = self.rest()[at + 1];
            match marker {
                0xD9 => return Ok(Some(at + 2)),
                0xFF => at += 1,
                0x01 | 0xD0..=0xD7 => at += 2,
                _ => {
                    if !self.fill(at + 4)? {
                        return Ok(None);
                    }
                    let len = u16::from_be_bytes([self.rest()[at + 2], self.rest()[at + 3]]) as usize;
                    if len < 2 {
                        return Err(self.bad(format!("JPEG segment of length {len}")));
                    }
                    at += 2 + len;
                    if marker == 0xDA {
                        // entropy-coded data: the bytes read so far scanned for 0xFF at once
                        loop {
                            if at > MAX_FRAME_BYTES {
                                return Err(self.bad(format!("a JPEG larger than {} MiB", MAX_FRAME_BYTES >> 20)));
                            }
                            if !self.fill(at + 2)? {
                                return Ok(None);
                            }
                            let b = self.rest();
                            match b[at..b.len() - 1].iter().position(|&x| x == 0xFF) {
                                Some(k) => {
                                    at += k;
                                    if !matches!(b[at + 1], 0x00 | 0xD0..=0xD7) {
                                        break;
                                    }
                                    at += 2;
                                }
                                // none before the last byte read: read on from there
                                None => at = b.len() - 1,
                            }
                        }
                    }
                }
            }
        }
    }

    /// Skips to the next image start (JPEG or PNG signature); false at the end of the stream.
    fn resync(&mut self) -> Result<bool> {
        loop {
            if !self.fill(8)? {
                let n = self.rest().len();
                self.take(n);
                return Ok(false);
            }
            let b = self.rest();
            if let Some(k) = (1..b.len().saturating_sub(7)).find(|&k| b[k..].starts_with(JPEG) || b[k..].starts_with(PNG)) {
                self.take(k);
                return Ok(true);
            }
            let keep = 7;
            let n = b.len() - keep;
            self.take(n);
            self.fill(self.rest().len() + READ_CHUNK)?;
        }
    }
}

const JPEG: &[u8] = &[0xFF, 0xD8, 0xFF];
const PNG: &[u8] = &[0x89, b'P', b'N', b'G', 0x0D, 0x0A, 0x1A, 0x0A];

impl<R: Read> Iterator for ImageStream<R> {
    /// One image's bytes, or what was wrong with the bytes skipped.
    type Item = Result<Vec<u8>>;
    fn next(&mut self) -> Option<Self::Item> {
        match self.fill(8) {
            Err(e) => return Some(Err(e)),
            Ok(false) if self.rest().is_empty() => return None,
            Ok(_) => {}
        }
        if !(self.rest().starts_with(JPEG) || self.rest().starts_with(PNG)) {
            let e = self.bad("neither a JPEG nor a PNG starts here: skipped to the next image".into());
            return match self.resync() {
                Ok(_) => Some(Err(e)),
                Err(io) => Some(Err(io)),
            };
        }
        match self.image_len() {
            Ok(Some(n)) => Some(Ok(self.take(n))),
            Ok(None) => {
                let e = self.bad(format!("the stream ended inside an image ({} bytes of it)", self.rest().len()));
                let n = self.rest().len();
                self.take(n);
                Some(Err(e))
            }
            Err(e) => {
                // skip the damaged image's start, then to the next one
                self.take(1);
                match self.resync() {
                    Ok(_) => Some(Err(e)),
                    Err(io) => Some(Err(io)),
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn jpeg(w: u32, h: u32, v: u8) -> Vec<u8> {
        let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([v, (x * 7) as u8, (y * 3) as u8]));
        let mut out = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 90).encode_image(&img).unwrap();
        out
    }

    fn png(w: u32, h: u32) -> Vec<u8> {
        let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x + y) as u8, 0, 9]));
        let mut out = Vec::new();
        img.write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Png).unwrap();
        out
    }

    /// Images split back exactly as they were written, whatever the read sizes, and garbage
    /// between them costs one error and nothing else.
    #[test]
    fn piped_images_split_back_exactly() {
        let (a, b, c) = (jpeg(40, 30, 1), png(17, 9), jpeg(64, 48, 200));
        let mut bytes = a.clone();
        bytes.extend_from_slice(&b);
        bytes.extend_from_slice(b"garbage between frames");
        bytes.extend_from_slice(&c);
        let got: Vec<Result<Vec<u8>>> = ImageStream::new(OneByte(std::io::Cursor::new(bytes)), "test").collect();
        assert_eq!(got.len(), 4);
        assert_eq!(got[0].as_ref().unwrap(), &a);
        assert_eq!(got[1].as_ref().unwrap(), &b);
        assert!(got[2].as_ref().unwrap_err().to_string().contains("neither a JPEG nor a PNG"));
        assert_eq!(got[3].as_ref().unwrap(), &c);
    }

    #[test]
    fn a_stream_cut_inside_an_image_reports_it() {
        let a = jpeg(40, 30, 1);
        let mut bytes = a.clone();
        bytes.extend_from_slice(&a[..a.len() / 2]);
        let got: Vec<Result<Vec<u8>>> = ImageStream::new(std::io::Cursor::new(bytes), "pipe").collect();
        assert_eq!(got.len(), 2);
        assert_eq!(got[0].as_ref().unwrap(), &a);
        assert!(got[1].as_ref().unwrap_err().to_string().contains("ended inside an image"), "{:?}", got[1]);
        assert_eq!(ImageStream::new(std::io::Cursor::new(Vec::new()), "empty").count(), 0);
    }

    /// A reader that hands out one byte at a time.
    struct OneByte<R>(R);
    impl<R: Read> Read for OneByte<R> {
        fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
            let n = buf.len().min(1);
            self.0.read(&mut buf[..n])
        }
    }
}
