//! PNG line plots of benchmark series (plotters, bitmap backend, text with the system's
//! DejaVu Sans through ab_glyph): one panel per series, sharing the x axis.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use anyhow::Context;
use plotters::prelude::*;

const FONT_PATHS: [&str; 3] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
];

const COLOURS: [RGBColor; 4] = [
    RGBColor(200, 30, 30),
    RGBColor(30, 90, 200),
    RGBColor(30, 140, 60),
    RGBColor(140, 60, 160),
];

/// Registers DejaVu Sans as plotters' `sans-serif` once.
fn font() -> anyhow::Result<()> {
    static FONT: OnceLock<Result<(), String>> = OnceLock::new();
    FONT.get_or_init(|| {
        let bytes = FONT_PATHS
            .iter()
            .find_map(|p| std::fs::read(p).ok())
            .ok_or_else(|| {
                "no DejaVu Sans font for plot text (install it: `apt-get install fonts-dejavu-core`)"
                    .to_string()
            })?;
        plotters::style::register_font("sans-serif", FontStyle::Normal, Box::leak(bytes.into_boxed_slice()))
            .map_err(|_| "DejaVu Sans could not be read".to_string())
    })
    .clone()
    .map_err(|e| anyhow::anyhow!(e))
}

/// Draws each `(label, points)` series in its own panel, stacked, and writes `path` (PNG);
/// `log_x` puts the x axis on a log scale.
pub fn lines(
    path: &Path,
    title: &str,
    x_label: &str,
    log_x: bool,
    series: &[(&str, Vec<(f64, f64)>)],
) -> anyhow::Result<PathBuf> {
    font()?;
    let panels = series.len().max(1);
    let root = BitMapBackend::new(path, (900, 300 * panels as u32)).into_drawing_area();
    let draw = || -> Result<(), Box<dyn std::error::Error + '_>> {
        root.fill(&WHITE)?;
        let root = root.titled(title, ("sans-serif", 22))?;
        let areas = root.split_evenly((panels, 1));
        for (i, ((label, points), area)) in series.iter().zip(areas.iter()).enumerate() {
            // A log x axis is drawn as log10(x) on a linear axis, labelled with x.
            let finite: Vec<(f64, f64)> = points
                .iter()
                .copied()
                .filter(|(x, y)| x.is_finite() && y.is_finite() && (!log_x || *x > 0.0))
                .map(|(x, y)| (if log_x { x.log10() } else { x }, y))
                .collect();
            let (x0, x1) = range(finite.iter().map(|p| p.0));
            let (y0, y1) = range(finite.iter().map(|p| p.1));
            let (y0, y1) = (y0.min(0.0), y1 * 1.1);
            let pad = (x1 - x0) * 0.05;
            let mut chart = ChartBuilder::on(area)
                .margin(12)
                .x_label_area_size(40)
                .y_label_area_size(70)
                .build_cartesian_2d(x0 - pad..x1 + pad, y0..y1)?;
            let x_text = |v: &f64| {
                let x = if log_x { 10f64.powf(*v) } else { *v };
                if x.abs() >= 1000.0 || log_x {
                    format!("{:.0}", x)
                } else {
                    format!("{x:.1}")
                }
            };
            chart
                .configure_mesh()
                .x_desc(x_label)
                .y_desc(*label)
                .x_label_formatter(&x_text)
                .label_style(("sans-serif", 14))
                .draw()?;
            let colour = COLOURS[i % COLOURS.len()];
            chart.draw_series(LineSeries::new(
                finite.iter().copied(),
                colour.stroke_width(2),
            ))?;
            chart.draw_series(finite.iter().map(|&p| Circle::new(p, 4, colour.filled())))?;
        }
        root.present()?;
        Ok(())
    };
    draw()
        .map_err(|e| anyhow::anyhow!("{e}"))
        .with_context(|| format!("drawing {}", path.display()))?;
    Ok(path.to_path_buf())
}

fn range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
        (a.min(v), b.max(v))
    });
    if !lo.is_finite() || !hi.is_finite() {
        return (0.0, 1.0);
    }
    if hi - lo < 1e-12 {
        return (lo - 0.5, hi + 0.5);
    }
    (lo, hi)
}
