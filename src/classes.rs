//! Semantic class tables: which classes exist, their palette colours, which are dynamic, and how
//! the ids found in label-map files translate into class indices.
//!
//! The default is the 19-class Cityscapes "train id" table (Cordts et al., CVPR 2016), which the
//! SemLook paper's segmenter (refs 31-32 of the paper) outputs. Class indices are `u8`; [`VOID`]
//! marks pixels that belong to no class (Cityscapes' ignore label 255).

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};

/// The `[classes]` section: the class table, how label-file ids map to it, and the classes left out.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ClassesConfig {
    /// "cityscapes" (19 train ids) or an inline list of `{ name, color, dynamic }`.
    pub table: TableSpec,
    /// How ids in single-channel label PNGs map to classes: "train_id" (id = table index),
    /// "cityscapes_label_id", "synthia", or a list of `[id, "class name" | "void"]` pairs.
    pub label_ids: LabelIds,
    /// File ids that mean "no class" (Cityscapes' ignore label is 255).
    pub void_ids: Vec<u32>,
    /// Class names left out of objects and edges, e.g. the dynamic classes
    /// ["person", "rider", "car", "truck", "bus", "train", "motorcycle", "bicycle"]. \[R\] default: none.
    pub exclude: Vec<String>,
}

impl Default for ClassesConfig {
    fn default() -> Self {
        ClassesConfig {
            table: TableSpec::Builtin("cityscapes".into()),
            label_ids: LabelIds::Named("train_id".into()),
            void_ids: vec![255],
            exclude: vec![],
        }
    }
}

/// Which class table (`classes.table`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum TableSpec {
    /// A built-in table by name: "cityscapes" ([`CITYSCAPES`]) or "camvid" ([`CAMVID`]).
    Builtin(String),
    /// An inline table, one entry per class, in class index order.
    Custom(Vec<ClassSpec>),
}

/// One class of an inline class table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClassSpec {
    /// The class name ("void" is reserved for pixels of no class).
    pub name: String,
    /// The palette colour of the class in colour label maps, RGB; unique within the table.
    pub color: [u8; 3],
    /// Whether the class is dynamic (it moves: people, vehicles); default false.
    #[serde(default)]
    pub dynamic: bool,
    /// The class's category (`similarity.class_match`); default: the built-in category of its
    /// name (`classes::category_of`), else its own name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub category: Option<String>,
}

/// How the ids of single-channel label maps translate into classes (`classes.label_ids`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum LabelIds {
    /// A built-in mapping: "train_id" (id = class index), "cityscapes_label_id" or "synthia"
    /// (both need the cityscapes table), or "camvid" (needs the camvid table; 11 is void).
    Named(String),
    /// `(id, class name)` pairs; the name "void" marks an id of no class. Ids up to 65535.
    Custom(Vec<(u32, String)>),
}
use std::collections::HashMap;

/// Class index of a pixel that belongs to no class (ignored everywhere).
pub const VOID: u8 = 255;
/// Marker in the id look-up table for ids the table does not know (an input error).
const UNKNOWN: u8 = 254;
/// Most classes a table may hold: indices 254 and 255 are markers.
pub const MAX_CLASSES: usize = 254;

/// (name, palette colour, dynamic) of the Cityscapes train ids 0..18.
pub const CITYSCAPES: [(&str, [u8; 3], bool); 19] = [
    ("road", [128, 64, 128], false),
    ("sidewalk", [244, 35, 232], false),
    ("building", [70, 70, 70], false),
    ("wall", [102, 102, 156], false),
    ("fence", [190, 153, 153], false),
    ("pole", [153, 153, 153], false),
    ("traffic light", [250, 170, 30], false),
    ("traffic sign", [220, 220, 0], false),
    ("vegetation", [107, 142, 35], false),
    ("terrain", [152, 251, 152], false),
    ("sky", [70, 130, 180], false),
    ("person", [220, 20, 60], true),
    ("rider", [255, 0, 0], true),
    ("car", [0, 0, 142], true),
    ("truck", [0, 0, 70], true),
    ("bus", [0, 60, 100], true),
    ("train", [0, 80, 100], true),
    ("motorcycle", [0, 0, 230], true),
    ("bicycle", [119, 11, 32], true),
];

/// The category of a built-in class name: Cityscapes' own grouping of its classes
/// (cityscapesScripts `labels.py`: flat, construction, object, nature, sky, human, vehicle), and
/// the CamVid classes placed in it. An off-domain segmenter swaps classes within a category far
/// more often than across (road / sidewalk, building / wall, vegetation / terrain, car / truck).
pub fn category_of(name: &str) -> Option<&'static str> {
    Some(match name {
        "road" | "sidewalk" | "Road" | "Pavement" => "flat",
        "building" | "wall" | "fence" | "Building" | "Fence" => "construction",
        "pole" | "traffic light" | "traffic sign" | "Pole" | "SignSymbol" => "object",
        "vegetation" | "terrain" | "Tree" => "nature",
        "sky" | "Sky" => "sky",
        "person" | "rider" | "Pedestrian" | "Bicyclist" => "human",
        "car" | "truck" | "bus" | "train" | "motorcycle" | "bicycle" | "Car" => "vehicle",
        _ => return None,
    })
}

/// (name, palette colour, dynamic) of the 11 CamVid classes in the SegNet convention (label
/// values 0..10; 11 is "Unlabelled"), colours from the SegNet tutorial's palette.
pub const CAMVID: [(&str, [u8; 3], bool); 11] = [
    ("Sky", [128, 128, 128], false),
    ("Building", [128, 0, 0], false),
    ("Pole", [192, 192, 128], false),
    ("Road", [128, 64, 128], false),
    ("Pavement", [60, 40, 222], false),
    ("Tree", [128, 128, 0], false),
    ("SignSymbol", [192, 128, 128], false),
    ("Fence", [64, 64, 128], false),
    ("Car", [64, 0, 128], true),
    ("Pedestrian", [64, 64, 0], true),
    ("Bicyclist", [0, 128, 192], true),
];

/// The CamVid label value of unlabelled pixels.
pub const CAMVID_VOID_ID: u32 = 11;

/// The CamVid class of each output channel of a Cityscapes segmenter (19 train ids, then the
/// background channel): road->Road, sidewalk->Pavement, building+wall->Building, fence->Fence,
/// pole->Pole, traffic light+sign->SignSymbol, vegetation+terrain->Tree, sky->Sky,
/// person->Pedestrian, rider+motorcycle+bicycle->Bicyclist, car+truck+bus+train->Car (the mapping
/// `../shared/models/README.md` evaluates the segmenters with).
pub const CITYSCAPES_TO_CAMVID: [&str; 20] = [
    "Road",
    "Pavement",
    "Building",
    "Building",
    "Fence",
    "Pole",
    "SignSymbol",
    "SignSymbol",
    "Tree",
    "Tree",
    "Sky",
    "Pedestrian",
    "Bicyclist",
    "Car",
    "Car",
    "Car",
    "Car",
    "Bicyclist",
    "Bicyclist",
    "void",
];

/// Colours of Cityscapes' void categories in `*_color.png` files (unlabeled, dynamic, ground,
/// parking, rail track, guard rail, bridge, tunnel, caravan, trailer).
const CITYSCAPES_VOID_COLORS: [[u8; 3]; 10] = [
    [0, 0, 0],
    [111, 74, 0],
    [81, 0, 81],
    [250, 170, 160],
    [230, 150, 140],
    [180, 165, 180],
    [150, 100, 100],
    [150, 120, 90],
    [0, 0, 90],
    [0, 0, 110],
];

/// Cityscapes full label ids 0..33 to train ids (255 = ignore), from cityscapesScripts' labels.py.
const CITYSCAPES_LABEL_TO_TRAIN: [u8; 34] =
    [255, 255, 255, 255, 255, 255, 255, 0, 1, 255, 255, 2, 3, 4, 255, 255, 255, 5, 255, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 255, 255, 16, 17, 18];

/// SYNTHIA class ids 0..15 (void, sky, building, road, sidewalk, fence, vegetation, pole, car,
/// traffic sign, pedestrian, bicycle, lanemarking, reserved, reserved, traffic light) to
/// Cityscapes train ids; lane markings count as road.
const SYNTHIA_TO_TRAIN: [u8; 16] = [255, 10, 2, 0, 1, 4, 8, 5, 13, 7, 11, 18, 0, 255, 255, 6];

/// A resolved class table.
#[derive(Debug, Clone)]
pub struct ClassTable {
    names: Vec<String>,
    colors: Vec<[u8; 3]>,
    dynamic: Vec<bool>,
    excluded: Vec<bool>,
    /// file id -> class index, VOID, or UNKNOWN; covers 16-bit ids.
    id_lut: Vec<u8>,
    /// Category index of each class (see [`category_of`]).
    categories: Vec<u8>,
    color_lut: HashMap<[u8; 3], u8>,
}

impl ClassTable {
    /// Builds the table a config describes; names in `exclude` must exist.
    pub fn from_config(cfg: &ClassesConfig) -> Result<Self> {
        let bad = |reason: String| Error::InvalidConfig { source_name: "[classes]".into(), reason };
        let specs: Vec<ClassSpec> = match &cfg.table {
            TableSpec::Builtin(name) if name == "cityscapes" => {
                CITYSCAPES.iter().map(|(n, c, d)| ClassSpec { name: n.to_string(), color: *c, dynamic: *d, category: None }).collect()
            }
            TableSpec::Builtin(name) if name == "camvid" => {
                CAMVID.iter().map(|(n, c, d)| ClassSpec { name: n.to_string(), color: *c, dynamic: *d, category: None }).collect()
            }
            TableSpec::Builtin(name) => return Err(bad(format!("unknown class table {name:?} (built in: \"cityscapes\", \"camvid\")"))),
            TableSpec::Custom(list) => list.clone(),
        };
        if specs.is_empty() || specs.len() > MAX_CLASSES {
            return Err(bad(format!("class table must hold 1..={MAX_CLASSES} classes, has {}", specs.len())));
        }
        let names: Vec<String> = specs.iter().map(|s| s.name.clone()).collect();
        let index_of = |name: &str| -> Result<u8> {
            if name == "void" {
                return Ok(VOID);
            }
            names.iter().position(|n| n == name).map(|i| i as u8).ok_or_else(|| bad(format!("class {name:?} is not in the class table")))
        };
        let mut excluded = vec![false; names.len()];
        for name in &cfg.exclude {
            let i = index_of(name)?;
            if i == VOID {
                return Err(bad("\"void\" cannot be excluded: it is never used".into()));
            }
            excluded[i as usize] = true;
        }
        let mut id_lut = vec![UNKNOWN; 1 << 16];
        match &cfg.label_ids {
            LabelIds::Named(n) if n == "train_id" => {
                for i in 0..names.len() {
                    id_lut[i] = i as u8;
                }
            }
            LabelIds::Named(n) if n == "cityscapes_label_id" || n == "synthia" => {
                if !is_cityscapes(&specs) {
                    return Err(bad(format!("label_ids = {n:?} needs the cityscapes class table")));
                }
                let table: &[u8] = if n == "synthia" { &SYNTHIA_TO_TRAIN } else { &CITYSCAPES_LABEL_TO_TRAIN };
                id_lut[..table.len()].copy_from_slice(table);
            }
            LabelIds::Named(n) if n == "camvid" => {
                if !(specs.len() == CAMVID.len() && specs.iter().zip(CAMVID.iter()).all(|(s, c)| s.name == c.0)) {
                    return Err(bad("label_ids = \"camvid\" needs the camvid class table".into()));
                }
                for i in 0..CAMVID.len() {
                    id_lut[i] = i as u8;
                }
                id_lut[CAMVID_VOID_ID as usize] = VOID;
            }
            LabelIds::Named(n) => {
                return Err(bad(format!(
                    "unknown label_ids {n:?} (train_id, cityscapes_label_id, synthia, camvid, or a list of [id, \"class\"] pairs)"
                )))
            }
            LabelIds::Custom(pairs) => {
                for (id, name) in pairs {
                    let slot = id_lut.get_mut(*id as usize).ok_or_else(|| bad(format!("label id {id} is above 65535")))?;
                    *slot = index_of(name)?;
                }
            }
        }
        for &v in &cfg.void_ids {
            let slot = id_lut.get_mut(v as usize).ok_or_else(|| bad(format!("void id {v} is above 65535")))?;
            *slot = VOID;
        }
        let mut color_lut = HashMap::new();
        if is_cityscapes(&specs) {
            for c in CITYSCAPES_VOID_COLORS {
                color_lut.insert(c, VOID);
            }
        }
        for (i, s) in specs.iter().enumerate() {
            if let Some(prev) = color_lut.insert(s.color, i as u8) {
                if prev != VOID {
                    return Err(bad(format!("classes {:?} and {:?} share colour {:?}", names[prev as usize], s.name, s.color)));
                }
            }
        }
        // categories: given, else the known one of the class's name, else the class's own name
        let category_names: Vec<String> =
            specs.iter().map(|s| s.category.clone().unwrap_or_else(|| category_of(&s.name).unwrap_or(&s.name).to_string())).collect();
        let mut distinct: Vec<&String> = Vec::new();
        let categories = category_names
            .iter()
            .map(|c| match distinct.iter().position(|d| *d == c) {
                Some(i) => i as u8,
                None => {
                    distinct.push(c);
                    (distinct.len() - 1) as u8
                }
            })
            .collect();
        Ok(ClassTable {
            categories,
            colors: specs.iter().map(|s| s.color).collect(),
            dynamic: specs.iter().map(|s| s.dynamic).collect(),
            names,
            excluded,
            id_lut,
            color_lut,
        })
    }

    /// The default Cityscapes train-id table with nothing excluded.
    pub fn cityscapes() -> Self {
        Self::from_config(&ClassesConfig::default()).expect("built-in table is valid")
    }

    /// The number of classes (1 to [`MAX_CLASSES`]).
    pub fn len(&self) -> usize {
        self.names.len()
    }
    /// Whether the table holds no class (never, for a table built by [`ClassTable::from_config`]).
    pub fn is_empty(&self) -> bool {
        self.names.is_empty()
    }
    /// The name of a class index; "void" for [`VOID`]. Panics on an index the table does not hold.
    pub fn name(&self, class: u8) -> &str {
        if class == VOID {
            "void"
        } else {
            &self.names[class as usize]
        }
    }
    /// Per class index, its category index (VOID keeps VOID; other indices map to themselves).
    pub fn category_key(&self) -> [u8; 256] {
        let mut key: [u8; 256] = std::array::from_fn(|i| i as u8);
        for (i, &c) in self.categories.iter().enumerate() {
            key[i] = c;
        }
        key
    }
    /// The class index of a class name, if the table holds it ("void" is not a class).
    pub fn index(&self, name: &str) -> Option<u8> {
        self.names.iter().position(|n| n == name).map(|i| i as u8)
    }
    /// Per class index 0..=255: whether `names` lists it; a name the table does not have is an
    /// error naming it and the config key `key` it came from.
    pub fn mask(&self, key: &str, names: &[String]) -> Result<[bool; 256]> {
        let mut mask = [false; 256];
        for name in names {
            let c = self.index(name).ok_or_else(|| Error::InvalidConfig {
                source_name: format!("[{}]", key.split('.').next().unwrap_or(key)),
                reason: format!("{key}: {name:?} is not a class of the table (classes.table)"),
            })?;
            mask[c as usize] = true;
        }
        Ok(mask)
    }
    /// The palette colour of a class index, RGB; black for [`VOID`]. Panics on an index the table
    /// does not hold.
    pub fn color(&self, class: u8) -> [u8; 3] {
        if class == VOID {
            [0, 0, 0]
        } else {
            self.colors[class as usize]
        }
    }
    /// Whether a class index is a dynamic class (false for [`VOID`]). Panics on an index the table
    /// does not hold.
    pub fn is_dynamic(&self, class: u8) -> bool {
        class != VOID && self.dynamic[class as usize]
    }
    /// Whether pixels of `class` take part in objects and edges (not void, not excluded).
    pub fn is_used(&self, class: u8) -> bool {
        class != VOID && !self.excluded[class as usize]
    }
    /// Per class index 0..=255: whether the class takes part (VOID and excluded: false).
    pub fn used_mask(&self) -> [bool; 256] {
        let mut m = [false; 256];
        for (c, slot) in m.iter_mut().enumerate().take(self.len()) {
            *slot = !self.excluded[c];
        }
        m
    }
    /// Class index of a file id: `Some(VOID)` for void ids, `None` for unknown ids.
    pub fn class_of_id(&self, id: u32) -> Option<u8> {
        match self.id_lut.get(id as usize).copied() {
            Some(UNKNOWN) | None => None,
            c => c,
        }
    }
    /// Class index of a palette colour: `Some(VOID)` for void colours, `None` for unknown ones.
    pub fn class_of_color(&self, rgb: [u8; 3]) -> Option<u8> {
        self.color_lut.get(&rgb).copied()
    }
}

fn is_cityscapes(specs: &[ClassSpec]) -> bool {
    specs.len() == CITYSCAPES.len() && specs.iter().zip(CITYSCAPES.iter()).all(|(s, c)| s.name == c.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cityscapes_ids_colours_and_void() {
        let t = ClassTable::cityscapes();
        assert_eq!(t.len(), 19);
        assert_eq!(t.class_of_id(13), Some(13));
        assert_eq!(t.class_of_id(255), Some(VOID));
        assert_eq!(t.class_of_id(19), None);
        assert_eq!(t.class_of_color([0, 0, 142]), Some(13));
        assert_eq!(t.class_of_color([0, 0, 0]), Some(VOID));
        assert_eq!(t.class_of_color([1, 2, 3]), None);
    }

    #[test]
    fn camvid_table_and_ids() {
        let cfg = ClassesConfig {
            table: TableSpec::Builtin("camvid".into()),
            label_ids: LabelIds::Named("camvid".into()),
            void_ids: vec![],
            exclude: vec![],
        };
        let t = ClassTable::from_config(&cfg).unwrap();
        assert_eq!((t.len(), t.name(3), t.class_of_id(8), t.class_of_id(11), t.class_of_id(12)), (11, "Road", Some(8), Some(VOID), None));
        assert!(t.is_dynamic(8) && !t.is_dynamic(5));
        // every Cityscapes channel maps to a CamVid class
        assert!(CITYSCAPES_TO_CAMVID.iter().all(|n| *n == "void" || t.index(n).is_some()));
        let wrong = ClassesConfig { label_ids: LabelIds::Named("camvid".into()), ..Default::default() };
        assert!(ClassTable::from_config(&wrong).is_err());
    }

    #[test]
    fn remaps_and_exclusions() {
        let mut cfg = ClassesConfig { label_ids: LabelIds::Named("cityscapes_label_id".into()), ..Default::default() };
        cfg.exclude = vec!["car".into(), "sky".into()];
        let t = ClassTable::from_config(&cfg).unwrap();
        assert_eq!(t.class_of_id(7), Some(0)); // road
        assert_eq!(t.class_of_id(26), Some(13)); // car
        assert_eq!(t.class_of_id(0), Some(VOID));
        assert!(!t.is_used(13) && !t.is_used(10) && t.is_used(0) && !t.is_used(VOID));
        cfg.exclude = vec!["spaceship".into()];
        assert!(ClassTable::from_config(&cfg).is_err());
        let synthia = ClassesConfig { label_ids: LabelIds::Named("synthia".into()), ..Default::default() };
        let t = ClassTable::from_config(&synthia).unwrap();
        assert_eq!(t.class_of_id(3), Some(0));
        assert_eq!(t.class_of_id(10), Some(11));
        assert_eq!(t.class_of_id(16), None);
    }
}
