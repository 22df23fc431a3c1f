//! `vlem.Map`: a map being built (the pipeline's live map) or loaded from a map file, as numpy
//! arrays, with text queries answered by the same library code as `vlem query`.

use std::path::PathBuf;
use std::sync::{Arc, Mutex, PoisonError};

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use vlem_core::live::LiveMap;
use vlem_core::{BuildContext, Encoder, MapSnapshot};
use vlem_query::answer::{
    AnswerOptions, Answered, Selection, answer, answer_snapshot, embed_texts, encoder_for_map,
    score_live, score_snapshot,
};
use vlem_query::grasp::GraspParams;

use crate::arrays::give;
use crate::errors;
use crate::json::to_python;

/// Where a map's content is.
enum Source {
    /// A pipeline's map, changing while it runs.
    Live(LiveMap),
    /// A map file's content; the encoder that made it is rebuilt on the first query.
    Saved {
        snapshot: Arc<MapSnapshot>,
        path: PathBuf,
        encoder: Mutex<Option<Arc<dyn Encoder>>>,
    },
}

/// A vision-language embedding map: points with colours and embeddings, queried with text.
///
/// From a pipeline (``pipeline.map``, live: it changes while the pipeline runs, and every read
/// sees whole integrated frames only) or from a map file (``vlem.Map.load("out/map.vlem")``).
/// Reads may come from any number of Python threads while a run feeds frames.
#[pyclass(module = "vlem", name = "Map", frozen)]
pub struct PyMap {
    source: Source,
}

impl PyMap {
    /// The live map of a pipeline; a `ConfigError` for a tracking-only pipeline.
    pub fn live(live: &LiveMap) -> PyResult<Self> {
        if !live.has_map() {
            return Err(errors::ConfigError::new_err(
                "the config has no [map] section: this pipeline only tracks",
            ));
        }
        Ok(Self {
            source: Source::Live(live.clone()),
        })
    }

    /// A consistent copy of the content: points, colours and embeddings of one integrated-frame
    /// count.
    fn content(&self, py: Python<'_>) -> PyResult<Arc<MapSnapshot>> {
        match &self.source {
            Source::Live(live) => py
                .detach(|| live.snapshot())
                .map(Arc::new)
                .map_err(errors::core),
            Source::Saved { snapshot, .. } => Ok(snapshot.clone()),
        }
    }

    /// The encoder that embeds query texts as the map's points were embedded.
    fn encoder(&self, py: Python<'_>) -> PyResult<Arc<dyn Encoder>> {
        match &self.source {
            Source::Live(live) => live.encoder().cloned().ok_or_else(|| {
                errors::QueryError::new_err(
                    "the pipeline has no encoder: its map holds geometry only and cannot be \
                     queried with text",
                )
            }),
            Source::Saved {
                snapshot,
                path,
                encoder,
            } => {
                let mut slot = encoder.lock().unwrap_or_else(PoisonError::into_inner);
                if let Some(e) = slot.as_ref() {
                    return Ok(e.clone());
                }
                let metadata = snapshot.metadata.clone();
                let name = path.display().to_string();
                let built: Arc<dyn Encoder> = py
                    .detach(|| encoder_for_map(&metadata, &name))
                    .map_err(errors::query)?
                    .into();
                *slot = Some(built.clone());
                Ok(built)
            }
        }
    }

    fn build_context(&self) -> BuildContext {
        let config_dir = match &self.source {
            Source::Live(live) => live.metadata().config_dir,
            Source::Saved { snapshot, .. } => snapshot.metadata.config_dir.clone(),
        };
        BuildContext {
            config_dir: config_dir.unwrap_or_default(),
            embedding_dim: None,
        }
    }
}

/// The largest score table [`PyMap::scores`] builds: 4 GiB (1M points × 1024 texts).
const MAX_SCORE_TABLE_BYTES: usize = 4 << 30;

fn texts_from(texts: &Bound<'_, PyAny>) -> PyResult<Vec<String>> {
    if let Ok(text) = texts.extract::<String>() {
        return Ok(vec![text]);
    }
    texts
        .extract::<Vec<String>>()
        .map_err(|_| pyo3::exceptions::PyTypeError::new_err("texts must be a str or a list of str"))
}

#[pymethods]
impl PyMap {
    /// Loads a map file written by ``vlem run``, ``Map.save`` or the query server.
    ///
    /// Query texts are embedded by the encoder that made the map, rebuilt from the file's
    /// metadata on the first query (its model weights must still be where the config said).
    #[staticmethod]
    fn load(py: Python<'_>, path: PathBuf) -> PyResult<Self> {
        let snapshot = py
            .detach(|| vlem_core::read_map_file(&path))
            .map_err(errors::core)?;
        Ok(Self {
            source: Source::Saved {
                snapshot: Arc::new(snapshot),
                path,
                encoder: Mutex::new(None),
            },
        })
    }

    /// Number of points (map elements).
    fn __len__(&self) -> PyResult<usize> {
        match &self.source {
            Source::Live(live) => live.read(|view| view.map.len()).map_err(errors::core),
            Source::Saved { snapshot, .. } => Ok(snapshot.len()),
        }
    }

    fn __repr__(&self, py: Python<'_>) -> PyResult<String> {
        let (kind, live) = match &self.source {
            Source::Live(live) => (
                live.read(|view| view.map.name().to_owned())
                    .map_err(errors::core)?,
                true,
            ),
            Source::Saved { snapshot, .. } => (snapshot.map_kind.clone(), false),
        };
        Ok(format!(
            "<vlem.Map `{kind}`{}: {} points, {}-d embeddings, {} frames integrated>",
            if live { " (live)" } else { "" },
            self.__len__()?,
            self.dim()?,
            self.frames_integrated(py)?
        ))
    }

    /// The map kind (``point-cloud``, ``voxel``, ``segment``, ...).
    #[getter]
    fn kind(&self) -> PyResult<String> {
        match &self.source {
            Source::Live(live) => live
                .read(|view| view.map.name().to_owned())
                .map_err(errors::core),
            Source::Saved { snapshot, .. } => Ok(snapshot.map_kind.clone()),
        }
    }

    /// Embedding dimension.
    #[getter]
    fn dim(&self) -> PyResult<usize> {
        match &self.source {
            Source::Live(live) => live.read(|view| view.map.dim()).map_err(errors::core),
            Source::Saved { snapshot, .. } => Ok(snapshot.dim),
        }
    }

    /// Frames integrated into the content a read sees now.
    #[getter]
    fn frames_integrated(&self, _py: Python<'_>) -> PyResult<usize> {
        match &self.source {
            Source::Live(live) => live
                .read(|view| view.frames_integrated)
                .map_err(errors::core),
            Source::Saved { snapshot, .. } => Ok(snapshot.metadata.frames_integrated),
        }
    }

    /// Point positions, ``float32[N, 3]`` in metres, world frame.
    #[getter]
    fn points<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let positions = match &self.source {
            Source::Live(live) => py
                .detach(|| live.read(|view| view.map.coloured_points().vertices))
                .map_err(errors::core)?,
            Source::Saved { snapshot, .. } => snapshot.positions.clone(),
        };
        let n = positions.len();
        give(py, positions.into_flattened(), &[n, 3])
    }

    /// Point colours, ``uint8[N, 3]`` (RGB).
    #[getter]
    fn colours<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let colours = match &self.source {
            Source::Live(live) => py
                .detach(|| live.read(|view| view.map.coloured_points().colours))
                .map_err(errors::core)?,
            Source::Saved { snapshot, .. } => snapshot.colours.clone(),
        };
        let n = colours.len();
        give(py, colours.into_flattened(), &[n, 3])
    }

    /// Point embeddings, ``float32[N, dim]`` (``dtype="float16"`` halves the memory).
    #[pyo3(signature = (dtype = "float32"))]
    fn embeddings<'py>(&self, py: Python<'py>, dtype: &str) -> PyResult<Bound<'py, PyAny>> {
        let snapshot = self.content(py)?;
        let snapshot = Arc::unwrap_or_clone(snapshot);
        embeddings_array(py, snapshot.embeddings, snapshot.dim, dtype)
    }

    /// Points, colours and embeddings that belong together (one integrated-frame count), as a
    /// dict: ``points``, ``colours``, ``embeddings`` and ``frames_integrated``.
    #[pyo3(signature = (dtype = "float32"))]
    fn snapshot<'py>(&self, py: Python<'py>, dtype: &str) -> PyResult<Bound<'py, PyDict>> {
        let snapshot = Arc::unwrap_or_clone(self.content(py)?);
        let n = snapshot.len();
        let out = PyDict::new(py);
        out.set_item(
            "points",
            give(py, snapshot.positions.into_flattened(), &[n, 3])?,
        )?;
        out.set_item(
            "colours",
            give(py, snapshot.colours.into_flattened(), &[n, 3])?,
        )?;
        out.set_item(
            "embeddings",
            embeddings_array(py, snapshot.embeddings, snapshot.dim, dtype)?,
        )?;
        out.set_item("frames_integrated", snapshot.metadata.frames_integrated)?;
        out.set_item("kind", snapshot.map_kind)?;
        Ok(out)
    }

    /// Every point's similarity to every text: ``float32[N, len(texts)]``, the paper's
    /// normalised cosine similarity ``(text . point + 1) / 2`` in ``[0, 1]``, as the heatmaps and
    /// segmenters use it. A table of more than 4 GiB (``N × len(texts) × 4`` bytes; scoring holds
    /// it twice) raises ``MemoryError`` before anything is scored: ask for fewer texts per call.
    fn scores<'py>(
        &self,
        py: Python<'py>,
        texts: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let texts = texts_from(texts)?;
        let points = match &self.source {
            Source::Live(live) => live.read(|view| view.map.len()).unwrap_or(0),
            Source::Saved { snapshot, .. } => snapshot.len(),
        };
        let bytes = points.saturating_mul(texts.len()).saturating_mul(4);
        if bytes > MAX_SCORE_TABLE_BYTES {
            return Err(pyo3::exceptions::PyMemoryError::new_err(format!(
                "the scores of {} texts over {points} points are a {:.1} GiB table (held twice \
                 while scoring); the limit is {} GiB: ask for fewer texts per call",
                texts.len(),
                bytes as f64 / (1u64 << 30) as f64,
                MAX_SCORE_TABLE_BYTES >> 30
            )));
        }
        let encoder = self.encoder(py)?;
        let segmenter = Selection::threshold()
            .build(&self.build_context())
            .map_err(errors::query)?;
        let scores = py
            .detach(|| -> Result<Vec<Vec<f32>>, vlem_query::QueryError> {
                let embedded = embed_texts(encoder.as_ref(), segmenter.as_ref(), &texts)?;
                match &self.source {
                    Source::Live(live) => Ok(score_live(live, &embedded)?.scores.scores),
                    Source::Saved { snapshot, .. } => {
                        Ok(score_snapshot(snapshot, &embedded)?.scores)
                    }
                }
            })
            .map_err(errors::query)?;
        let n = scores.first().map_or(0, Vec::len);
        let q = scores.len();
        let mut table = vec![0.0f32; n * q];
        for (j, column) in scores.iter().enumerate() {
            for (i, s) in column.iter().enumerate() {
                table[i * q + j] = *s;
            }
        }
        give(py, table, &[n, q])
    }

    /// Answers texts as ``vlem query`` does: per text the best point, the point sets the
    /// segmenter selects (best mean similarity first) and, with ``grasp=True``, a grasp on the
    /// best set.
    ///
    /// Returns a dict: ``segmenter``, ``points``, ``frames_integrated``, ``queries`` (one dict per
    /// text: ``text``, ``best``, ``selected``, ``sets``, ``grasp``, and ``indices``, one
    /// ``int64`` index array per set into ``points``) and ``lines`` (what ``vlem query`` prints).
    #[pyo3(signature = (texts, *, segmenter = "threshold", threshold = None, baseline = None, grasp = false))]
    fn query<'py>(
        &self,
        py: Python<'py>,
        texts: &Bound<'py, PyAny>,
        segmenter: &str,
        threshold: Option<f32>,
        baseline: Option<String>,
        grasp: bool,
    ) -> PyResult<Bound<'py, PyAny>> {
        let texts = texts_from(texts)?;
        if let Some(t) = threshold
            && !t.is_finite()
        {
            return Err(PyValueError::new_err(format!(
                "threshold must be finite, not {t}"
            )));
        }
        let selection = Selection {
            segmenter: segmenter.to_owned(),
            threshold,
            baseline,
        };
        let segmenter = selection
            .build(&self.build_context())
            .map_err(errors::query)?;
        let encoder = self.encoder(py)?;
        let options = AnswerOptions {
            grasp: grasp.then(GraspParams::default),
            indices: false,
        };
        let answered: Answered = py
            .detach(|| match &self.source {
                Source::Live(live) => {
                    let embedded = embed_texts(encoder.as_ref(), segmenter.as_ref(), &texts)?;
                    let scored = score_live(live, &embedded)?;
                    answer(
                        &scored.positions,
                        scored.scores,
                        scored.frames_integrated,
                        segmenter.as_ref(),
                        &options,
                    )
                }
                Source::Saved { snapshot, .. } => answer_snapshot(
                    snapshot,
                    encoder.as_ref(),
                    segmenter.as_ref(),
                    &texts,
                    &options,
                ),
            })
            .map_err(errors::query)?;
        let out = to_python(py, &answered.answer)?;
        let queries = out.get_item("queries")?;
        for (q, query) in queries.try_iter()?.enumerate() {
            let query = query?;
            let mut sets: Vec<_> = answered
                .sets
                .iter()
                .filter(|s| s.query == q && !s.indices.is_empty())
                .collect();
            // The summary lists sets best first; the index arrays follow the same order.
            sets.sort_by(|a, b| b.mean_score.total_cmp(&a.mean_score));
            let indices = PyList::empty(py);
            for set in sets {
                let ids: Vec<i64> = set.indices.iter().map(|&i| i as i64).collect();
                let n = ids.len();
                indices.append(give(py, ids, &[n])?)?;
            }
            query.set_item("indices", indices)?;
        }
        out.set_item("lines", answered.answer.lines())?;
        Ok(out)
    }

    /// Writes the map to a map file (atomically: a crash leaves the old file or none) and
    /// returns the number of points written.
    fn save(&self, py: Python<'_>, path: PathBuf) -> PyResult<usize> {
        py.detach(|| match &self.source {
            Source::Live(live) => live.save(&path).map(|saved| saved.points),
            Source::Saved { snapshot, .. } => {
                vlem_core::write_map_file(&path, snapshot).map(|_| snapshot.len())
            }
        })
        .map_err(errors::core)
    }
}

fn embeddings_array<'py>(
    py: Python<'py>,
    embeddings: Vec<f32>,
    dim: usize,
    dtype: &str,
) -> PyResult<Bound<'py, PyAny>> {
    let n = embeddings.len().checked_div(dim).unwrap_or(0);
    let array = give(py, embeddings, &[n, dim])?;
    match dtype {
        "float32" => Ok(array),
        "float16" => array.call_method1("astype", ("float16",)),
        other => Err(PyValueError::new_err(format!(
            "dtype must be \"float32\" or \"float16\", not {other:?}"
        ))),
    }
}
