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
            let finite: Vec<(f64, f64)> = points
                .iter()
                .copied()
                .filter(|(x, y)| x.is_finite() && y.is_finite())
                .collect();
            let (x0, x1) = range(finite.iter().map(|p| p.0));
            let (y0, y1) = range(finite.iter().map(|p| p.1));
            let (y0, y1) = (y0.min(0.0), y1 * 1.1);
            let mut builder = ChartBuilder::on(area);
            builder
                .margin(12)
                .x_label_area_size(40)
                .y_label_area_size(70);
            let colour = COLOURS[i % COLOURS.len()];
            if log_x {
                let (x0, x1) = (x0.max(1e-9), x1.max(x0.max(1e-9) * 10.0));
                let mut chart =
                    builder.build_cartesian_2d((x0 * 0.8..x1 * 1.25).log_scale(), y0..y1)?;
                chart
                    .configure_mesh()
                    .x_desc(x_label)
                    .y_desc(*label)
                    .label_style(("sans-serif", 14))
                    .draw()?;
                chart.draw_series(LineSeries::new(
                    finite.iter().copied(),
                    colour.stroke_width(2),
                ))?;
                chart.draw_series(finite.iter().map(|&p| Circle::new(p, 4, colour.filled())))?;
            } else {
                let mut chart = builder.build_cartesian_2d(x0..x1, y0..y1)?;
                chart
                    .configure_mesh()
                    .x_desc(x_label)
                    .y_desc(*label)
                    .label_style(("sans-serif", 14))
                    .draw()?;
                chart.draw_series(LineSeries::new(
                    finite.iter().copied(),
                    colour.stroke_width(2),
                ))?;
                chart.draw_series(finite.iter().map(|&p| Circle::new(p, 4, colour.filled())))?;
            }
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
