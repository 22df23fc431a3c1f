//! The plugin registry: stage names in the TOML config → trait objects.
//!
//! Every implementation registers itself with one of the `register_*!` macros, which put a
//! [`Registration`] into an [`inventory`] collection at link time. [`Registry::global`] gathers them
//! once into sorted maps, refusing duplicate names. Lookups of an unknown name list the known names
//! and, when a [`FeatureHint`] says so, the cargo feature that would compile the missing one in.
//!
//! Datasets are a stage like the others: each reader registers with [`register_dataset!`] a
//! [`DatasetReader`] (how to open it, and the probe that recognises its folders for
//! `kind = "auto"`); `vlem_datasets::open` picks one.
//!
//! A plugin crate that is a dependency but never referenced is not linked, and its registrations
//! vanish silently: binaries reference every plugin crate they depend on (see `src/plugins.rs` of the
//! `vlem` binary), and a test there checks the expected names.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use serde::de::DeserializeOwned;

use crate::config::{Config, DatasetConfig, StageConfig, config_folder};
use crate::error::{CoreError, Result};
use crate::stage::StageKind;
use crate::traits::embedding_map::EmbeddingMap;
use crate::traits::encoder::Encoder;
use crate::traits::frame_source::FrameSource;
use crate::traits::region_proposer::RegionProposer;
use crate::traits::segmenter::Segmenter;
use crate::traits::tracker::Tracker;

/// What the build step of an implementation may use besides its own parameters. It never holds a
/// network client: weights are read from paths the config names.
#[derive(Clone, Debug, Default)]
pub struct BuildContext {
    /// Directory of the config file; relative paths in parameters are resolved against it.
    pub config_dir: PathBuf,
    /// The encoder's embedding dimension, once the encoder is built (maps read it).
    pub embedding_dim: Option<usize>,
}

impl BuildContext {
    /// The context of a config in `config_dir`, made absolute so relative paths resolve from any
    /// working directory.
    ///
    /// # Errors
    /// [`CoreError::Io`] when the folder does not exist.
    pub fn for_config_dir(config_dir: &std::path::Path) -> Result<Self> {
        let config_dir = config_dir
            .canonicalize()
            .map_err(|e| CoreError::io(config_dir, e))?;
        Ok(Self {
            config_dir,
            embedding_dim: None,
        })
    }

    /// Resolves a path from a config parameter against the config's directory.
    pub fn resolve(&self, path: &std::path::Path) -> PathBuf {
        if path.is_absolute() {
            path.to_path_buf()
        } else {
            self.config_dir.join(path)
        }
    }
}

/// Reads a config file and the build context its relative paths resolve against (its folder,
/// made absolute so the paths resolve from anywhere): what every front-end needs to build a
/// pipeline from a file.
///
/// # Errors
/// As [`Config::from_file`], and [`CoreError::Io`] when the folder cannot be made absolute.
pub fn load_config(path: &std::path::Path) -> Result<(Config, BuildContext)> {
    let config = Config::from_file(path)?;
    let ctx = BuildContext::for_config_dir(config_folder(path))?;
    Ok((config, ctx))
}

/// Signature of a build function: the stage's parameters (its config section without `kind`).
pub type BuildFn<T> = fn(&toml::Table, &BuildContext) -> Result<Box<T>>;

/// Opens a dataset: the `[dataset]` settings, and the path they resolve to (a folder, or for
/// readers that take one a single file; readers that need none, such as a generated scene, ignore
/// it).
pub type OpenDatasetFn = fn(&DatasetConfig, &Path) -> Result<Box<dyn FrameSource>>;

/// How `kind = "auto"` recognises a reader's datasets.
#[derive(Clone, Copy, Debug)]
pub struct DatasetProbe {
    /// Whether `path` holds this reader's layout; cheap (file names, not contents).
    pub probe: fn(&Path) -> bool,
    /// Probes run in ascending order, the first match wins: a more specific layout comes before a
    /// looser one that would also match it.
    pub order: u16,
    /// What the probe looks for, for the error that lists them when none matches, e.g.
    /// `"rgb.txt and depth.txt (TUM RGB-D)"`.
    pub looks_for: &'static str,
}

/// A registered dataset reader: how it is opened and found.
#[derive(Clone, Copy, Debug)]
pub struct DatasetReader {
    /// Opens it.
    pub open: OpenDatasetFn,
    /// How `kind = "auto"` recognises it; `None`: only by name.
    pub detect: Option<DatasetProbe>,
    /// Whether it reads a path (false for a scene generated from its settings alone).
    pub needs_path: bool,
    /// Parses the reader's own `[dataset]` keys without opening anything, so that a typo is found
    /// before a long job starts (a study's cells); `None`: they are checked when it opens.
    pub check_settings: Option<fn(&DatasetConfig) -> Result<()>>,
    /// The trajectory file of one of its folders, found as the reader finds it (for
    /// `vlem eval trajectory --reference DIR`); `None` for layouts without one such file.
    pub trajectory_file: Option<fn(&Path) -> Result<PathBuf>>,
}

impl DatasetReader {
    /// A reader of a path, opened by `open`, found only by name.
    pub const fn new(open: OpenDatasetFn) -> Self {
        Self {
            open,
            detect: None,
            needs_path: true,
            check_settings: None,
            trajectory_file: None,
        }
    }

    /// With the function that checks its own `[dataset]` keys.
    pub const fn with_settings_check(mut self, check: fn(&DatasetConfig) -> Result<()>) -> Self {
        self.check_settings = Some(check);
        self
    }

    /// Found by `kind = "auto"` where `probe` says so, in `order` (see [`DatasetProbe`]).
    pub const fn detected_by(
        mut self,
        order: u16,
        looks_for: &'static str,
        probe: fn(&Path) -> bool,
    ) -> Self {
        self.detect = Some(DatasetProbe {
            probe,
            order,
            looks_for,
        });
        self
    }

    /// A reader that reads no path.
    pub const fn without_path(mut self) -> Self {
        self.needs_path = false;
        self
    }

    /// With the function that finds a folder's trajectory file.
    pub const fn with_trajectory_file(mut self, find: fn(&Path) -> Result<PathBuf>) -> Self {
        self.trajectory_file = Some(find);
        self
    }
}

/// The constructor of one registered implementation.
#[derive(Clone, Copy)]
pub enum Builder {
    /// Opens a dataset ([`FrameSource`]).
    Dataset(DatasetReader),
    /// Builds a [`Tracker`].
    Tracker(BuildFn<dyn Tracker>),
    /// Builds a [`RegionProposer`].
    Proposer(BuildFn<dyn RegionProposer>),
    /// Builds an [`Encoder`].
    Encoder(BuildFn<dyn Encoder>),
    /// Builds an [`EmbeddingMap`].
    Map(BuildFn<dyn EmbeddingMap>),
    /// Builds a [`Segmenter`].
    Segmenter(BuildFn<dyn Segmenter>),
}

impl Builder {
    /// The stage this builder makes.
    pub fn kind(&self) -> StageKind {
        match self {
            Builder::Dataset(_) => StageKind::Dataset,
            Builder::Tracker(_) => StageKind::Tracker,
            Builder::Proposer(_) => StageKind::Proposer,
            Builder::Encoder(_) => StageKind::Encoder,
            Builder::Map(_) => StageKind::Map,
            Builder::Segmenter(_) => StageKind::Segmenter,
        }
    }
}

/// One implementation, as submitted by a `register_*!` macro.
pub struct Registration {
    /// The name used as `kind = "..."` in the config.
    pub name: &'static str,
    /// One line for `vlem plugins`.
    pub description: &'static str,
    /// The constructor.
    pub builder: Builder,
}

inventory::collect!(Registration);

/// "`name` of `kind` is provided by cargo feature `feature`": lets the registry tell a user how to
/// get an implementation that this binary was built without.
pub struct FeatureHint {
    /// Stage.
    pub kind: StageKind,
    /// Implementation name.
    pub name: &'static str,
    /// Cargo feature of the `vlem` package that compiles it in.
    pub feature: &'static str,
}

inventory::collect!(FeatureHint);

/// All registered implementations, by stage and name.
pub struct Registry {
    entries: BTreeMap<(StageKind, &'static str), &'static Registration>,
}

impl Registry {
    /// The registry of everything linked into this binary, built on first use.
    ///
    /// # Errors
    /// [`CoreError::DuplicateImplementation`] when two plugins register one name for one stage.
    pub fn global() -> Result<&'static Registry> {
        static REGISTRY: OnceLock<std::result::Result<Registry, DuplicateName>> = OnceLock::new();
        match REGISTRY.get_or_init(|| Registry::from_registrations(inventory::iter::<Registration>))
        {
            Ok(registry) => Ok(registry),
            Err(d) => Err(CoreError::DuplicateImplementation {
                kind: d.kind,
                name: d.name,
                first: d.first,
                second: d.second,
            }),
        }
    }

    fn from_registrations(
        registrations: impl IntoIterator<Item = &'static Registration>,
    ) -> std::result::Result<Self, DuplicateName> {
        let mut entries = BTreeMap::new();
        for r in registrations {
            let key = (r.builder.kind(), r.name);
            if let Some(first) = entries.insert(key, r) {
                return Err(DuplicateName {
                    kind: key.0,
                    name: r.name,
                    first: first.description,
                    second: r.description,
                });
            }
        }
        Ok(Self { entries })
    }

    /// Names registered for `kind`, sorted.
    pub fn names(&self, kind: StageKind) -> Vec<&'static str> {
        self.entries
            .keys()
            .filter(|(k, _)| *k == kind)
            .map(|(_, n)| *n)
            .collect()
    }

    /// Every registration, sorted by stage then name.
    pub fn iter(&self) -> impl Iterator<Item = &'static Registration> + '_ {
        self.entries.values().copied()
    }

    /// The cargo feature that compiles in `name` of `kind`, where one is declared
    /// ([`feature_hint!`]); `None` for what every build has.
    pub fn feature_of(&self, kind: StageKind, name: &str) -> Option<&'static str> {
        inventory::iter::<FeatureHint>
            .into_iter()
            .find(|h| h.kind == kind && h.name == name)
            .map(|h| h.feature)
    }

    /// The implementations of `kind` this build lacks, with the cargo feature of each, sorted.
    pub fn not_built(&self, kind: StageKind) -> Vec<(&'static str, &'static str)> {
        let mut missing: Vec<_> = inventory::iter::<FeatureHint>
            .into_iter()
            .filter(|h| h.kind == kind && !self.entries.contains_key(&(kind, h.name)))
            .map(|h| (h.name, h.feature))
            .collect();
        missing.sort_unstable();
        missing.dedup();
        missing
    }

    /// The registration for `name`, or the unknown-name error.
    ///
    /// # Errors
    /// [`CoreError::UnknownImplementation`] listing the known names and, if a hint exists, the
    /// cargo feature that provides `name`.
    pub fn get(&self, kind: StageKind, name: &str) -> Result<&'static Registration> {
        self.entries
            .iter()
            .find(|((k, n), _)| *k == kind && *n == name)
            .map(|(_, r)| *r)
            .ok_or_else(|| CoreError::UnknownImplementation {
                kind,
                name: name.to_owned(),
                known: self.names(kind),
                feature: self.feature_of(kind, name).map(str::to_owned),
            })
    }

    /// The dataset reader registered as `name`.
    ///
    /// # Errors
    /// [`CoreError::UnknownImplementation`], as [`Registry::get`].
    pub fn dataset(&self, name: &str) -> Result<DatasetReader> {
        match self.get(StageKind::Dataset, name)?.builder {
            Builder::Dataset(reader) => Ok(reader),
            _ => Err(mismatched(StageKind::Dataset, name)),
        }
    }

    /// The dataset readers `kind = "auto"` can detect, in the order their probes run.
    pub fn dataset_probes(&self) -> Vec<(&'static str, DatasetProbe)> {
        let mut probes: Vec<_> = self
            .iter()
            .filter_map(|r| match r.builder {
                Builder::Dataset(DatasetReader {
                    detect: Some(probe),
                    ..
                }) => Some((r.name, probe)),
                _ => None,
            })
            .collect();
        probes.sort_by_key(|(name, probe)| (probe.order, *name));
        probes
    }

    /// Builds the tracker a config section names.
    ///
    /// # Errors
    /// Unknown names and the implementation's own parameter errors.
    pub fn build_tracker(
        &self,
        stage: &StageConfig,
        ctx: &BuildContext,
    ) -> Result<Box<dyn Tracker>> {
        match self.get(StageKind::Tracker, &stage.kind)?.builder {
            Builder::Tracker(build) => build(&stage.params, ctx),
            _ => Err(mismatched(StageKind::Tracker, &stage.kind)),
        }
    }

    /// Builds the region proposer a config section names.
    ///
    /// # Errors
    /// Unknown names and the implementation's own parameter errors.
    pub fn build_proposer(
        &self,
        stage: &StageConfig,
        ctx: &BuildContext,
    ) -> Result<Box<dyn RegionProposer>> {
        match self.get(StageKind::Proposer, &stage.kind)?.builder {
            Builder::Proposer(build) => build(&stage.params, ctx),
            _ => Err(mismatched(StageKind::Proposer, &stage.kind)),
        }
    }

    /// Builds the encoder a config section names.
    ///
    /// # Errors
    /// Unknown names and the implementation's own parameter errors.
    pub fn build_encoder(
        &self,
        stage: &StageConfig,
        ctx: &BuildContext,
    ) -> Result<Box<dyn Encoder>> {
        match self.get(StageKind::Encoder, &stage.kind)?.builder {
            Builder::Encoder(build) => build(&stage.params, ctx),
            _ => Err(mismatched(StageKind::Encoder, &stage.kind)),
        }
    }

    /// Builds the map a config section names.
    ///
    /// # Errors
    /// Unknown names and the implementation's own parameter errors.
    pub fn build_map(
        &self,
        stage: &StageConfig,
        ctx: &BuildContext,
    ) -> Result<Box<dyn EmbeddingMap>> {
        match self.get(StageKind::Map, &stage.kind)?.builder {
            Builder::Map(build) => build(&stage.params, ctx),
            _ => Err(mismatched(StageKind::Map, &stage.kind)),
        }
    }

    /// Builds the segmenter a config section names.
    ///
    /// # Errors
    /// Unknown names and the implementation's own parameter errors.
    pub fn build_segmenter(
        &self,
        stage: &StageConfig,
        ctx: &BuildContext,
    ) -> Result<Box<dyn Segmenter>> {
        match self.get(StageKind::Segmenter, &stage.kind)?.builder {
            Builder::Segmenter(build) => build(&stage.params, ctx),
            _ => Err(mismatched(StageKind::Segmenter, &stage.kind)),
        }
    }
}

struct DuplicateName {
    kind: StageKind,
    name: &'static str,
    first: &'static str,
    second: &'static str,
}

// Unreachable by construction (entries are keyed by the builder's own kind), kept as an error
// rather than a panic.
fn mismatched(kind: StageKind, name: &str) -> CoreError {
    CoreError::MissingStage {
        message: format!("registry entry `{name}` is not a {kind}"),
    }
}

/// Deserialises a stage's parameters into its config struct, with errors that name the section,
/// the implementation and the offending key.
///
/// # Errors
/// [`CoreError::InvalidParams`].
pub fn parse_params<T: DeserializeOwned>(
    kind: StageKind,
    name: &str,
    params: &toml::Table,
) -> Result<T> {
    T::deserialize(toml::Value::Table(params.clone())).map_err(|e| CoreError::InvalidParams {
        section: kind.section().to_owned(),
        name: name.to_owned(),
        message: e.to_string().trim().to_owned(),
    })
}

/// Registers a dataset reader:
/// `register_dataset!("name", "one-line description", DatasetReader::new(open_fn)…);`
/// with a [`DatasetReader`] (its probe for `kind = "auto"`, whether it reads a path, its
/// trajectory file).
#[macro_export]
macro_rules! register_dataset {
    ($name:expr, $description:expr, $reader:expr) => {
        $crate::__private::inventory::submit! {
            $crate::Registration {
                name: $name,
                description: $description,
                builder: $crate::Builder::Dataset($reader),
            }
        }
    };
}

/// Registers a [`Tracker`]: `register_tracker!("name", "one-line description", build_fn);`
/// where `build_fn: fn(&toml::Table, &BuildContext) -> Result<Box<dyn Tracker>>`.
#[macro_export]
macro_rules! register_tracker {
    ($name:expr, $description:expr, $build:expr) => {
        $crate::__private::inventory::submit! {
            $crate::Registration {
                name: $name,
                description: $description,
                builder: $crate::Builder::Tracker($build),
            }
        }
    };
}

/// Registers a [`RegionProposer`], like [`register_tracker!`].
#[macro_export]
macro_rules! register_proposer {
    ($name:expr, $description:expr, $build:expr) => {
        $crate::__private::inventory::submit! {
            $crate::Registration {
                name: $name,
                description: $description,
                builder: $crate::Builder::Proposer($build),
            }
        }
    };
}

/// Registers an [`Encoder`], like [`register_tracker!`].
#[macro_export]
macro_rules! register_encoder {
    ($name:expr, $description:expr, $build:expr) => {
        $crate::__private::inventory::submit! {
            $crate::Registration {
                name: $name,
                description: $description,
                builder: $crate::Builder::Encoder($build),
            }
        }
    };
}

/// Registers an [`EmbeddingMap`], like [`register_tracker!`].
#[macro_export]
macro_rules! register_map {
    ($name:expr, $description:expr, $build:expr) => {
        $crate::__private::inventory::submit! {
            $crate::Registration {
                name: $name,
                description: $description,
                builder: $crate::Builder::Map($build),
            }
        }
    };
}

/// Registers a [`Segmenter`], like [`register_tracker!`].
#[macro_export]
macro_rules! register_segmenter {
    ($name:expr, $description:expr, $build:expr) => {
        $crate::__private::inventory::submit! {
            $crate::Registration {
                name: $name,
                description: $description,
                builder: $crate::Builder::Segmenter($build),
            }
        }
    };
}

/// Declares that `name` (a `kind` implementation) is compiled in by cargo feature `feature`:
/// `feature_hint!(Encoder, "clip", "clip");`.
#[macro_export]
macro_rules! feature_hint {
    ($kind:ident, $name:expr, $feature:expr) => {
        $crate::__private::inventory::submit! {
            $crate::FeatureHint {
                kind: $crate::StageKind::$kind,
                name: $name,
                feature: $feature,
            }
        }
    };
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::traits::tracker::{TrackedPose, TrackingState};
    use crate::types::{Frame, Pose};

    struct Fixed;
    impl Tracker for Fixed {
        fn name(&self) -> &'static str {
            "test-fixed"
        }
        fn track(&mut self, _frame: &Frame) -> Result<TrackedPose> {
            Ok(TrackedPose {
                pose: Pose::identity(),
                state: TrackingState::Tracking,
            })
        }
    }

    #[derive(serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    struct FixedParams {
        #[serde(default)]
        #[allow(dead_code, reason = "only parsed")]
        offset: f64,
    }

    fn build_fixed(params: &toml::Table, _ctx: &BuildContext) -> Result<Box<dyn Tracker>> {
        let _: FixedParams = parse_params(StageKind::Tracker, "test-fixed", params)?;
        Ok(Box::new(Fixed))
    }

    register_tracker!("test-fixed", "a tracker for registry tests", build_fixed);
    feature_hint!(Encoder, "test-missing", "test-feature");

    static A: Registration = Registration {
        name: "twin",
        description: "first twin",
        builder: Builder::Tracker(build_fixed),
    };
    static B: Registration = Registration {
        name: "twin",
        description: "second twin",
        builder: Builder::Tracker(build_fixed),
    };

    #[test]
    fn registered_names_build_and_unknown_names_list_the_known_ones() {
        let registry = Registry::global().unwrap();
        assert!(registry.names(StageKind::Tracker).contains(&"test-fixed"));
        let stage = StageConfig::named("test-fixed");
        assert_eq!(
            registry
                .build_tracker(&stage, &BuildContext::default())
                .unwrap()
                .name(),
            "test-fixed"
        );
        let err = registry
            .build_tracker(&StageConfig::named("nope"), &BuildContext::default())
            .err()
            .unwrap();
        let msg = err.to_string();
        assert!(msg.starts_with("unknown tracker `nope` (known: "), "{msg}");
        assert!(msg.contains("test-fixed"), "{msg}");
    }

    #[test]
    fn unknown_name_with_a_hint_names_the_cargo_feature() {
        let err = Registry::global()
            .unwrap()
            .get(StageKind::Encoder, "test-missing")
            .err()
            .unwrap();
        assert_eq!(
            err.to_string(),
            "unknown encoder `test-missing` (none is compiled in); `test-missing` is provided by the \
             cargo feature `test-feature`, which this binary was built without: rebuild with \
             `cargo build --release --features test-feature`"
        );
    }

    #[test]
    fn duplicate_names_are_refused() {
        let Err(d) = Registry::from_registrations([&A, &B]) else {
            panic!("duplicate accepted");
        };
        let err = CoreError::DuplicateImplementation {
            kind: d.kind,
            name: d.name,
            first: d.first,
            second: d.second,
        };
        assert_eq!(
            err.to_string(),
            "two plugins register the tracker `twin`: first twin and second twin"
        );
    }

    #[test]
    fn bad_params_name_the_section_and_key() {
        let mut params = toml::Table::new();
        params.insert("ofset".into(), toml::Value::Float(1.0));
        let stage = StageConfig {
            kind: "test-fixed".into(),
            params,
        };
        let err = Registry::global()
            .unwrap()
            .build_tracker(&stage, &BuildContext::default())
            .err()
            .unwrap();
        let msg = err.to_string();
        assert!(
            msg.starts_with("[tracker] kind = \"test-fixed\": unknown field `ofset`"),
            "{msg}"
        );
    }
}
