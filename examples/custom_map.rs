//! A new map built on the `vlem-maps` kit, registered and run through the pipeline.
//!
//! The map, `latest-voxel`, cuts the world into coarse voxels and keeps, per voxel, only the
//! latest observation: the last pixel that fell into it, with its world point, colour and
//! embedding. Everything a map shares with the others comes from `vlem::maps::kit`: the config's
//! `dim`, `max_depth`, `pixel_stride` and `precision` and their checks ([`vlem::maps::map_config!`]),
//! the valid, in-range, embedded pixels of a frame in world coordinates
//! ([`vlem::maps::kit::FramePixels`]), the embedding lookup and the input checks; the embedding
//! table is [`vlem::maps::storage::EmbeddingStore`]. What is left is the fusion rule.
//!
//! It maps the 30 committed living-room frames in `data/` with their trajectory and the
//! weight-free `colour-names` encoder, then prints the map's size and the best score of one
//! query. Run it from the repository root (default features) with
//!
//! ```text
//! cargo run --release --example custom_map
//! ```

use std::collections::HashMap;
use std::path::Path;

use anyhow::{Context, Result};
use vlem::core::pipeline::{Pipeline, Progress};
use vlem::core::{
    BuildContext, Config, CoreError, EmbeddingMap, IntegrationStats, MapBudget, MapMetadata,
    MapSnapshot, Observation, StageKind, parse_params,
};
use vlem::maps::kit::{FramePixels, check_observation, count_in, embedding, number_in};
use vlem::maps::storage::EmbeddingStore;

/// The registered name.
const NAME: &str = "latest-voxel";

vlem::maps::map_config! {
    /// `[map] kind = "latest-voxel"` parameters.
    pub struct LatestVoxelConfig {
        /// Edge length of a voxel in metres; default 0.1.
        pub voxel_size: f32 = 0.1,
        /// Voxel budget; default 100,000. New voxels beyond it are not added.
        pub max_voxels: usize = 100_000,
    }
}

/// The map: one element per voxel, overwritten by every later observation of it.
struct LatestVoxelMap {
    config: LatestVoxelConfig,
    dim: usize,
    /// Dense index of every voxel.
    index: HashMap<[i32; 3], usize>,
    positions: Vec<[f32; 3]>,
    colours: Vec<[u8; 3]>,
    embeddings: EmbeddingStore,
    /// The frame count when each voxel was last written.
    written: Vec<usize>,
    frames: usize,
}

fn build(params: &toml::Table, ctx: &BuildContext) -> vlem::core::Result<Box<dyn EmbeddingMap>> {
    let config: LatestVoxelConfig = parse_params(StageKind::Map, NAME, params)?;
    // Every numeric setting has a range, refused at build with the key, the range and the value.
    number_in(NAME, "voxel_size", config.voxel_size, (0.001, 10.0), "m")?;
    count_in(
        NAME,
        "max_voxels",
        config.max_voxels,
        (1, 1 << 30),
        "voxels",
    )?;
    let dim = config.common().validate(NAME, ctx.embedding_dim)?;
    Ok(Box::new(LatestVoxelMap {
        embeddings: EmbeddingStore::new(dim, config.precision),
        config,
        dim,
        index: HashMap::new(),
        positions: Vec::new(),
        colours: Vec::new(),
        written: Vec::new(),
        frames: 0,
    }))
}

vlem::core::register_map!(
    NAME,
    "the latest observation per coarse voxel (examples/custom_map.rs)",
    build
);

impl EmbeddingMap for LatestVoxelMap {
    fn name(&self) -> &'static str {
        NAME
    }

    fn dim(&self) -> usize {
        self.dim
    }

    fn integrate(&mut self, obs: &Observation<'_>) -> vlem::core::Result<IntegrationStats> {
        check_observation(self.dim, obs).map_err(|e| CoreError::stage(StageKind::Map, NAME, e))?;
        self.frames += 1;
        let mut stats = IntegrationStats::default();
        let mut scratch = vec![0.0f32; self.dim];
        let inverse_size = 1.0 / self.config.voxel_size;
        for pixel in FramePixels::new(obs, &self.config.common()).iter() {
            let row: &[f32] = match obs.embeddings {
                Some(e) if self.dim > 0 => match embedding(e, pixel.index, &mut scratch) {
                    Some(row) => row,
                    None => continue,
                },
                _ => &[],
            };
            stats.observed += 1;
            let key = pixel.world.map(|x| (x * inverse_size).floor() as i32);
            let colour = pixel.colour(&obs.frame.colour);
            let slot = match self.index.get(&key) {
                Some(&slot) => {
                    if self.written[slot] < self.frames {
                        stats.fused += 1;
                    }
                    self.positions[slot] = pixel.world;
                    self.colours[slot] = colour;
                    if self.dim > 0 {
                        self.embeddings.set_row(slot, row);
                    }
                    slot
                }
                None if self.positions.len() < self.config.max_voxels => {
                    let slot = self.positions.len();
                    self.index.insert(key, slot);
                    self.positions.push(pixel.world);
                    self.colours.push(colour);
                    self.written.push(0);
                    if self.dim > 0 {
                        self.embeddings.push(row);
                    }
                    stats.inserted += 1;
                    slot
                }
                None => continue,
            };
            self.written[slot] = self.frames;
        }
        Ok(stats)
    }

    fn len(&self) -> usize {
        self.positions.len()
    }

    fn budget(&self) -> Option<MapBudget> {
        Some(MapBudget {
            parameter: "max_voxels",
            elements: self.config.max_voxels,
        })
    }

    fn memory_bytes(&self) -> usize {
        self.positions.capacity() * std::mem::size_of::<[f32; 3]>()
            + self.colours.capacity() * 3
            + self.written.capacity() * std::mem::size_of::<usize>()
            + self.index.capacity() * std::mem::size_of::<([i32; 3], usize)>()
            + self.embeddings.memory_bytes()
    }

    fn similarity(&self, text: &[f32], out: &mut Vec<f32>) -> vlem::core::Result<()> {
        self.embeddings.similarity(text, out)
    }

    fn snapshot(&self) -> vlem::core::Result<MapSnapshot> {
        Ok(MapSnapshot {
            map_kind: NAME.into(),
            dim: self.dim,
            positions: self.positions.clone(),
            colours: self.colours.clone(),
            embeddings: self.embeddings.to_f32(),
            metadata: MapMetadata {
                frames_integrated: self.frames,
                ..MapMetadata::default()
            },
        })
    }
}

const CONFIG: &str = r#"
[tracker]
kind = "ground-truth"

[encoder]
kind = "colour-names"

[map]
kind = "latest-voxel"
voxel_size = 0.05
pixel_stride = 2
"#;

fn main() -> Result<()> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let config = Config::from_toml(CONFIG)?;
    let ctx = BuildContext {
        config_dir: root.to_path_buf(),
        embedding_dim: None,
    };
    let mut pipeline = Pipeline::from_config(&config, &ctx)?;
    let mut source = vlem::datasets::open(&config.dataset, &root.join("data/living-room"))?;
    let report = pipeline.run(source.as_mut(), None, &|_: Progress| {})?;

    let map = pipeline.map().context("the config has a [map]")?;
    let encoder = pipeline.encoder().context("the config has an [encoder]")?;
    let query = "white wall";
    let mut scores = Vec::new();
    map.similarity(&encoder.encode_text(query)?, &mut scores)?;
    let best = scores
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .context("the map is empty")?;
    println!(
        "map `{}`: {} voxels from {} frames ({:.1} MB)",
        map.name(),
        map.len(),
        report.frames_processed,
        map.memory_bytes() as f64 / 1e6
    );
    println!(
        "query \"{query}\": best score {:.3} at voxel {} ({:?})",
        best.1,
        best.0,
        map.snapshot()?.positions[best.0]
    );
    Ok(())
}
