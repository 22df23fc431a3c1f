//! The class lists the semantic segmentation protocols evaluate: NYU40 and the ScanNet20
//! benchmark subset, both as NYU40 ids.
//!
//! Following the paper (Table "3D segmentation performance"), the mIoU leaves out the background
//! `unlabeled` (id 0, never a class here) and the unspecific classes `otherstructure` (38),
//! `otherfurniture` (39) and `otherprop` (40): [`ClassList::evaluated`] drops them, so NYU40
//! evaluates 37 classes and ScanNet20 19. Ground-truth points (or pixels) whose label is not an
//! evaluated class are ignored, like unlabelled ones (as RayFronts and the ScanNet benchmark do).
//!
//! Names are the NYU40 names as text queries: `refrigerator` is spelt correctly (the NYU40 table
//! has "refridgerator"), multi-word classes keep their space (`floor mat`, `night stand`).

use std::sync::Arc;

use serde::Serialize;
use vlem_core::LabelNames;

/// The 40 NYU40 classes, ids 1 to 40 in order.
pub const NYU40_NAMES: [&str; 40] = [
    "wall",
    "floor",
    "cabinet",
    "bed",
    "chair",
    "sofa",
    "table",
    "door",
    "window",
    "bookshelf",
    "picture",
    "counter",
    "blinds",
    "desk",
    "shelves",
    "curtain",
    "dresser",
    "pillow",
    "mirror",
    "floor mat",
    "clothes",
    "ceiling",
    "books",
    "refrigerator",
    "television",
    "paper",
    "towel",
    "shower curtain",
    "box",
    "whiteboard",
    "person",
    "night stand",
    "toilet",
    "sink",
    "lamp",
    "bathtub",
    "bag",
    "otherstructure",
    "otherfurniture",
    "otherprop",
];

/// The 20 classes of the ScanNet semantic segmentation benchmark, as NYU40 ids.
pub const SCANNET20_IDS: [u16; 20] = [
    1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 14, 16, 24, 28, 33, 34, 36, 39,
];

/// NYU40 ids of the unspecific `other*` classes, left out of every mIoU.
pub const EXCLUDED_IDS: [u16; 3] = [38, 39, 40];

/// The NYU40 name of `id` (1–40); `None` otherwise.
pub fn nyu40_name(id: u16) -> Option<&'static str> {
    NYU40_NAMES.get(usize::from(id).checked_sub(1)?).copied()
}

/// One class: its NYU40 id (the value in label images) and its name (the text query).
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct Class {
    /// NYU40 id.
    pub id: u16,
    /// Name, used as the text query unless a prompt replaces it.
    pub name: String,
}

/// Which built-in class list to evaluate.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ClassList {
    /// The 40 NYU40 classes (37 evaluated).
    Nyu40,
    /// The 20 ScanNet benchmark classes (19 evaluated).
    Scannet20,
}

impl ClassList {
    /// Parses `nyu40` or `scannet20` (case-insensitive).
    pub fn parse(text: &str) -> Option<Self> {
        match text.to_ascii_lowercase().as_str() {
            "nyu40" => Some(Self::Nyu40),
            "scannet20" => Some(Self::Scannet20),
            _ => None,
        }
    }

    /// The list's name as the CLI and the JSON report write it.
    pub fn label(self) -> &'static str {
        match self {
            Self::Nyu40 => "nyu40",
            Self::Scannet20 => "scannet20",
        }
    }

    /// Every class of the list, the excluded ones included, by ascending id.
    pub fn all(self) -> Vec<Class> {
        let ids: Vec<u16> = match self {
            Self::Nyu40 => (1..=40).collect(),
            Self::Scannet20 => SCANNET20_IDS.to_vec(),
        };
        ids.into_iter()
            .filter_map(|id| {
                nyu40_name(id).map(|name| Class {
                    id,
                    name: name.to_owned(),
                })
            })
            .collect()
    }

    /// The classes the mIoU is computed over: [`ClassList::all`] without [`EXCLUDED_IDS`].
    pub fn evaluated(self) -> Vec<Class> {
        self.all()
            .into_iter()
            .filter(|c| !EXCLUDED_IDS.contains(&c.id))
            .collect()
    }
}

/// Maps label ids to positions in a class slice: `index(id)` is `Some(i)` when `classes[i].id ==
/// id`, `None` for ids that are not evaluated (they are ignored).
#[derive(Clone, Debug)]
pub struct ClassIndex {
    by_id: Vec<Option<usize>>,
}

impl ClassIndex {
    /// The index of `classes`.
    pub fn new(classes: &[Class]) -> Self {
        let max = classes.iter().map(|c| usize::from(c.id)).max().unwrap_or(0);
        let mut by_id = vec![None; max + 1];
        for (i, c) in classes.iter().enumerate() {
            by_id[usize::from(c.id)] = Some(i);
        }
        Self { by_id }
    }

    /// The position of class `id`, `None` when it is not evaluated (or is 0, unlabelled).
    #[inline]
    pub fn index(&self, id: u16) -> Option<usize> {
        if id == 0 {
            return None;
        }
        self.by_id.get(usize::from(id)).copied().flatten()
    }
}

/// A class name reduced for matching: lower case, letters and digits only (`Night Stand` and
/// `nightstand` match), with NYU40's own misspelling `refridgerator` corrected.
fn normalise_name(name: &str) -> String {
    let s: String = name
        .chars()
        .filter(char::is_ascii_alphanumeric)
        .map(|c| c.to_ascii_lowercase())
        .collect();
    if s == "refridgerator" {
        "refrigerator".into()
    } else {
        s
    }
}

/// Maps a dataset's label ids to NYU40 ids by class name, so that datasets whose `labels.json`
/// numbers classes differently still evaluate against NYU40. Ids without a name, and names that
/// are no NYU40 class, map to 0 (ignored, like unlabelled pixels).
#[derive(Clone, Debug)]
pub struct LabelRemap {
    table: Vec<u16>,
    /// Named dataset classes that are no NYU40 class (`(id, name)`), ignored.
    pub unknown: Vec<(u16, String)>,
    names: Arc<LabelNames>,
}

impl LabelRemap {
    /// The remapping of a dataset's class table.
    pub fn new(names: &Arc<LabelNames>) -> Self {
        let nyu: Vec<String> = NYU40_NAMES.iter().map(|n| normalise_name(n)).collect();
        let max = names
            .iter()
            .map(|(id, _)| usize::from(id))
            .max()
            .unwrap_or(0);
        let mut table = vec![0u16; max + 1];
        let mut unknown = Vec::new();
        for (id, name) in names.iter() {
            let key = normalise_name(name);
            match nyu.iter().position(|n| *n == key) {
                Some(i) => table[usize::from(id)] = (i + 1) as u16,
                None if matches!(key.as_str(), "unlabelled" | "unlabeled" | "void" | "") => {}
                None => unknown.push((id, name.to_owned())),
            }
        }
        Self {
            table,
            unknown,
            names: Arc::clone(names),
        }
    }

    /// Whether this remapping was made for `names` (the same shared table).
    pub fn is_for(&self, names: &Arc<LabelNames>) -> bool {
        Arc::ptr_eq(&self.names, names)
    }

    /// The NYU40 id of dataset id `id` (0 for unnamed and unknown classes).
    #[inline]
    pub fn map(&self, id: u16) -> u16 {
        self.table.get(usize::from(id)).copied().unwrap_or(0)
    }

    /// [`LabelRemap::map`] over a label image.
    pub fn apply(&self, ids: &[u16]) -> Vec<u16> {
        ids.iter().map(|&id| self.map(id)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dataset_labels_map_to_nyu40_by_name() {
        let names = Arc::new(LabelNames::new([
            (1, "wall".to_owned()),
            (5, "Night Stand".to_owned()),
            (6, "refridgerator".to_owned()),
            (7, "spaceship".to_owned()),
            (9, "unlabelled".to_owned()),
        ]));
        let remap = LabelRemap::new(&names);
        assert_eq!(
            remap.apply(&[0, 1, 5, 6, 7, 8, 9, 300]),
            vec![0, 1, 32, 24, 0, 0, 0, 0]
        );
        assert_eq!(remap.unknown, vec![(7, "spaceship".to_owned())]);
        assert!(remap.is_for(&names));
        assert!(!remap.is_for(&Arc::new(LabelNames::new([]))));
    }

    #[test]
    fn nyu40_has_forty_ids_and_evaluates_thirty_seven() {
        let all = ClassList::Nyu40.all();
        assert_eq!(all.len(), 40);
        assert_eq!(all[0].name, "wall");
        assert_eq!(all[39].name, "otherprop");
        assert_eq!(nyu40_name(24), Some("refrigerator"));
        assert_eq!(nyu40_name(32), Some("night stand"));
        assert_eq!(nyu40_name(0), None);
        assert_eq!(nyu40_name(41), None);
        let evaluated = ClassList::Nyu40.evaluated();
        assert_eq!(evaluated.len(), 37);
        assert!(evaluated.iter().all(|c| !c.name.starts_with("other")));
        assert_eq!(evaluated.last().map(|c| c.id), Some(37));
    }

    #[test]
    fn scannet20_is_the_benchmark_subset() {
        let all = ClassList::Scannet20.all();
        assert_eq!(all.len(), 20);
        let names: Vec<&str> = all.iter().map(|c| c.name.as_str()).collect();
        for expected in [
            "wall",
            "floor",
            "counter",
            "desk",
            "curtain",
            "refrigerator",
            "shower curtain",
            "toilet",
            "sink",
            "bathtub",
            "otherfurniture",
        ] {
            assert!(
                names.contains(&expected),
                "{expected} missing from {names:?}"
            );
        }
        for absent in ["pillow", "lamp", "ceiling", "blinds"] {
            assert!(
                !names.contains(&absent),
                "{absent} is not a ScanNet20 class"
            );
        }
        let evaluated = ClassList::Scannet20.evaluated();
        assert_eq!(evaluated.len(), 19);
        assert!(evaluated.iter().all(|c| c.id != 39));
    }

    #[test]
    fn class_lists_parse_and_index() {
        assert_eq!(ClassList::parse("NYU40"), Some(ClassList::Nyu40));
        assert_eq!(ClassList::parse("scannet20"), Some(ClassList::Scannet20));
        assert_eq!(ClassList::parse("coco"), None);
        let classes = ClassList::Scannet20.evaluated();
        let index = ClassIndex::new(&classes);
        assert_eq!(index.index(1), Some(0));
        assert_eq!(index.index(14), Some(12));
        assert_eq!(index.index(13), None);
        assert_eq!(index.index(0), None);
        assert_eq!(index.index(39), None);
        assert_eq!(index.index(1000), None);
    }
}
