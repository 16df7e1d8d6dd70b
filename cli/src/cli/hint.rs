//! The command line's words for what the engine says a caller can do ([`Remedy`]): library
//! messages speak of the API, this names the flags. A hint names only flags the running command
//! has: each way out of a refusal names the flag it needs, and is left out of commands without it
//! (other commands are named in full, `` `semlook map build --force` ``). A way may need the flag
//! with the shape of its value (`--labels DIR`, a folder, against `inspect`'s `--labels FILE`).

use semlook::error::{Error, Remedy};
use std::sync::OnceLock;

/// One way out: its words, and the flag of the running command they need (`None`: they need
/// none, or name another command in full), alone (`--resume`) or with its value's name
/// (`--labels DIR`: only where `--labels` takes a DIR).
struct Way {
    text: &'static str,
    needs: Option<&'static str>,
}

/// Every remedy's ways out, most direct first.
fn ways(r: Remedy) -> &'static [Way] {
    match r {
        Remedy::AddResumeOrReplace => &[
            Way { text: "`semlook map add --map MAP` appends to it", needs: None },
            Way { text: "--resume continues its interrupted build", needs: Some("--resume") },
            Way { text: "--force replaces it", needs: Some("--force") },
        ],
        Remedy::ResumeOrReplace => &[
            Way { text: "--resume continues an interrupted build", needs: Some("--resume") },
            Way { text: "--force replaces what is there", needs: Some("--force") },
        ],
        Remedy::BuildOrResume => &[
            Way { text: "build it with `semlook map build --images DIR --map MAP`", needs: None },
            Way { text: "continue an interrupted build with `semlook map build --resume`", needs: None },
        ],
        Remedy::GiveLabels => &[
            Way { text: "pass --labels DIR (label maps named like the images)", needs: Some("--labels DIR") },
            Way { text: "pass --labels FILE (the image's label map)", needs: Some("--labels FILE") },
            Way { text: "pass --segmenter MODEL.onnx", needs: Some("--segmenter") },
            Way { text: "`semlook models` lists the segmenter setup.sh installs, and what is missing", needs: None },
        ],
        Remedy::GiveImagesOrNoAppearance => &[
            Way { text: "pass --images DIR", needs: Some("--images") },
            Way { text: "--no-appearance encodes label maps alone", needs: Some("--no-appearance") },
        ],
        Remedy::GiveKeypointModel => &[
            Way { text: "pass --keypoints MODEL.onnx", needs: Some("--keypoints") },
            Way { text: "set models.keypoint_onnx in --config", needs: Some("--config") },
        ],
        Remedy::SmallerSegments => &[Way { text: "build the map with smaller segments: `semlook map build --segment-images N`", needs: None }],
        Remedy::NameReferenceTraversal => &[Way { text: "pass --reference-traversal NAME", needs: Some("--reference-traversal") }],
        Remedy::NameImageRoot => {
            &[Way { text: "pass --pairs-root DIR, a folder that holds the query and reference images", needs: Some("--pairs-root") }]
        }
        Remedy::RebuildWithLabels => &[
            Way { text: "--setting appearance or verified run on this map (and hog where it stores HOG descriptors)", needs: Some("--setting") },
            Way {
                text: "for the others build it again with labels: `semlook map build --force --labels DIR`, or with a segmenter (`semlook models`)",
                needs: None,
            },
        ],
        Remedy::RebuildWithHog => &[Way { text: "build the map again with HOG descriptors: `semlook map build --force --hog`", needs: None }],
        Remedy::SkipStored => &[
            Way { text: "--resume skips the images the map holds already (an interrupted run goes on)", needs: Some("--resume") },
            Way { text: "--id-prefix PREFIX stores the new images under other ids (PREFIX + file name)", needs: Some("--id-prefix") },
        ],
        Remedy::RebuildIndex => &[
            Way { text: "build the index again with `semlook map index --map MAP`", needs: None },
            Way { text: "or drop it with `semlook map index --map MAP --drop` (queries then scan every place)", needs: None },
        ],
        Remedy::SkipInvalid => &[Way { text: "--skip-invalid skips images that fail to load", needs: Some("--skip-invalid") }],
        Remedy::WaitForBuild => &[Way { text: "wait for the build to finish, then run this again", needs: None }],
        Remedy::ResumeWithSameLayout => &[
            Way { text: "--hog as the interrupted build had it (given, or not)", needs: Some("--hog") },
            Way { text: "--f16 as the interrupted build had it (given, or not)", needs: Some("--f16") },
        ],
        Remedy::NoIndexWithoutAppearance => {
            &[Way { text: "--index auto (or none) builds no index on a map without appearance vectors", needs: Some("--index") }]
        }
    }
}

/// The long flags of the command that runs, once it is known (see [`set_command_flags`]).
static FLAGS: OnceLock<Vec<String>> = OnceLock::new();

/// Records the long flags of the running (sub)command, which hints may name: each `--flag`, and
/// `--flag NAME` for a flag whose value is named (`value_name`).
pub fn set_command_flags(flags: Vec<String>) {
    let _ = FLAGS.set(flags);
}

/// The hint for `e` in the running command's words (flags it does not have are left out).
pub fn hint(e: &Error) -> Option<String> {
    let flags = FLAGS.get();
    hint_for(e.remedy()?, &|f| flags.is_none_or(|all| all.iter().any(|x| x == f)))
}

/// The ways out of `r` whose flag `has` says the command has, joined.
pub fn hint_for(r: Remedy, has: &dyn Fn(&str) -> bool) -> Option<String> {
    let words: Vec<&str> = ways(r).iter().filter(|w| w.needs.is_none_or(has)).map(|w| w.text).collect();
    (!words.is_empty()).then(|| words.join("; "))
}

/// The long flags of clap command `c` (its own arguments), as [`set_command_flags`] takes them.
pub fn flags_of(c: &clap::Command) -> Vec<String> {
    let mut out = Vec::new();
    for a in c.get_arguments() {
        let Some(long) = a.get_long() else { continue };
        out.push(format!("--{long}"));
        if let Some([name]) = a.get_value_names() {
            out.push(format!("--{long} {name}"));
        }
    }
    out
}

/// Every remedy (for the tests).
#[cfg(test)]
const ALL: [Remedy; 17] = [
    Remedy::AddResumeOrReplace,
    Remedy::ResumeOrReplace,
    Remedy::BuildOrResume,
    Remedy::GiveLabels,
    Remedy::GiveImagesOrNoAppearance,
    Remedy::GiveKeypointModel,
    Remedy::SmallerSegments,
    Remedy::NameReferenceTraversal,
    Remedy::NameImageRoot,
    Remedy::RebuildWithLabels,
    Remedy::RebuildWithHog,
    Remedy::SkipStored,
    Remedy::RebuildIndex,
    Remedy::SkipInvalid,
    Remedy::WaitForBuild,
    Remedy::ResumeWithSameLayout,
    Remedy::NoIndexWithoutAppearance,
];

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    /// The `--flags` a text names outside the spans that name another command in full.
    fn own_flags(text: &str) -> Vec<String> {
        let mut out = Vec::new();
        for (i, part) in text.split('`').enumerate() {
            // odd parts are inside backticks; those starting with `semlook ` name a command
            if i % 2 == 1 && part.starts_with("semlook ") {
                continue;
            }
            out.extend(part.split(|c: char| c.is_whitespace() || c == ',' || c == '(' || c == ')').filter(|w| w.starts_with("--")).map(String::from));
        }
        out
    }

    /// Every (sub)command with its long flags (and `--flag NAME` where the value is named),
    /// globals included.
    fn commands() -> Vec<(String, Vec<String>)> {
        fn walk(c: &clap::Command, path: String, globals: &[String], out: &mut Vec<(String, Vec<String>)>) {
            let mut flags: Vec<String> = globals.to_vec();
            flags.extend(flags_of(c));
            out.push((path.clone(), flags.clone()));
            for s in c.get_subcommands() {
                walk(s, format!("{path} {}", s.get_name()), &flags, out);
            }
        }
        let mut out = Vec::new();
        walk(&crate::cli::args::Cli::command(), "semlook".into(), &[], &mut out);
        out
    }

    /// Each remedy's hint, in every command of the command line, names only flags that command
    /// has (an eval hint named `--labels DIR`, a flag eval does not have).
    #[test]
    fn hints_name_only_the_running_commands_flags() {
        for w in ALL.iter().flat_map(|&r| ways(r)) {
            let named = own_flags(w.text);
            match w.needs {
                // the flag itself, without the name of its value
                Some(f) => assert_eq!(named, [f.split(' ').next().unwrap_or(f)], "{:?} names other flags than it needs", w.text),
                None => assert!(named.is_empty(), "{:?} names {named:?} without needing them", w.text),
            }
        }
        for (cmd, flags) in commands() {
            for r in ALL {
                if let Some(h) = hint_for(r, &|f| flags.iter().any(|x| x == f)) {
                    for f in own_flags(&h) {
                        assert!(flags.contains(&f), "`{cmd}`: the hint for {r:?} names {f}, which it does not have: {h}");
                    }
                }
            }
        }
        // eval is offered the segmenter, not label maps it has no flag for
        let eval = commands().into_iter().find(|c| c.0 == "semlook eval").unwrap().1;
        let h = hint_for(Remedy::GiveLabels, &|f| eval.iter().any(|x| x == f)).unwrap();
        assert!(h.contains("--segmenter") && !h.contains("--labels"), "{h}");
    }

    /// Each hint for label maps names the value `--labels` takes in the command: a folder for
    /// `query`, `map build` and `localize`, one file for `inspect` (its hint said `--labels DIR`,
    /// and `inspect --labels` takes the image's label map). Seen failing with the words of
    /// before (one `--labels DIR` way needing `--labels`).
    #[test]
    fn the_labels_hint_names_the_value_each_command_takes() {
        let all = commands();
        let hint = |cmd: &str| {
            let flags = &all.iter().find(|c| c.0 == cmd).unwrap_or_else(|| panic!("no command {cmd}")).1;
            hint_for(Remedy::GiveLabels, &|f| flags.iter().any(|x| x == f)).unwrap()
        };
        let inspect = hint("semlook inspect");
        assert!(inspect.contains("--labels FILE") && !inspect.contains("--labels DIR"), "{inspect}");
        for cmd in ["semlook query", "semlook map build", "semlook map add", "semlook localize"] {
            let h = hint(cmd);
            assert!(h.contains("--labels DIR") && !h.contains("--labels FILE"), "{cmd}: {h}");
        }
    }
}
