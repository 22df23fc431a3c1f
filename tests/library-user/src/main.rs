//! A library user's program: it names only `vlem`, builds a pipeline from a TOML text (a typo in
//! it refused on its line), maps a generated scene, queries the live map, and checks that the
//! features it asked for, and only those, are linked. `.ci/run` runs it; it exits non-zero when a
//! check fails.

use std::process::ExitCode;

use vlem::prelude::*;

const CONFIG: &str = r#"
[dataset]
kind = "synthetic"

[dataset.synthetic]
frames = 6
width = 160
height = 120

[tracker]
kind = "ground-truth"

[encoder]
kind = "colour-names"

[map]
kind = "point-cloud"
"#;

fn main() -> ExitCode {
    match run() {
        Ok(()) => {
            println!("library-user: ok");
            ExitCode::SUCCESS
        }
        Err(message) => {
            eprintln!("library-user: {message}");
            ExitCode::FAILURE
        }
    }
}

fn run() -> Result<(), String> {
    let registry = Registry::global().map_err(|e| e.to_string())?;
    // Linked without a `use … as _;` line: the features are vlem's.
    for (kind, name) in [
        (vlem::core::StageKind::Encoder, "colour-names"),
        (vlem::core::StageKind::Map, "point-cloud"),
        (vlem::core::StageKind::Dataset, "synthetic"),
        (vlem::core::StageKind::Tracker, "ground-truth"),
    ] {
        registry
            .get(kind, name)
            .map_err(|e| format!("{kind} `{name}` is not linked: {e}"))?;
    }
    // Left out by the feature list, and the error says which feature adds it.
    let err = match registry.get(vlem::core::StageKind::Map, "voxel") {
        Ok(_) => return Err("the voxel map is linked though its feature is off".to_owned()),
        Err(e) => e.to_string(),
    };
    if !err.contains("feature") {
        return Err(format!("the unknown-map error names no feature: {err}"));
    }

    // A key the map does not take is refused, on its line of the text the config came from.
    let typo = CONFIG.replace(
        "kind = \"point-cloud\"",
        "kind = \"point-cloud\"\nmax_point = 5",
    );
    let err = match Config::from_toml(&typo) {
        Ok(config) => match Pipeline::from_config(
            &config.with_source_text(typo.as_str(), "user.toml"),
            &BuildContext::default(),
        ) {
            Ok(_) => return Err("a [map] typo was accepted".to_owned()),
            Err(e) => e.to_string(),
        },
        Err(e) => return Err(e.to_string()),
    };
    let line = typo
        .lines()
        .position(|l| l == "max_point = 5")
        .map_or(0, |i| i + 1);
    if !(err.contains("unknown field `max_point`")
        && err.ends_with(&format!("(config user.toml, line {line})")))
    {
        return Err(format!("the typo's error does not name its line: {err}"));
    }

    let config = Config::from_toml(CONFIG).map_err(|e| e.to_string())?;
    let dir = std::env::temp_dir();
    let ctx = BuildContext::for_config_dir(&dir).map_err(|e| e.to_string())?;
    let mut pipeline = Pipeline::from_config(&config, &ctx).map_err(|e| e.to_string())?;
    let mut source = vlem::datasets::open(&config.dataset, &dir).map_err(|e| e.to_string())?;
    let report = pipeline
        .run(source.as_mut(), None, &|_: Progress| {})
        .map_err(|e| e.to_string())?;
    if report.frames_processed != 6 {
        return Err(format!("{} frames mapped, not 6", report.frames_processed));
    }

    let segmenter = Selection::threshold()
        .build(&ctx)
        .map_err(|e| e.to_string())?;
    let texts = vec!["white".to_owned(), "brown".to_owned(), "grey".to_owned()];
    let (answered, positions) = answer_live(
        &pipeline.live(),
        segmenter.as_ref(),
        &texts,
        &AnswerOptions::default(),
    )
    .map_err(|e| e.to_string())?;
    let answer = &answered.answer;
    if positions.is_empty() || answer.points != positions.len() {
        return Err(format!("the map holds {} points", positions.len()));
    }
    if answer.queries.iter().all(|q| q.selected == 0) {
        return Err(format!("no query selected a point: {:?}", answer.queries));
    }
    println!(
        "{} frames mapped into {} points; selected: {:?}",
        report.frames_processed,
        answer.points,
        answer
            .queries
            .iter()
            .map(|q| (&q.text, q.selected))
            .collect::<Vec<_>>()
    );
    Ok(())
}
