//! `vlem query`: answer texts on a saved map (`--map`) or on the live map of a running
//! `vlem run --serve` (`--connect`), once or interactively. The answers come from `vlem-query`;
//! this module only prints them and writes the files asked for.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::Args;
use vlem_core::{BuildContext, Encoder, MapSnapshot, PointSet, Segmenter};
use vlem_query::answer::{
    AnswerOptions, Answered, Selection, answer_snapshot, encoder_for_map, slug,
};
use vlem_query::grasp::GraspParams;
use vlem_query::heatmap::{gripper_vertices, heatmap_ply};
use vlem_server::Client;
use vlem_server::api::QueryRequest;

use super::{RerunArgs, one_line};
use crate::output;
use crate::recording::Recorder;

/// `vlem query`.
#[derive(Args)]
pub struct QueryArgs {
    /// Map file written by `vlem run`.
    #[arg(long, required_unless_present = "connect", conflicts_with = "connect")]
    map: Option<PathBuf>,
    /// Address of a running `vlem run --serve ADDR` to query its live map instead.
    #[arg(long, value_name = "127.0.0.1:PORT")]
    connect: Option<String>,
    /// Bearer token of a server started with `--serve-token` (with --connect).
    #[arg(
        long,
        env = "VLEM_SERVE_TOKEN",
        hide_env_values = true,
        value_name = "TOKEN"
    )]
    token: Option<String>,
    /// Write a PLY heatmap (jet colours); with several queries, one file per query.
    #[arg(long)]
    ply: Option<PathBuf>,
    /// How points are selected: `threshold` (similarity ≥ --threshold), `argmax` (the best of
    /// the queries and the baseline "object") or `cluster` (argmax, then GMM on similarity and
    /// DBSCAN on coordinates: one point set per object, best first).
    #[arg(long, default_value = "threshold")]
    segmenter: String,
    /// Normalised similarity at or above which a point counts as a hit (default 0.75 for
    /// `threshold`; for `argmax` and `cluster`, a minimum on top of beating the baseline).
    #[arg(long)]
    threshold: Option<f32>,
    /// The generic text a point must match better to belong to a query, for `argmax` and
    /// `cluster` (default "object"; it must be a text the map's encoder can embed).
    #[arg(long)]
    baseline: Option<String>,
    /// Compute a parallel-gripper grasp (approach from above, +y) on each query's best point
    /// set; with --ply, the gripper is drawn into the heatmap.
    #[arg(long)]
    grasp: bool,
    /// Read queries from standard input, one per line, on the loaded map and encoder (`:help`
    /// lists the commands); with --ply or --rerun, every query updates them.
    #[arg(long)]
    interactive: bool,
    #[command(flatten)]
    rerun: RerunArgs,
    /// Query texts.
    #[arg(required_unless_present = "interactive")]
    text: Vec<String>,
}

/// What answers the queries: a loaded map with its encoder, or a query server.
enum Target {
    Map {
        snapshot: Box<MapSnapshot>,
        encoder: Box<dyn Encoder>,
        segmenter: Box<dyn Segmenter>,
        ctx: BuildContext,
    },
    Server(Client),
}

/// `vlem query`.
///
/// # Errors
/// An unreadable map, an unreachable server, a text the encoder cannot embed (outside
/// `--interactive`, where the session goes on).
pub fn execute(args: QueryArgs) -> Result<()> {
    let mut session = QuerySession::open(args)?;
    let texts = std::mem::take(&mut session.args.text);
    if !texts.is_empty() {
        session.ask(&texts)?;
    }
    if session.args.interactive {
        session.interact()?;
    }
    Ok(())
}

/// Answers queries without reloading the map or the encoder.
struct QuerySession {
    target: Target,
    args: QueryArgs,
    selection: Selection,
    /// The `:threshold` typed for each segmenter in an interactive session: a threshold means
    /// something else to each (a similarity to `threshold`, a minimum to `argmax` and `cluster`),
    /// so switching segmenters takes that segmenter's own, or its default.
    thresholds: std::collections::BTreeMap<String, f32>,
    recorder: Option<Recorder>,
}

impl QuerySession {
    fn open(args: QueryArgs) -> Result<Self> {
        let selection = Selection {
            segmenter: args.segmenter.clone(),
            threshold: args.threshold,
            baseline: args.baseline.clone(),
        };
        let target = match (&args.map, &args.connect) {
            (Some(path), _) => open_map(path, &selection)?,
            (None, Some(address)) => {
                if args.rerun.rerun.is_some() || args.rerun.rerun_connect.is_some() {
                    bail!("--rerun records a loaded map: it does not combine with --connect");
                }
                let client = match &args.token {
                    Some(token) => Client::new(address).with_token(token),
                    None => Client::new(address),
                };
                let status = client.status()?;
                let map = status
                    .map
                    .context("the server's pipeline has no [map]: there is nothing to query")?;
                println!(
                    "{address}: {} points, {}-d embeddings from `{}`, {} frames integrated so far",
                    map.points,
                    map.dim,
                    status.encoder.as_deref().unwrap_or("(none)"),
                    map.frames_integrated
                );
                Target::Server(client)
            }
            (None, None) => bail!("give --map FILE or --connect ADDR"),
        };
        let recorder = args.rerun.open()?;
        if let (Some(recorder), Target::Map { snapshot, .. }) = (&recorder, &target) {
            recorder.log_static_map(&snapshot.positions, &snapshot.colours)?;
        }
        let thresholds = selection
            .threshold
            .map(|t| (selection.segmenter.clone(), t))
            .into_iter()
            .collect();
        Ok(Self {
            target,
            args,
            selection,
            thresholds,
            recorder,
        })
    }

    /// Answers `texts`: the summary lines, grasps, PLY heatmaps and the recording.
    fn ask(&self, texts: &[String]) -> Result<()> {
        match &self.target {
            Target::Map {
                snapshot,
                encoder,
                segmenter,
                ..
            } => {
                let options = AnswerOptions {
                    grasp: self.args.grasp.then(GraspParams::default),
                    indices: false,
                };
                let answered = answer_snapshot(
                    snapshot,
                    encoder.as_ref(),
                    segmenter.as_ref(),
                    texts,
                    &options,
                )?;
                for line in answered.answer.lines() {
                    println!("{line}");
                }
                if let Some(ply) = &self.args.ply {
                    for (i, scores) in answered.scores.scores.iter().enumerate() {
                        let marker = answered
                            .grasps
                            .get(i)
                            .and_then(Option::as_ref)
                            .map(gripper_vertices)
                            .unwrap_or_default();
                        let path = self.ply_path(ply, texts, i);
                        output::write_atomically(
                            &path,
                            &heatmap_ply(&snapshot.positions, scores, &marker),
                        )?;
                        println!("wrote {}", path.display());
                    }
                }
                if let Some(recorder) = &self.recorder {
                    record_answers(recorder, &snapshot.positions, &answered)?;
                }
            }
            Target::Server(client) => {
                let answer = client.query(&QueryRequest {
                    texts: texts.to_vec(),
                    segmenter: Some(self.selection.segmenter.clone()),
                    threshold: self.selection.threshold,
                    baseline: self.selection.baseline.clone(),
                    grasp: self.args.grasp,
                    indices: false,
                })?;
                for line in answer.lines() {
                    println!("{line}");
                }
                if let Some(ply) = &self.args.ply {
                    for (i, text) in texts.iter().enumerate() {
                        let path = self.ply_path(ply, texts, i);
                        output::write_atomically(&path, &client.heatmap(text, self.args.grasp)?)?;
                        println!("wrote {}", path.display());
                    }
                }
            }
        }
        Ok(())
    }

    /// One query on the command line writes FILE itself; several, or a session of queries, write
    /// one file per query beside it.
    fn ply_path(&self, ply: &Path, texts: &[String], i: usize) -> PathBuf {
        if texts.len() == 1 && !self.args.interactive {
            ply.to_path_buf()
        } else {
            let stem = ply
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default();
            ply.with_file_name(format!("{stem}-{}.ply", slug(&texts[i])))
        }
    }

    /// The read-eval loop of `--interactive`: one query per line until `:quit` or end of input.
    fn interact(&mut self) -> Result<()> {
        use std::io::{BufRead, IsTerminal, Write};
        let stdin = std::io::stdin();
        let prompt = stdin.is_terminal();
        println!("type a query, or :help");
        let mut lines = stdin.lock().lines();
        loop {
            if prompt {
                print!("vlem> ");
                std::io::stdout().flush()?;
            }
            let Some(line) = lines.next().transpose()? else {
                break;
            };
            let line = line.trim();
            if line.is_empty() {
                continue;
            }
            let outcome = match line.strip_prefix(':') {
                Some(command) => match self.command(command) {
                    Ok(Continue::Stop) => break,
                    other => other.map(|_| ()),
                },
                None => self.ask(&[line.to_owned()]),
            };
            // A failed query (an unknown word, a bad threshold) does not end the session.
            if let Err(e) = outcome {
                println!("error: {}", one_line(&e));
            }
            std::io::stdout().flush()?;
        }
        Ok(())
    }

    fn command(&mut self, command: &str) -> Result<Continue> {
        let mut words = command.split_whitespace();
        let name = words.next().unwrap_or_default();
        let argument = words.collect::<Vec<_>>().join(" ");
        match name {
            "q" | "quit" | "exit" => return Ok(Continue::Stop),
            "help" | "h" => println!("{INTERACTIVE_HELP}"),
            "threshold" => {
                let value: f32 = argument
                    .parse()
                    .with_context(|| format!(":threshold needs a number, got \"{argument}\""))?;
                self.reconfigure(|s| s.threshold = Some(value))?;
                self.thresholds
                    .insert(self.selection.segmenter.clone(), value);
                println!(
                    "threshold {value} for segmenter `{}`",
                    self.selection.segmenter
                );
            }
            "segmenter" => {
                let own = self.thresholds.get(&argument).copied();
                self.reconfigure(|s| {
                    s.segmenter = argument.clone();
                    s.threshold = own;
                })?;
                println!("segmenter `{}`", self.selection.segmenter);
                self.show();
            }
            "show" => self.show(),
            "baseline" => {
                self.reconfigure(|s| s.baseline = Some(argument.clone()))?;
                println!("baseline \"{argument}\"");
            }
            "grasp" => {
                self.args.grasp = match argument.as_str() {
                    "on" => true,
                    "off" => false,
                    _ => bail!(":grasp takes on or off"),
                };
                println!("grasp {argument}");
            }
            _ => bail!("unknown command :{name} (:help lists them)"),
        }
        Ok(Continue::Go)
    }

    /// Prints the settings the next query uses.
    fn show(&self) {
        let Selection {
            segmenter,
            threshold,
            baseline,
        } = &self.selection;
        let threshold = threshold.map_or_else(|| "its default".to_owned(), |t| t.to_string());
        println!("segmenter `{segmenter}`, threshold {threshold}");
        if segmenter != "threshold" {
            let generic = match &self.target {
                Target::Map { encoder, .. } => encoder.generic_text().to_owned(),
                Target::Server(_) => vlem_core::GENERIC_TEXT.to_owned(),
            };
            println!("baseline \"{}\"", baseline.as_deref().unwrap_or(&generic));
        }
        println!("grasp {}", if self.args.grasp { "on" } else { "off" });
    }

    /// Changes how points are selected (rebuilding a loaded map's segmenter); on failure nothing
    /// changes.
    fn reconfigure(&mut self, change: impl FnOnce(&mut Selection)) -> Result<()> {
        let mut selection = self.selection.clone();
        change(&mut selection);
        if let Target::Map { segmenter, ctx, .. } = &mut self.target {
            *segmenter = selection.build(ctx)?;
        }
        self.selection = selection;
        Ok(())
    }
}

/// Loads a map file and rebuilds the encoder that made it.
fn open_map(path: &Path, selection: &Selection) -> Result<Target> {
    let snapshot = vlem_core::read_map_file(path)?;
    let encoder = encoder_for_map(&snapshot.metadata, &path.display().to_string())?;
    let ctx = BuildContext {
        config_dir: snapshot.metadata.config_dir.clone().unwrap_or_default(),
        embedding_dim: None,
    };
    let segmenter = selection.build(&ctx)?;
    println!(
        "{}: {} points, {}-d embeddings from `{}`",
        path.display(),
        snapshot.len(),
        snapshot.dim,
        encoder.name()
    );
    Ok(Target::Map {
        snapshot: Box::new(snapshot),
        encoder,
        segmenter,
        ctx,
    })
}

/// Logs each query's heatmap, point sets and grasp to `recorder` (no grasps when none were asked
/// for).
pub fn record_answers(
    recorder: &Recorder,
    positions: &[[f32; 3]],
    answered: &Answered,
) -> Result<()> {
    for (q, text) in answered.scores.queries.iter().enumerate() {
        let own: Vec<&PointSet> = answered
            .sets
            .iter()
            .filter(|set| set.query == q && !set.indices.is_empty())
            .collect();
        let Some(s) = answered.scores.scores.get(q) else {
            continue;
        };
        // No grasps at all: none were asked for.
        let grasp = if answered.grasps.is_empty() {
            None
        } else {
            Some(answered.grasps.get(q).and_then(Option::as_ref))
        };
        recorder.log_query(text, positions, s, &own, grasp)?;
    }
    recorder.flush()
}

/// What the interactive loop does after a command.
enum Continue {
    Go,
    Stop,
}

const INTERACTIVE_HELP: &str = "\
a line of text      query the map with it (summary, and --ply / --rerun output)
:threshold X        the current segmenter's threshold (threshold: the similarity a point must
                    reach; argmax and cluster: their minimum); each segmenter keeps its own
:segmenter NAME     threshold, argmax or cluster (as --segmenter), with its own threshold
:show               the settings the next query uses
:baseline TEXT      the generic text argmax and cluster compare against
:grasp on|off       compute a grasp for each query's best point set
:quit               leave (so does end of input)";
