//! The study plot: mIoU against peak resident memory, one marker per cell, one colour per map
//! (the paper's Fig. 4 compares VRAM and mIoU the same way).
//!
//! The SVG keeps its text as SVG text; the PNG needs a TrueType font to rasterise its labels, taken
//! from `VLEM_PLOT_FONT` or the usual system locations (DejaVu, Liberation). Without one only the
//! SVG is written.

use std::path::{Path, PathBuf};

use anyhow::{Result, anyhow};
use plotters::coord::Shift;
use plotters::prelude::*;

use vlem_eval::study::CellResult;

const SIZE: (u32, u32) = (900, 600);
const FONT: &str = "sans-serif";

/// Fonts tried for the PNG, after `VLEM_PLOT_FONT`.
const FONT_CANDIDATES: [&str; 4] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
];

/// A plotted cell: memory in MiB, mIoU in percent, label (the names of its other varying axes),
/// map name (its colour).
struct Point {
    mib: f64,
    miou: f64,
    label: String,
    map: String,
}

/// Writes `OUT/study.svg` and, where a font is found, `OUT/study.png`; returns the files written
/// (none when no cell has both an mIoU and a memory figure).
pub(crate) fn write_plots(out: &Path, results: &[CellResult]) -> Result<Vec<PathBuf>> {
    // Markers are coloured by map; the other axes that differ between cells name each marker.
    let axes: [fn(&CellResult) -> &str; 3] = [|r| &r.sequence, |r| &r.tracker, |r| &r.encoder];
    let varying: Vec<fn(&CellResult) -> &str> = axes
        .into_iter()
        .filter(|axis| results.iter().any(|r| axis(r) != axis(&results[0])))
        .collect();
    let points: Vec<Point> = results
        .iter()
        .filter_map(|r| {
            let miou = r.miou.filter(|m| m.is_finite())?;
            let bytes = r.peak_resident_bytes?;
            Some(Point {
                mib: bytes as f64 / (1024.0 * 1024.0),
                miou: miou * 100.0,
                label: varying
                    .iter()
                    .map(|axis| axis(r))
                    .collect::<Vec<_>>()
                    .join(" / "),
                map: r.map.clone(),
            })
        })
        .collect();
    if points.is_empty() {
        return Ok(Vec::new());
    }
    let font_ready = register_font();
    let mut written = Vec::new();
    let svg = out.join("study.svg");
    // The backends write where they are pointed; draw to a temporary name and rename, so that a
    // reader never sees half a plot.
    let svg_tmp = out.join(".study.svg.tmp");
    draw(SVGBackend::new(&svg_tmp, SIZE).into_drawing_area(), &points)?;
    std::fs::rename(&svg_tmp, &svg)?;
    written.push(svg);
    if font_ready {
        let png = out.join("study.png");
        let png_tmp = out.join(".study.tmp.png");
        draw(
            BitMapBackend::new(&png_tmp, SIZE).into_drawing_area(),
            &points,
        )?;
        std::fs::rename(&png_tmp, &png)?;
        written.push(png);
    } else {
        eprintln!(
            "no TrueType font found for study.png (set VLEM_PLOT_FONT to a .ttf file); study.svg has the same plot"
        );
    }
    Ok(written)
}

/// Registers the first font found under the family name the plot uses; false if none is found.
fn register_font() -> bool {
    static REGISTERED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *REGISTERED.get_or_init(|| {
        let from_env = std::env::var_os("VLEM_PLOT_FONT").map(PathBuf::from);
        let candidates = from_env
            .into_iter()
            .chain(FONT_CANDIDATES.iter().map(PathBuf::from));
        for path in candidates {
            if let Ok(bytes) = std::fs::read(&path) {
                // plotters keeps registered fonts for the life of the process.
                let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                if plotters::style::register_font(FONT, FontStyle::Normal, bytes).is_ok() {
                    return true;
                }
            }
        }
        false
    })
}

fn draw<B: DrawingBackend>(root: DrawingArea<B, Shift>, points: &[Point]) -> Result<()>
where
    B::ErrorType: 'static,
{
    let fail = |e: DrawingAreaErrorKind<B::ErrorType>| anyhow!("cannot draw the study plot: {e}");
    root.fill(&WHITE).map_err(fail)?;
    let (lo, hi) = points.iter().fold((f64::INFINITY, 0f64), |(lo, hi), p| {
        (lo.min(p.mib), hi.max(p.mib))
    });
    let mut chart = ChartBuilder::on(&root);
    chart
        .caption("mIoU against peak resident memory", (FONT, 22))
        .margin(20)
        .x_label_area_size(50)
        .y_label_area_size(60);
    // A log axis once memory spans an order of magnitude (maps differ that much), else linear.
    if hi > 10.0 * lo.max(1.0) {
        let mut chart = chart
            .build_cartesian_2d((lo.max(1.0) / 1.25..hi * 1.25).log_scale(), 0f64..100f64)
            .map_err(fail)?;
        finish_chart(&mut chart, points).map_err(fail)?;
    } else {
        let pad = ((hi - lo) * 0.15).max(1.0);
        let mut chart = chart
            .build_cartesian_2d((lo - pad).max(0.0)..hi + pad, 0f64..100f64)
            .map_err(fail)?;
        finish_chart(&mut chart, points).map_err(fail)?;
    }
    root.present().map_err(fail)?;
    Ok(())
}

/// Axes, one series per map, legend.
fn finish_chart<'a, DB, X>(
    chart: &mut ChartContext<'a, DB, Cartesian2d<X, plotters::coord::types::RangedCoordf64>>,
    points: &[Point],
) -> std::result::Result<(), DrawingAreaErrorKind<DB::ErrorType>>
where
    DB: DrawingBackend + 'a,
    X: Ranged<ValueType = f64> + plotters::coord::ranged1d::ValueFormatter<f64>,
{
    chart
        .configure_mesh()
        .x_desc("peak resident memory of the run [MiB]")
        .y_desc("mIoU [%]")
        .label_style((FONT, 14))
        .draw()?;
    let mut maps: Vec<&str> = points.iter().map(|p| p.map.as_str()).collect();
    maps.sort_unstable();
    maps.dedup();
    for (i, map) in maps.iter().enumerate() {
        let colour = Palette99::pick(i).to_rgba();
        chart
            .draw_series(points.iter().filter(|p| p.map == *map).map(|p| {
                EmptyElement::at((p.mib, p.miou))
                    + Circle::new((0, 0), 6, colour.filled())
                    + Text::new(p.label.clone(), (9, -7), (FONT, 12))
            }))?
            .label(*map)
            .legend(move |(x, y)| Circle::new((x + 10, y), 6, colour.filled()));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font((FONT, 14))
        .draw()
}
