//! From texts to answers: embed the texts, score every map point, select point sets, grasp.
//!
//! Why it exists: every front-end (`vlem query`, `vlem eval semseg*`, the query server, a Python
//! module, a robot node) answers the same question the same way, on a saved map
//! ([`MapSnapshot`]) or on a map being built ([`LiveMap`]). The texts are embedded before the
//! live map is locked, and segmentation and grasping run on a copy of the positions after it is
//! unlocked, so a query holds the map only for one similarity pass.

use serde::{Deserialize, Serialize};
use vlem_core::live::LiveMap;
use vlem_core::query::normalised_similarity_many;
use vlem_core::{
    BuildContext, Encoder, MapMetadata, MapSnapshot, PointSet, QueryScores, Registry, Segmenter,
    StageConfig,
};

use crate::error::{QueryError, Result};
use crate::grasp::{Grasp, GraspParams, grasp_from_points};

/// How points are selected: a segmenter by name and its two tunable parameters, as `vlem query`
/// and the query server take them.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Selection {
    /// Registered segmenter name (`threshold`, `argmax`, `cluster`, ...).
    #[serde(default = "default_segmenter")]
    pub segmenter: String,
    /// Minimum normalised similarity (default 0.75 for `threshold`, none for the others).
    #[serde(default)]
    pub threshold: Option<f32>,
    /// The generic text a point must match better (for `argmax` and `cluster`).
    #[serde(default)]
    pub baseline: Option<String>,
}

fn default_segmenter() -> String {
    "threshold".into()
}

impl Selection {
    /// The `threshold` segmenter at its default threshold.
    pub fn threshold() -> Self {
        Self {
            segmenter: default_segmenter(),
            threshold: None,
            baseline: None,
        }
    }

    /// Builds the segmenter through the registry.
    ///
    /// # Errors
    /// An unknown segmenter name (listing the known ones) or parameters out of range.
    pub fn build(&self, ctx: &BuildContext) -> Result<Box<dyn Segmenter>> {
        let mut params = toml::Table::new();
        // The threshold segmenter always has one (0.75 unless given); the others only when asked.
        let threshold = match (self.segmenter.as_str(), self.threshold) {
            ("threshold", t) => Some(t.unwrap_or(0.75)),
            (_, t) => t,
        };
        if let Some(t) = threshold {
            params.insert("threshold".into(), toml::Value::Float(f64::from(t)));
        }
        if let Some(b) = &self.baseline {
            params.insert("baseline".into(), toml::Value::String(b.clone()));
        }
        Ok(Registry::global()?.build_segmenter(
            &StageConfig {
                kind: self.segmenter.clone(),
                params,
            },
            ctx,
        )?)
    }
}

/// Rebuilds the encoder that made a map from the map's metadata, so texts are embedded the way
/// the map's points were. `map` names the map in the error for a geometry-only map.
///
/// # Errors
/// [`QueryError::GeometryOnly`] for a map mapped without an encoder; registry and model-loading
/// errors of the encoder (e.g. missing weights, naming the file).
pub fn encoder_for_map(metadata: &MapMetadata, map: &str) -> Result<Box<dyn Encoder>> {
    let Some(stage) = &metadata.encoder else {
        return Err(QueryError::GeometryOnly { map: map.into() });
    };
    let ctx = BuildContext {
        config_dir: metadata.config_dir.clone().unwrap_or_default(),
        embedding_dim: None,
    };
    Ok(Registry::global()?.build_encoder(stage, &ctx)?)
}

/// Query texts and the segmenter's baseline, embedded.
#[derive(Clone, Debug, PartialEq)]
pub struct EmbeddedTexts {
    /// The texts, in order.
    pub texts: Vec<String>,
    /// One unit embedding per text.
    pub embeddings: Vec<Vec<f32>>,
    /// The baseline text's embedding, when the segmenter compares against one.
    pub baseline: Option<Vec<f32>>,
}

impl EmbeddedTexts {
    /// Every embedding to score in one pass: the texts', then the baseline's.
    fn all(&self) -> Vec<&[f32]> {
        self.embeddings
            .iter()
            .chain(&self.baseline)
            .map(Vec::as_slice)
            .collect()
    }

    /// The scores of one pass over [`EmbeddedTexts::all`], split back into the texts' and the
    /// baseline's.
    fn split(&self, mut scores: Vec<Vec<f32>>) -> QueryScores {
        let baseline = self.baseline.as_ref().and_then(|_| scores.pop());
        QueryScores {
            queries: self.texts.clone(),
            scores,
            baseline,
        }
    }
}

/// Embeds `texts`, and the baseline `segmenter` asks for, with `encoder`.
///
/// # Errors
/// [`QueryError::NoTexts`], [`QueryError::Embed`] for a text the encoder cannot embed,
/// [`QueryError::Baseline`] for a baseline it cannot embed.
pub fn embed_texts(
    encoder: &dyn Encoder,
    segmenter: &dyn Segmenter,
    texts: &[String],
) -> Result<EmbeddedTexts> {
    if texts.is_empty() {
        return Err(QueryError::NoTexts);
    }
    let embeddings = texts
        .iter()
        .map(|text| {
            encoder
                .encode_text(text)
                .map_err(|source| QueryError::Embed {
                    text: text.clone(),
                    source,
                })
        })
        .collect::<Result<_>>()?;
    let baseline = segmenter
        .baseline_query()
        .map(|text| {
            // The generic baseline is each encoder's own word for "anything".
            let text = if text == vlem_core::GENERIC_TEXT {
                encoder.generic_text()
            } else {
                text
            };
            encoder
                .encode_text(text)
                .map_err(|source| QueryError::Baseline {
                    text: text.to_owned(),
                    segmenter: segmenter.name(),
                    generic: encoder.generic_text().to_owned(),
                    source: Box::new(source),
                })
        })
        .transpose()?;
    Ok(EmbeddedTexts {
        texts: texts.to_vec(),
        embeddings,
        baseline,
    })
}

/// Every point's similarity to every text, with the points they belong to.
#[derive(Clone, Debug, PartialEq)]
pub struct Scored {
    /// Map element positions, in score order.
    pub positions: Vec<[f32; 3]>,
    /// Per-query (and baseline) similarities.
    pub scores: QueryScores,
    /// Frames integrated into the map these scores belong to.
    pub frames_integrated: usize,
}

fn check_dim(map_dim: usize, encoder: &dyn Encoder) -> Result<()> {
    if map_dim == encoder.dim() {
        Ok(())
    } else {
        Err(QueryError::EncoderDimension {
            map_dim,
            encoder: encoder.name().into(),
            encoder_dim: encoder.dim(),
        })
    }
}

/// Scores a saved map.
///
/// # Errors
/// [`QueryError::EncoderDimension`] when `texts` were embedded in another dimension than the map's.
pub fn score_snapshot(snapshot: &MapSnapshot, texts: &EmbeddedTexts) -> Result<QueryScores> {
    let mut scores = Vec::new();
    normalised_similarity_many(
        &snapshot.embeddings,
        snapshot.dim,
        &texts.all(),
        &mut scores,
    )?;
    Ok(texts.split(scores))
}

/// Scores the live map as it is after a whole number of frames, holding its read lock for one
/// similarity pass over the map (all texts at once) and a copy of the positions.
///
/// # Errors
/// A live map without a map, or similarities of the wrong dimension.
pub fn score_live(live: &LiveMap, texts: &EmbeddedTexts) -> Result<Scored> {
    // Every text and the baseline in one pass over the map: the read lock (which integration
    // waits for) is held for one pass, however many texts a query has.
    let all = texts.all();
    live.read(|view| -> Result<Scored> {
        let mut scored = Vec::new();
        view.map.similarity_many(&all, &mut scored)?;
        let scores = texts.split(scored);
        Ok(Scored {
            positions: view.map.coloured_points().vertices,
            scores,
            frames_integrated: view.frames_integrated,
        })
    })?
}

/// One selected point set, summarised for printing and for the wire.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SetSummary {
    /// Points in the set.
    pub points: usize,
    /// Their mean similarity.
    pub mean_score: f32,
    /// Their centroid.
    pub centre: [f64; 3],
    /// Indices of the points (into the map's points), when asked for.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub indices: Option<Vec<usize>>,
}

/// The best-scoring point of a query.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct BestPoint {
    /// Index into the map's points.
    pub index: usize,
    /// Its similarity.
    pub score: f32,
    /// Its position.
    pub position: [f32; 3],
}

/// A grasp on a query's best point set, or why there is none.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "outcome")]
pub enum GraspAnswer {
    /// A grasp was found.
    Found {
        /// Centre between the fingertips (m, map frame).
        position: [f64; 3],
        /// Orientation as a unit quaternion `[x, y, z, w]`; its rotation matrix has the columns
        /// closing direction, approach × closing and approach.
        orientation: [f64; 4],
        /// Unit closing direction.
        closing: [f64; 3],
        /// Unit approach direction.
        approach: [f64; 3],
        /// Object width across the closing direction (m).
        width: f64,
        /// Points of the set the grasp was computed from.
        from_points: usize,
    },
    /// No grasp: the reason.
    None {
        /// Why.
        reason: String,
    },
}

/// What one text found.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct QueryAnswer {
    /// The text.
    pub text: String,
    /// The best-scoring point; `None` for an empty map.
    pub best: Option<BestPoint>,
    /// Points selected over all sets.
    pub selected: usize,
    /// The non-empty point sets, best mean similarity first.
    pub sets: Vec<SetSummary>,
    /// The grasp on the best set, when one was asked for.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grasp: Option<GraspAnswer>,
}

/// Answers to a list of texts on one state of a map.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Answer {
    /// The segmenter that selected the points.
    pub segmenter: String,
    /// Map elements scored.
    pub points: usize,
    /// Frames integrated into the map state that was queried.
    pub frames_integrated: usize,
    /// One answer per text, in order.
    pub queries: Vec<QueryAnswer>,
}

/// An [`Answer`] with everything a front-end draws from: the scores, the point sets and the grasps.
#[derive(Clone, Debug)]
pub struct Answered {
    /// The summary (what is printed and sent).
    pub answer: Answer,
    /// Per-point similarities.
    pub scores: QueryScores,
    /// Every point set the segmenter made.
    pub sets: Vec<PointSet>,
    /// Per query, the grasp on its best set; empty when no grasp was asked for.
    pub grasps: Vec<Option<Grasp>>,
}

/// Options of [`answer`].
#[derive(Clone, Debug, Default)]
pub struct AnswerOptions {
    /// Compute a grasp on each query's best point set with these parameters.
    pub grasp: Option<GraspParams>,
    /// Put each set's point indices into the summary.
    pub indices: bool,
}

/// Segments the scored points and summarises each query (best point, sets, grasp).
///
/// # Errors
/// The segmenter's errors (e.g. score lists that do not match the points).
pub fn answer(
    positions: &[[f32; 3]],
    scores: QueryScores,
    frames_integrated: usize,
    segmenter: &dyn Segmenter,
    options: &AnswerOptions,
) -> Result<Answered> {
    let sets = segmenter.segment(positions, &scores)?;
    let mut grasps = Vec::new();
    let queries = scores
        .queries
        .iter()
        .enumerate()
        .map(|(q, text)| {
            let s = &scores.scores[q];
            let best = (0..s.len())
                .max_by(|&a, &b| s[a].total_cmp(&s[b]))
                .map(|index| BestPoint {
                    index,
                    score: s[index],
                    position: positions[index],
                });
            let mut own: Vec<&PointSet> = sets
                .iter()
                .filter(|set| set.query == q && !set.indices.is_empty())
                .collect();
            own.sort_by(|a, b| b.mean_score.total_cmp(&a.mean_score));
            let grasp = options.grasp.as_ref().map(|params| {
                let (grasp, outcome) = grasp_best(positions, own.first().copied(), params);
                grasps.push(grasp);
                outcome
            });
            QueryAnswer {
                text: text.clone(),
                best,
                selected: own.iter().map(|set| set.indices.len()).sum(),
                sets: own
                    .iter()
                    .map(|set| SetSummary {
                        points: set.indices.len(),
                        mean_score: set.mean_score,
                        centre: centroid(positions, &set.indices),
                        indices: options.indices.then(|| set.indices.clone()),
                    })
                    .collect(),
                grasp,
            }
        })
        .collect();
    Ok(Answered {
        answer: Answer {
            segmenter: segmenter.name().into(),
            points: positions.len(),
            frames_integrated,
            queries,
        },
        scores,
        sets,
        grasps,
    })
}

/// Texts → answer on a saved map, with an encoder built for it ([`encoder_for_map`]).
///
/// # Errors
/// As [`embed_texts`], [`score_snapshot`] and [`answer`].
pub fn answer_snapshot(
    snapshot: &MapSnapshot,
    encoder: &dyn Encoder,
    segmenter: &dyn Segmenter,
    texts: &[String],
    options: &AnswerOptions,
) -> Result<Answered> {
    check_dim(snapshot.dim, encoder)?;
    let embedded = embed_texts(encoder, segmenter, texts)?;
    let scores = score_snapshot(snapshot, &embedded)?;
    answer(
        &snapshot.positions,
        scores,
        snapshot.metadata.frames_integrated,
        segmenter,
        options,
    )
}

/// Texts → answer on the live map, with the encoder that is building it; the map stays locked
/// only for the similarity pass.
///
/// # Errors
/// [`QueryError::GeometryOnly`] for a pipeline without an encoder, and as [`embed_texts`],
/// [`score_live`] and [`answer`].
pub fn answer_live(
    live: &LiveMap,
    segmenter: &dyn Segmenter,
    texts: &[String],
    options: &AnswerOptions,
) -> Result<(Answered, Vec<[f32; 3]>)> {
    let encoder = live.encoder().ok_or_else(|| QueryError::GeometryOnly {
        map: "the live map".into(),
    })?;
    let embedded = embed_texts(encoder.as_ref(), segmenter, texts)?;
    let scored = score_live(live, &embedded)?;
    let answered = answer(
        &scored.positions,
        scored.scores,
        scored.frames_integrated,
        segmenter,
        options,
    )?;
    Ok((answered, scored.positions))
}

/// The grasp on a query's best set, and its summary.
fn grasp_best(
    positions: &[[f32; 3]],
    best: Option<&PointSet>,
    params: &GraspParams,
) -> (Option<Grasp>, GraspAnswer) {
    let Some(best) = best else {
        return (
            None,
            GraspAnswer::None {
                reason: "no point set selected".into(),
            },
        );
    };
    let points: Vec<[f32; 3]> = best
        .indices
        .iter()
        .filter_map(|&i| positions.get(i).copied())
        .collect();
    match grasp_from_points(&points, params) {
        Ok(g) => {
            let q = g.rotation.quaternion();
            let outcome = GraspAnswer::Found {
                position: g.position,
                orientation: [q.i, q.j, q.k, q.w],
                closing: g.closing,
                approach: g.approach,
                width: g.width,
                from_points: points.len(),
            };
            (Some(g), outcome)
        }
        Err(e) => (
            None,
            GraspAnswer::None {
                reason: e.to_string(),
            },
        ),
    }
}

fn centroid(positions: &[[f32; 3]], indices: &[usize]) -> [f64; 3] {
    let n = indices.len().max(1) as f64;
    indices.iter().fold([0.0f64; 3], |acc, &i| {
        let p = positions[i];
        [
            acc[0] + f64::from(p[0]) / n,
            acc[1] + f64::from(p[1]) / n,
            acc[2] + f64::from(p[2]) / n,
        ]
    })
}

/// How many point sets per query the printed summary lists.
const SHOWN_SETS: usize = 5;

impl Answer {
    /// The lines `vlem query` prints: per query its best point and selection (and, for
    /// segmenters that make several sets, the best few), then per query the grasp when asked.
    pub fn lines(&self) -> Vec<String> {
        let mut lines = Vec::new();
        for q in &self.queries {
            let text = &q.text;
            match &q.best {
                Some(best) => {
                    let p = best.position;
                    lines.push(format!(
                        "\"{text}\": best {:.3} at ({:.2}, {:.2}, {:.2}); {} of {} points in {} point set{} selected by `{}`",
                        best.score,
                        p[0],
                        p[1],
                        p[2],
                        q.selected,
                        self.points,
                        q.sets.len(),
                        if q.sets.len() == 1 { "" } else { "s" },
                        self.segmenter
                    ));
                }
                None => lines.push(format!("\"{text}\": the map is empty")),
            }
            // Several sets per query are clusters (objects): list the best few.
            if q.sets.len() > 1 {
                for (rank, set) in q.sets.iter().take(SHOWN_SETS).enumerate() {
                    let c = set.centre;
                    lines.push(format!(
                        "  cluster {}: {} points, mean similarity {:.3}, centre ({:.2}, {:.2}, {:.2})",
                        rank + 1,
                        set.points,
                        set.mean_score,
                        c[0],
                        c[1],
                        c[2]
                    ));
                }
                if q.sets.len() > SHOWN_SETS {
                    lines.push(format!(
                        "  … and {} more clusters with lower similarity",
                        q.sets.len() - SHOWN_SETS
                    ));
                }
            }
        }
        for q in &self.queries {
            let text = &q.text;
            match &q.grasp {
                Some(GraspAnswer::Found {
                    position: p,
                    closing: c,
                    width,
                    from_points,
                    ..
                }) => lines.push(format!(
                    "\"{text}\": grasp at ({:.3}, {:.3}, {:.3}), closing along ({:.3}, {:.3}, {:.3}), width {:.3} m, from a set of {} points",
                    p[0], p[1], p[2], c[0], c[1], c[2], width, from_points
                )),
                Some(GraspAnswer::None { reason }) => {
                    lines.push(format!("\"{text}\": no grasp: {reason}"));
                }
                None => {}
            }
        }
        lines
    }
}

/// A file-name-safe form of a query text (`query-<slug>.ply`).
pub fn slug(text: &str) -> String {
    let s: String = text
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() {
                c.to_ascii_lowercase()
            } else {
                '-'
            }
        })
        .collect();
    let s = s.trim_matches('-').to_owned();
    if s.is_empty() { "query".into() } else { s }
}
