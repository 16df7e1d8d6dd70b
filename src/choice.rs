//! Closed sets of named values that the front ends offer by name: the matching settings, the
//! backends, the label-file formats. Each has one list, one name per value
//! and one line of help ([`Choice`]); the command line builds its parsers and its help from them,
//! Python and the ROS node parse the same names, so no front end's derive sits on these types.

/// A closed set of values named for the front ends.
pub trait Choice: Copy + PartialEq + Send + Sync + 'static {
    /// Every value, in the order the front ends list them.
    const CHOICES: &'static [Self];
    /// The value's one name: the command line's and Python's, and serde's (JSON, the config) but
    /// for the label formats, whose config spelling is snake case (`first_channel`).
    fn name(self) -> &'static str;
    /// One line that says what the value does (the command line's help lists it).
    fn help(self) -> &'static str;
    /// The value named `name`, if any.
    fn named(name: &str) -> Option<Self> {
        Self::CHOICES.iter().copied().find(|c| c.name() == name)
    }
    /// The value named `name`, or why there is none (`"x" is not one of a, b, c`).
    fn parse_name(name: &str) -> Result<Self, String> {
        Self::named(name).ok_or_else(|| format!("{name:?} is not one of {}", Self::CHOICES.iter().map(|c| c.name()).collect::<Vec<_>>().join(", ")))
    }
}

impl Choice for crate::matching::Setting {
    const CHOICES: &'static [Self] = &crate::matching::Setting::ALL;
    fn name(self) -> &'static str {
        crate::matching::Setting::name(self)
    }
    fn help(self) -> &'static str {
        use crate::matching::Setting::*;
        match self {
            Hog => "Baseline: VPR-Bench's HOG (grey 512 x 512, cosine), the floor any VPR method must beat",
            Appearance => "Baseline: the VLAD of all the image's appearance descriptors with the map's codebook (cosine)",
            Global => "Coarse stage only: rank by SSIM of the global descriptors (\"Edge (Coarse)\")",
            Forest => "method.md §6.1 (1): Forest descriptors only, against the whole map, no appearance",
            Local => "method.md §6.1 (2): SemLook local descriptors (Forest + appearance), against the whole map",
            GlobalForest => "method.md §6.1 (3): global descriptor selects K candidates, Forest re-ranks them (`matching.coarse`: the edge descriptor alone, or fused with the whole-image appearance)",
            Semlook => "method.md §6.1 (4): the full method: global top-K, SemLook local re-ranking (`matching.coarse` as for setting 3)",
            Fused => "Beyond the paper, coarse stage only: rank by cos(whole-image appearance) + w_embedding x cos(whole-image embeddings) + w_global x SSIM of the global descriptors (`matching.w_embedding`, `matching.w_global`)",
            Verified => "Beyond the paper, the recommended pipeline: the fused coarse top-K, re-ranked by SemLook local similarity and geometric verification (`verification`)",
        }
    }
}

impl Choice for crate::engine::Backend {
    const CHOICES: &'static [Self] = &crate::engine::Backend::ALL;
    fn name(self) -> &'static str {
        crate::engine::Backend::name(self)
    }
    fn help(self) -> &'static str {
        use crate::engine::Backend::*;
        match self {
            Cpu => "The CPU reference path (all cores, through rayon)",
            Gpu => "The WGSL kernels on a GPU adapter (a software one too); fails if there is none",
            Auto => "A hardware GPU if there is one, else the CPU (with a warning)",
        }
    }
}

impl Choice for crate::input::LabelFormat {
    const CHOICES: &'static [Self] = &[crate::input::LabelFormat::Auto, crate::input::LabelFormat::FirstChannel, crate::input::LabelFormat::Palette];
    fn name(self) -> &'static str {
        use crate::input::LabelFormat::*;
        match self {
            Auto => "auto",
            FirstChannel => "first-channel",
            Palette => "palette",
        }
    }
    fn help(self) -> &'static str {
        use crate::input::LabelFormat::*;
        match self {
            Auto => "Grey (8 or 16 bit) files hold ids; colour files use the class palette",
            FirstChannel => "The first channel holds the id, whatever the colour type (SYNTHIA's GT/LABELS)",
            Palette => "Colour files in the class palette (Cityscapes `*_color.png`)",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::Choice;
    use crate::engine::Backend;
    use crate::input::LabelFormat;
    use crate::matching::Setting;

    /// Each value is listed once, with a name of its own that names it back.
    fn one_name_each<T: Choice + std::fmt::Debug>() {
        for (i, &c) in T::CHOICES.iter().enumerate() {
            assert_eq!(T::named(c.name()), Some(c));
            assert!(T::CHOICES[..i].iter().all(|&d| d != c && d.name() != c.name()), "{c:?} listed twice");
            assert!(!c.help().is_empty());
        }
        let err = T::parse_name("nothing-of-the-kind").unwrap_err();
        assert!(T::CHOICES.iter().all(|c| err.contains(c.name())), "{err}");
    }
    /// ... and that name is serde's (JSON, TOML, the map's files), so a name read back is the value written.
    fn serde_names<T: Choice + std::fmt::Debug + serde::Serialize + serde::de::DeserializeOwned>() {
        one_name_each::<T>();
        for &c in T::CHOICES {
            assert_eq!(serde_json::to_string(&c).ok(), Some(format!("\"{}\"", c.name())), "{c:?}");
            assert_eq!(serde_json::from_str::<T>(&format!("\"{}\"", c.name())).ok(), Some(c), "{c:?}");
        }
    }

    #[test]
    fn every_choice_has_one_name_which_serde_reads_and_writes() {
        serde_names::<Setting>();
        serde_names::<Backend>();
        one_name_each::<crate::batch::IndexPolicy>();
        // the config file's `label_format` is snake case (`first_channel`), the command line's kebab
        one_name_each::<LabelFormat>();
        assert_eq!(Setting::CHOICES.len(), 9);
        assert_eq!(<LabelFormat as Choice>::CHOICES.len(), 3);
    }
}
