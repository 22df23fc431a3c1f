//! The plugin registry: stage names in the TOML config → trait objects.
//!
//! Every implementation registers itself with one of the `register_*!` macros, which put a
//! [`Registration`] into an [`inventory`] collection at link time. [`Registry::global`] gathers them
//! once into sorted maps, refusing duplicate names. Lookups of an unknown name list the known names
//! and, when a [`FeatureHint`] says so, the cargo feature that would compile the missing one in.
//!
//! A plugin crate that is a dependency but never referenced is not linked, and its registrations
//! vanish silently: binaries reference every plugin crate they depend on (see `src/plugins.rs` of the
//! `vlem` binary), and a test there checks the expected names.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::OnceLock;

use serde::de::DeserializeOwned;

use crate::config::{Config, StageConfig, config_folder};
use crate::error::{CoreError, Result};
use crate::stage::StageKind;
use crate::traits::embedding_map::EmbeddingMap;
use crate::traits::encoder::Encoder;
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

/// The constructor of one registered implementation.
#[derive(Clone, Copy)]
pub enum Builder {
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
                feature: inventory::iter::<FeatureHint>
                    .into_iter()
                    .find(|h| h.kind == kind && h.name == name)
                    .map(|h| h.feature.to_owned()),
            })
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
