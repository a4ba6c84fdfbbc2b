//! PNG plots of benchmark results (plotters, bitmap backend, text in the system's DejaVu
//! Sans through ab_glyph): [`lines`] stacks one panel per series over a shared log x axis;
//! [`pareto`] draws error against cost per configuration, with the Pareto front and a
//! reference mark. Cost axes are logarithmic, error axes linear from 0, ticks at round numbers.

use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use plotters::coord::ranged1d::ValueFormatter;
use plotters::prelude::*;

const FONT_PATHS: [&str; 3] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
];

const COLOURS: [RGBColor; 8] = [
    RGBColor(200, 30, 30),
    RGBColor(30, 90, 200),
    RGBColor(30, 140, 60),
    RGBColor(140, 60, 160),
    RGBColor(230, 140, 20),
    RGBColor(20, 160, 170),
    RGBColor(120, 80, 40),
    RGBColor(90, 90, 90),
];

/// Registers DejaVu Sans as plotters' `sans-serif` once.
fn font() -> anyhow::Result<()> {
    static FONT: OnceLock<Result<(), String>> = OnceLock::new();
    FONT.get_or_init(|| {
        let bytes = FONT_PATHS
            .iter()
            .find_map(|p| std::fs::read(p).ok())
            .ok_or_else(|| {
                "no DejaVu Sans font for plot text (install it: `scripts/setup.sh`, or `apt-get install fonts-dejavu-core`)"
                    .to_string()
            })?;
        plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            Box::leak(bytes.into_boxed_slice()),
        )
        .map_err(|_| "DejaVu Sans could not be read".to_string())
    })
    .clone()
    .map_err(|e| anyhow::anyhow!(e))
}

/// A positive range covering `values` on a log scale, widened to whole decades' round
/// neighbours so that ticks fall on round numbers.
fn log_range(values: impl Iterator<Item = f64>) -> Range<f64> {
    let (lo, hi) = values
        .filter(|v| v.is_finite() && *v > 0.0)
        .fold((f64::INFINITY, 0.0f64), |(a, b), v| (a.min(v), b.max(v)));
    if !lo.is_finite() || hi <= 0.0 {
        return 1.0..10.0;
    }
    let round_down = |v: f64| {
        let d = 10f64.powf(v.log10().floor());
        [5.0, 2.0, 1.0]
            .iter()
            .map(|m| m * d)
            .find(|r| *r <= v)
            .unwrap_or(d)
    };
    let round_up = |v: f64| {
        let d = 10f64.powf(v.log10().floor());
        [1.0, 2.0, 5.0, 10.0]
            .iter()
            .map(|m| m * d)
            .find(|r| *r >= v)
            .unwrap_or(10.0 * d)
    };
    let (a, b) = (round_down(lo * 0.95), round_up(hi * 1.05));
    if b > a { a..b } else { a..a * 10.0 }
}

/// A tick label: round numbers without noise digits.
fn tick(v: &f64) -> String {
    if v.abs() >= 100.0 || *v == 0.0 {
        return format!("{v:.0}");
    }
    let digits = (2 - v.abs().log10().floor() as i32).clamp(1, 8) as usize;
    let s = format!("{v:.digits$}");
    s.trim_end_matches('0').trim_end_matches('.').to_string()
}

fn draw_error(path: &Path) -> impl Fn(Box<dyn std::error::Error + '_>) -> anyhow::Error + '_ {
    move |e| anyhow::anyhow!("drawing {}: {e}", path.display())
}

/// Draws each `(label, points)` series in its own panel, stacked over a shared logarithmic x
/// axis, and writes `path` (PNG).
pub fn lines(
    path: &Path,
    title: &str,
    x_label: &str,
    series: &[(&str, Vec<(f64, f64)>)],
) -> anyhow::Result<PathBuf> {
    font()?;
    let panels = series.len().max(1);
    let root = BitMapBackend::new(path, (900, 40 + 300 * panels as u32)).into_drawing_area();
    let draw = || -> Result<(), Box<dyn std::error::Error + '_>> {
        root.fill(&WHITE)?;
        let root = root.titled(title, ("sans-serif", 22))?;
        let x_range = log_range(series.iter().flat_map(|(_, p)| p.iter().map(|q| q.0)));
        for (i, ((label, points), area)) in series
            .iter()
            .zip(root.split_evenly((panels, 1)).iter())
            .enumerate()
        {
            let finite: Vec<(f64, f64)> = points
                .iter()
                .copied()
                .filter(|(x, y)| *x > 0.0 && x.is_finite() && y.is_finite())
                .collect();
            let top = finite.iter().map(|p| p.1).fold(0.0f64, f64::max);
            let y_range = 0.0..if top > 0.0 { top * 1.15 } else { 1.0 };
            let mut chart = ChartBuilder::on(area)
                .margin(14)
                .x_label_area_size(44)
                .y_label_area_size(80)
                .build_cartesian_2d(x_range.clone().log_scale(), y_range)?;
            chart
                .configure_mesh()
                .x_labels(12)
                .x_desc(x_label)
                .y_desc(*label)
                .x_label_formatter(&tick)
                .y_label_formatter(&tick)
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
    draw().map_err(draw_error(path))?;
    Ok(path.to_path_buf())
}

/// A set of configurations in one colour: (cost, error, label of the point).
#[derive(Clone, Debug, PartialEq)]
pub struct Series {
    /// Legend text.
    pub label: String,
    /// Points: x (cost), y (error), a short tag drawn beside the point.
    pub points: Vec<(f64, f64, String)>,
}

/// A vertical reference line (e.g. the paper's operating point).
#[derive(Clone, Debug, PartialEq)]
pub struct Marker {
    /// Where, in x units.
    pub x: f64,
    /// Its text.
    pub label: String,
}

/// A horizontal reference line: an error no configuration can be told below (e.g. the
/// raster's sampling floor).
#[derive(Clone, Debug, PartialEq)]
pub struct Floor {
    /// Where, in y units.
    pub y: f64,
    /// Its text.
    pub label: String,
}

impl Floor {
    /// The raster's sampling floor of a quality benchmark (`QualityView::sampling_floor`).
    pub fn sampling(y: f64) -> Floor {
        Floor {
            y,
            label: format!("sampling floor {y:.3} (exact light at pixel centres)"),
        }
    }
}

/// One panel of a Pareto plot.
#[derive(Clone, Debug, PartialEq)]
pub struct ParetoPanel {
    /// The cost axis.
    pub x_label: String,
    /// The error axis.
    pub y_label: String,
    /// The configurations.
    pub series: Vec<Series>,
    /// A reference mark.
    pub marker: Option<Marker>,
    /// A floor of the error.
    pub floor: Option<Floor>,
}

/// The points no other point beats in both cost and error, by increasing cost.
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<(f64, f64)> {
    let mut sorted: Vec<(f64, f64)> = points
        .iter()
        .copied()
        .filter(|(x, y)| x.is_finite() && y.is_finite())
        .collect();
    sorted.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
    let mut front: Vec<(f64, f64)> = Vec::new();
    for p in sorted {
        if front.last().is_none_or(|last| p.1 < last.1) {
            front.push(p);
        }
    }
    front
}

fn pareto_panel<'a, 'b: 'a, X, Y>(
    chart: &mut ChartContext<'a, BitMapBackend<'b>, Cartesian2d<X, Y>>,
    panel: &ParetoPanel,
    x_range: &Range<f64>,
    y_range: &Range<f64>,
) -> Result<(), Box<dyn std::error::Error + 'b>>
where
    X: Ranged<ValueType = f64> + ValueFormatter<f64>,
    Y: Ranged<ValueType = f64> + ValueFormatter<f64>,
{
    let all: Vec<(f64, f64)> = panel
        .series
        .iter()
        .flat_map(|s| s.points.iter().map(|p| (p.0, p.1)))
        .filter(|(x, y)| *x > 0.0 && *y >= 0.0)
        .collect();
    let front = pareto_front(&all);
    let grey = RGBColor(90, 90, 90);
    chart
        .draw_series(LineSeries::new(front.iter().copied(), grey.stroke_width(2)))?
        .label("Pareto front")
        .legend(move |(x, y)| PathElement::new([(x, y), (x + 18, y)], grey.stroke_width(2)));
    for (i, s) in panel.series.iter().enumerate() {
        let colour = COLOURS[i % COLOURS.len()];
        let pts: Vec<_> = s
            .points
            .iter()
            .filter(|p| p.0 > 0.0 && p.1 >= 0.0 && p.1.is_finite())
            .cloned()
            .collect();
        chart
            .draw_series(
                pts.iter()
                    .map(|p| Circle::new((p.0, p.1), 5, colour.filled())),
            )?
            .label(s.label.clone())
            .legend(move |(x, y)| Circle::new((x + 9, y), 5, colour.filled()));
        chart.draw_series(pts.iter().map(|p| {
            EmptyElement::at((p.0, p.1))
                + Text::new(
                    p.2.clone(),
                    (7, -16),
                    ("sans-serif", 13).into_font().color(&colour),
                )
        }))?;
    }
    // Reference lines, dashed, with their legend entries.
    let lines = panel
        .marker
        .iter()
        .map(|m| {
            let line = [(m.x, y_range.start), (m.x, y_range.end)];
            (line, RGBColor(0, 0, 0), &m.label)
        })
        .chain(panel.floor.iter().map(|f| {
            let line = [(x_range.start, f.y), (x_range.end, f.y)];
            (line, RGBColor(200, 30, 30), &f.label)
        }));
    for (line, colour, label) in lines {
        chart
            .draw_series(DashedLineSeries::new(line, 6, 4, colour.stroke_width(1)))?
            .label(label.clone())
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 18, y)], colour.stroke_width(1)));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 13))
        .position(SeriesLabelPosition::UpperRight)
        .draw()?;
    Ok(())
}

/// Draws the panels side by side, error against cost on log-log axes, and writes `path`.
pub fn pareto(path: &Path, title: &str, panels: &[ParetoPanel]) -> anyhow::Result<PathBuf> {
    font()?;
    let n = panels.len().max(1) as u32;
    let root = BitMapBackend::new(path, (620 * n, 560)).into_drawing_area();
    let draw = || -> Result<(), Box<dyn std::error::Error + '_>> {
        root.fill(&WHITE)?;
        let root = root.titled(title, ("sans-serif", 22))?;
        for (panel, area) in panels.iter().zip(root.split_evenly((1, n as usize)).iter()) {
            let xs = panel
                .series
                .iter()
                .flat_map(|s| s.points.iter().map(|p| p.0));
            // Headroom on the right for the points' tags.
            let xs: Vec<f64> = xs.chain(panel.marker.iter().map(|m| m.x)).collect();
            let widest = xs.iter().copied().fold(0.0f64, f64::max) * 1.6;
            let x_range = log_range(xs.into_iter().chain([widest]));
            // Errors on a linear axis from 0 (their ticks at round steps), costs on a log one;
            // errors spanning more than 20× (before and after a change that cut them by
            // orders of magnitude) on a log axis too, or the small ones would lie flat on 0.
            let ys: Vec<f64> = panel
                .series
                .iter()
                .flat_map(|s| s.points.iter().map(|p| p.1))
                .chain(panel.floor.iter().map(|f| f.y))
                .filter(|y| y.is_finite())
                .collect();
            let top = ys.iter().copied().fold(0.0f64, f64::max);
            let least = ys
                .iter()
                .copied()
                .filter(|y| *y > 0.0)
                .fold(f64::INFINITY, f64::min);
            let builder = || {
                let mut b = ChartBuilder::on(area);
                b.margin(16).x_label_area_size(48).y_label_area_size(80);
                b
            };
            if top > 20.0 * least {
                let y_range = log_range(ys.iter().copied().chain([top * 1.5]));
                let mut chart = builder()
                    .build_cartesian_2d(x_range.clone().log_scale(), y_range.clone().log_scale())?;
                chart
                    .configure_mesh()
                    .x_labels(12)
                    .y_labels(12)
                    .x_desc(panel.x_label.as_str())
                    .y_desc(format!("{} (log)", panel.y_label))
                    .x_label_formatter(&tick)
                    .y_label_formatter(&tick)
                    .label_style(("sans-serif", 14))
                    .draw()?;
                pareto_panel(&mut chart, panel, &x_range, &y_range)?;
                continue;
            }
            let y_range = 0.0..log_range([top * 1.1].into_iter()).end;
            let mut chart =
                builder().build_cartesian_2d(x_range.clone().log_scale(), y_range.clone())?;
            chart
                .configure_mesh()
                .x_labels(12)
                .y_labels(8)
                .x_desc(panel.x_label.as_str())
                .y_desc(panel.y_label.as_str())
                .x_label_formatter(&tick)
                .y_label_formatter(&tick)
                .label_style(("sans-serif", 14))
                .draw()?;
            pareto_panel(&mut chart, panel, &x_range, &y_range)?;
        }
        root.present()?;
        Ok(())
    };
    draw().map_err(draw_error(path))?;
    Ok(path.to_path_buf())
}

/// Draws `series` (legend text, points) as lines on linear axes from 0, each in its own
/// colour with a legend, and writes `path` (PNG).
pub fn linear(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[(String, Vec<(f64, f64)>)],
) -> anyhow::Result<PathBuf> {
    font()?;
    let root = BitMapBackend::new(path, (900, 560)).into_drawing_area();
    let finite = |p: &&(f64, f64)| p.0.is_finite() && p.1.is_finite();
    let points = || series.iter().flat_map(|(_, p)| p.iter().filter(finite));
    let right = points().map(|p| p.0).fold(0.0f64, f64::max);
    let top = points().map(|p| p.1).fold(0.0f64, f64::max);
    let x_range = 0.0..if right > 0.0 { right * 1.05 } else { 1.0 };
    let y_range = 0.0..log_range([top.max(1e-6) * 1.1].into_iter()).end;
    let draw = || -> Result<(), Box<dyn std::error::Error + '_>> {
        root.fill(&WHITE)?;
        let root = root.titled(title, ("sans-serif", 22))?;
        let mut chart = ChartBuilder::on(&root)
            .margin(16)
            .x_label_area_size(48)
            .y_label_area_size(80)
            .build_cartesian_2d(x_range.clone(), y_range.clone())?;
        chart
            .configure_mesh()
            .x_labels(12)
            .y_labels(8)
            .x_desc(x_label)
            .y_desc(y_label)
            .x_label_formatter(&tick)
            .y_label_formatter(&tick)
            .label_style(("sans-serif", 14))
            .draw()?;
        for (i, (label, pts)) in series.iter().enumerate() {
            let colour = COLOURS[i % COLOURS.len()];
            let pts: Vec<(f64, f64)> = pts.iter().filter(finite).copied().collect();
            chart
                .draw_series(LineSeries::new(pts.clone(), colour.stroke_width(2)))?
                .label(label.as_str())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2))
                });
            chart.draw_series(pts.iter().map(|&p| Circle::new(p, 4, colour.filled())))?;
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 13))
            .position(SeriesLabelPosition::UpperLeft)
            .draw()?;
        root.present()?;
        Ok(())
    };
    draw().map_err(draw_error(path))?;
    Ok(path.to_path_buf())
}

/// Decades of the error map of [`comparison`]: a pixel's relMSE term from 10⁻³ (darkest) to
/// 10 (brightest), log scale.
pub const ERROR_MAP_DECADES: (f64, f64) = (-3.0, 1.0);

/// Draws `test` and `reference` (`width × height`, linear radiance, both tone-mapped at the
/// reference's exposure) and `map` (each pixel's relMSE term,
/// [`cloudlight_render::metrics::relmse_map`]; viridis over [`ERROR_MAP_DECADES`], black where
/// it is 0) side by side, each panel under its title and enlarged to at least 256 pixels
/// wide (8× at most), and writes `path`.
pub fn comparison(
    path: &Path,
    (width, height): (u32, u32),
    test: &[cloudlight_scenes::glam::Vec3],
    reference: &[cloudlight_scenes::glam::Vec3],
    map: &[f64],
    titles: [&str; 3],
) -> anyhow::Result<PathBuf> {
    use cloudlight_render::{image_io, metrics};
    use plotters::style::colors::colormaps::ViridisRGB;
    let n = (width * height) as usize;
    anyhow::ensure!(
        test.len() == n && reference.len() == n && map.len() == n,
        "images of a comparison are not {width}x{height}"
    );
    font()?;
    let zoom = 256u32.div_ceil(width.max(1)).clamp(1, 8);
    let (pw, ph, title_h, gap) = (width * zoom, height * zoom, 28u32, 8u32);
    let size = (3 * pw + 4 * gap, ph + title_h + gap);
    let stops = image_io::auto_exposure(reference);
    let tone = |img: &[cloudlight_scenes::glam::Vec3]| -> Vec<RGBColor> {
        metrics::tonemap(img, stops)
            .chunks_exact(3)
            .map(|c| RGBColor(c[0], c[1], c[2]))
            .collect()
    };
    let (lo, hi) = ERROR_MAP_DECADES;
    let errors: Vec<RGBColor> = map
        .iter()
        .map(|&e| {
            if e > 0.0 {
                ViridisRGB::get_color_normalized(e.log10().clamp(lo, hi), lo, hi)
            } else {
                BLACK
            }
        })
        .collect();
    let panels = [tone(test), tone(reference), errors];
    {
        let root = BitMapBackend::new(path, size).into_drawing_area();
        let err = draw_error(path);
        root.fill(&WHITE).map_err(|e| err(Box::new(e)))?;
        for (k, (pixels, title)) in panels.iter().zip(titles).enumerate() {
            let x0 = gap + k as u32 * (pw + gap);
            root.draw_text(
                title,
                &("sans-serif", 16).into_font().color(&BLACK),
                (x0 as i32, 6),
            )
            .map_err(|e| err(Box::new(e)))?;
            for (i, c) in pixels.iter().enumerate() {
                let (x, y) = ((i as u32 % width) * zoom, (i as u32 / width) * zoom);
                for dy in 0..zoom {
                    for dx in 0..zoom {
                        root.draw_pixel(((x0 + x + dx) as i32, (title_h + y + dy) as i32), c)
                            .map_err(|e| err(Box::new(e)))?;
                    }
                }
            }
        }
        root.present().map_err(|e| err(Box::new(e)))?;
    }
    Ok(path.to_path_buf())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_comparison_draws_three_enlarged_panels_and_refuses_images_of_another_size() {
        use cloudlight_scenes::glam::Vec3;
        let (w, h) = (32u32, 16u32);
        let n = (w * h) as usize;
        let reference: Vec<Vec3> = (0..n).map(|i| Vec3::splat(0.1 + (i % 9) as f32)).collect();
        let mut test = reference.clone();
        test[5] = Vec3::splat(100.0);
        let map = cloudlight_render::metrics::relmse_map(&test, &reference, &vec![true; n]);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.png");
        comparison(
            &path,
            (w, h),
            &test,
            &reference,
            &map,
            ["ours", "reference", "error"],
        )
        .unwrap();
        let img = image::open(&path).unwrap().to_rgb8();
        // Panels enlarged 8× (to 256 wide), under a title row.
        assert_eq!(img.dimensions(), (3 * 256 + 4 * 8, 128 + 28 + 8));
        // The bad pixel is bright in the error map, a good one black (its term is 0).
        let at = |panel: u32, x: u32, y: u32| {
            *img.get_pixel(8 + panel * (256 + 8) + x * 8 + 3, 28 + y * 8 + 3)
        };
        let bad = at(2, 5, 0);
        assert!(
            bad.0.iter().map(|c| *c as u32).sum::<u32>() > 300,
            "{bad:?}"
        );
        assert_eq!(at(2, 6, 0).0, [0, 0, 0]);
        assert_eq!(at(0, 6, 0), at(1, 6, 0));
        assert!(comparison(&path, (w, h + 1), &test, &reference, &map, ["a", "b", "c"]).is_err());
    }

    #[test]
    fn the_pareto_front_keeps_only_undominated_points() {
        let pts = [(1.0, 0.5), (2.0, 0.6), (3.0, 0.2), (4.0, 0.25), (5.0, 0.1)];
        assert_eq!(pareto_front(&pts), vec![(1.0, 0.5), (3.0, 0.2), (5.0, 0.1)]);
    }

    #[test]
    fn log_ranges_and_ticks_are_round() {
        let r = log_range([0.078, 0.149].into_iter());
        assert_eq!((r.start, r.end), (0.05, 0.2));
        let r = log_range([7.4, 275.9].into_iter());
        assert_eq!((r.start, r.end), (5.0, 500.0));
        assert_eq!(tick(&0.05), "0.05");
        assert_eq!(tick(&2.0), "2");
        assert_eq!(tick(&500.0), "500");
        assert_eq!(tick(&0.002), "0.002");
        assert_eq!(tick(&0.15), "0.15");
        assert_eq!(tick(&20.0), "20");
    }
}
