//! An experiment's report: `report.md`, `report.html` (the same, with the runs' videos beside
//! the reference's) and its PNG plots, written from the runs' results.
//!
//! Per link profile: every cut's error beside its latency, bandwidth and costs, and a plot of
//! error against the age of the light and against megabits per second; the error against
//! injected latency (the paper's latency question); a recommendation per link profile and
//! client class: the cut with the least error within the latency and bandwidth budget
//! ([`Budget`]), with the reason.

use std::path::{Path, PathBuf};

use anyhow::Context;
use cloudlight_transport::LinkProfile;
use serde::Serialize;

use super::Experiment;
use super::cuts::ClientClass;
use super::run::{RunResult, common_times};
use crate::bench::table::{Markdown, escape_html, short};
use crate::plot;

/// What a cut may cost to be recommended.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Budget {
    /// Largest age of the indirect light shown, p50, ms: the paper finds up to about half a
    /// second of latency in indirect light hard to notice.
    pub indirect_age_ms: f64,
    /// Largest time from a player's input to the frame showing it, ms, where whole frames
    /// cross the network (the camera is then rendered in the cloud): the link's round trip,
    /// the cloud's frame and encode, and the client's decode. Interactive play wants it
    /// within about 150 ms.
    pub input_to_frame_ms: f64,
    /// Largest share of the link's bandwidth one client's stream may take.
    pub link_share: f64,
}

impl Default for Budget {
    fn default() -> Self {
        Budget {
            indirect_age_ms: 500.0,
            input_to_frame_ms: 150.0,
            link_share: 0.8,
        }
    }
}

impl Budget {
    /// Why `r` over `link` is outside the budget, if it is.
    fn exceeded(&self, r: &RunResult, link: &LinkProfile) -> Option<String> {
        if r.age_ms_p50 > self.indirect_age_ms {
            return Some(format!(
                "its indirect light is {:.0} ms old (p50) > {:.0} ms",
                r.age_ms_p50, self.indirect_age_ms
            ));
        }
        if r.frames_cross {
            let input = 2.0 * (link.latency_ms + f64::from(r.extra_latency_ms))
                + r.cloud_frame_ms.unwrap_or(0.0)
                + r.client_frame_ms_p50;
            if input > self.input_to_frame_ms {
                return Some(format!(
                    "input to frame takes {input:.0} ms (round trip, cloud frame and encode, decode) > {:.0} ms",
                    self.input_to_frame_ms
                ));
            }
        }
        if let Some(bw) = link.bandwidth_mbps
            && r.mbps_per_client > self.link_share * bw
        {
            return Some(format!(
                "{:.1} Mbit/s per client > {:.0}% of the link's {bw} Mbit/s",
                r.mbps_per_client,
                self.link_share * 100.0
            ));
        }
        if r.relmse.is_none() {
            return Some("no sample was compared".into());
        }
        None
    }
}

/// The cut recommended for a link profile and client class.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Recommendation {
    /// Link profile.
    pub link: String,
    /// Client class.
    pub client: ClientClass,
    /// The run chosen (`None`: no cut fits the budget).
    pub run: Option<String>,
    /// Its technique and cut.
    pub choice: Option<String>,
    /// Its relMSE.
    pub relmse: Option<f64>,
    /// Why.
    pub reason: String,
}

/// The recommendation per link profile of `experiment` and client class, from `results`
/// (runs without added latency, the first client count).
pub fn recommend(
    experiment: &Experiment,
    results: &[RunResult],
    budget: &Budget,
) -> Vec<Recommendation> {
    let clients = experiment.clients.first().copied().unwrap_or(1);
    let mut out = Vec::new();
    for link_name in &experiment.links {
        let Some(link) = LinkProfile::named(link_name) else {
            continue;
        };
        for class in ClientClass::ALL {
            let runs: Vec<&RunResult> = results
                .iter()
                .filter(|r| r.ok() && &r.link == link_name)
                .filter(|r| r.extra_latency_ms == 0 && r.clients == clients)
                .filter(|r| r.client_class.is_some_and(|c| c <= class))
                .collect();
            let mut fit: Vec<&RunResult> = Vec::new();
            let mut out_of_budget = Vec::new();
            for r in &runs {
                match budget.exceeded(r, &link) {
                    None => fit.push(r),
                    Some(why) => out_of_budget.push(format!("{} {}: {why}", r.technique, r.cut)),
                }
            }
            fit.sort_by(|a, b| {
                a.relmse
                    .unwrap_or(f64::INFINITY)
                    .total_cmp(&b.relmse.unwrap_or(f64::INFINITY))
            });
            let left_out = if out_of_budget.is_empty() {
                String::new()
            } else {
                format!(" Out of budget: {}.", out_of_budget.join("; "))
            };
            let rec = match fit.first() {
                Some(best) => {
                    let e = |r: &RunResult| r.relmse.unwrap_or(f64::NAN);
                    let next = fit.get(1).map_or(String::new(), |n| {
                        format!("; next: {} {} ({:.3})", n.technique, n.cut, e(n))
                    });
                    // Cuts whose error is within 5% of the least are a tie as far as these
                    // samples tell: say which of them costs the link least.
                    let cheapest = fit
                        .iter()
                        .filter(|r| e(r) <= e(best) * 1.05)
                        .min_by(|a, b| a.mbps_per_client.total_cmp(&b.mbps_per_client))
                        .filter(|c| c.id != best.id && c.mbps_per_client < best.mbps_per_client);
                    let next = match cheapest {
                        Some(c) => format!(
                            "{next}; {} {} is within 5% ({:.3}) at {:.2} Mbit/s against {:.2}",
                            c.technique,
                            c.cut,
                            e(c),
                            c.mbps_per_client,
                            best.mbps_per_client
                        ),
                        None => next,
                    };
                    Recommendation {
                        link: link_name.clone(),
                        client: class,
                        run: Some(best.id.clone()),
                        choice: Some(format!("{} {}", best.technique, best.cut)),
                        relmse: best.relmse,
                        reason: format!(
                            "least relMSE ({:.3}) of the {} cut{} a {} client runs within budget{next}.{left_out}",
                            best.relmse.unwrap_or(f64::NAN),
                            fit.len(),
                            if fit.len() == 1 { "" } else { "s" },
                            class.name(),
                        ),
                    }
                }
                None => Recommendation {
                    link: link_name.clone(),
                    client: class,
                    run: None,
                    choice: None,
                    relmse: None,
                    reason: if runs.is_empty() {
                        format!("no cut a {} client runs was measured.", class.name())
                    } else {
                        format!("no cut fits the budget.{left_out}")
                    },
                },
            };
            out.push(rec);
        }
    }
    out
}

/// A piece of the report, written as Markdown and as HTML.
enum Block {
    Heading(u8, String),
    Text(String),
    Table(Markdown),
    Image(String, String),
    Pictures(String, Vec<(String, String)>),
    Videos(String, Vec<(String, String)>),
}

/// The files a report is.
#[derive(Clone, Debug, Default)]
pub struct Report {
    /// `report.md`.
    pub markdown: PathBuf,
    /// `report.html`.
    pub html: PathBuf,
    /// The plots.
    pub plots: Vec<PathBuf>,
    /// The recommendations (also in `recommendations.json`).
    pub recommendations: Vec<Recommendation>,
}

fn opt(v: Option<f64>, digits: usize) -> String {
    v.map_or("–".into(), |v| format!("{v:.digits$}"))
}

fn about_link(name: &str) -> String {
    let Some(l) = LinkProfile::named(name) else {
        return name.into();
    };
    format!(
        "{} ms ± {} ms one way, {}, {}% loss",
        short(l.latency_ms),
        short(l.jitter_ms),
        l.bandwidth_mbps
            .map_or("unlimited".into(), |b| format!("{} Mbit/s", short(b))),
        short(l.loss * 100.0)
    )
}

/// Writes the report of `results` into `out`.
pub fn write(experiment: &Experiment, results: &[RunResult], out: &Path) -> anyhow::Result<Report> {
    let budget = Budget::default();
    let recommendations = recommend(experiment, results, &budget);
    let mut plots = Vec::new();
    let mut b = Vec::new();
    let m = &experiment.measure;
    b.push(Block::Heading(
        1,
        format!("Experiment `{}`", experiment.name),
    ));
    b.push(Block::Text(format!(
        "Scene `{}`, {} s per run, {} client count{} ({}), link profiles {}. Clients show {}×{} at {} frames/s; \
         every {} s of scene time after {} s, client 0's picture is compared with the reference path tracer's \
         image of the same view at the same scene time ({} samples per pixel), so latency and staleness count as \
         error. relMSE is per channel on radiance divided by the reference's mean luminance (ε = 0.01), over pixels \
         saturated in neither picture; FLIP is LDR-FLIP of the two pictures at one exposure chosen from the reference.",
        experiment.scene,
        experiment.duration_s,
        experiment.clients.len(),
        if experiment.clients.len() == 1 { "" } else { "s" },
        experiment.clients.iter().map(|c| c.to_string()).collect::<Vec<_>>().join(", "),
        experiment.links.join(", "),
        m.width,
        m.height,
        m.fps,
        m.sample_every_s,
        m.warmup_s,
        m.reference_spp,
    )));
    for link in &experiment.links {
        link_section(&mut b, experiment, results, link, out, &mut plots)?;
    }
    latency_section(&mut b, experiment, results, out, &mut plots)?;
    b.push(Block::Heading(2, "Recommendation".into()));
    b.push(Block::Text(format!(
        "Per link profile and client class (thin: decode only; medium: raster; powerful: splatting, or the whole \
         technique), the cut with the least relMSE among those the client runs whose indirect light is at most {:.0} ms \
         old (p50), whose stream takes at most {:.0}% of the link, and, where whole frames cross, whose input-to-frame \
         time (the link's round trip, the cloud's frame and encode, the client's decode) is at most {:.0} ms. Runs \
         without added latency, {} client(s).",
        budget.indirect_age_ms,
        budget.link_share * 100.0,
        budget.input_to_frame_ms,
        experiment.clients.first().copied().unwrap_or(1)
    )));
    let mut t = Markdown::new(&["link", "client", "cut", "relMSE", "why"]);
    for r in &recommendations {
        t.row(vec![
            r.link.clone(),
            format!("{} ({})", r.client.name(), r.client.about()),
            r.choice.clone().unwrap_or("none".into()),
            opt(r.relmse, 3),
            r.reason.clone(),
        ]);
    }
    b.push(Block::Table(t));
    let failed: Vec<&RunResult> = results.iter().filter(|r| !r.ok()).collect();
    if !failed.is_empty() {
        b.push(Block::Heading(2, "Runs that failed".into()));
        let mut t = Markdown::new(&["run", "error"]);
        for r in failed {
            t.row(vec![r.id.clone(), r.error.clone().unwrap_or_default()]);
        }
        b.push(Block::Table(t));
    }
    let markdown = out.join("report.md");
    std::fs::write(&markdown, to_markdown(&b))
        .with_context(|| format!("writing {}", markdown.display()))?;
    let html = out.join("report.html");
    std::fs::write(&html, to_html(&experiment.name, &b))
        .with_context(|| format!("writing {}", html.display()))?;
    let json = out.join("recommendations.json");
    std::fs::write(&json, serde_json::to_string_pretty(&recommendations)?)
        .with_context(|| format!("writing {}", json.display()))?;
    Ok(Report {
        markdown,
        html,
        plots,
        recommendations,
    })
}

/// The runs of `link` without added latency, at the first client count.
fn plain_runs<'r>(
    experiment: &Experiment,
    results: &'r [RunResult],
    link: &str,
) -> Vec<&'r RunResult> {
    let clients = experiment.clients.first().copied().unwrap_or(1);
    results
        .iter()
        .filter(|r| r.link == link && r.extra_latency_ms == 0 && r.clients == clients)
        .collect()
}

fn link_section(
    b: &mut Vec<Block>,
    experiment: &Experiment,
    results: &[RunResult],
    link: &str,
    out: &Path,
    plots: &mut Vec<PathBuf>,
) -> anyhow::Result<()> {
    b.push(Block::Heading(
        2,
        format!("Link `{link}`: {}", about_link(link)),
    ));
    let mut t = Markdown::new(&[
        "technique",
        "cut",
        "client",
        "clients",
        "relMSE",
        "FLIP",
        "energy",
        "age p50 / p99 ms",
        "server ms / update",
        "cloud frame ms",
        "client frame ms",
        "fps",
        "Mbit/s per client",
        "Mbit/s total",
    ]);
    let mut by_technique: Vec<plot::Series> = Vec::new();
    let mut by_technique_bw: Vec<plot::Series> = Vec::new();
    for r in results
        .iter()
        .filter(|r| r.link == link && r.extra_latency_ms == 0)
    {
        if !r.ok() {
            t.row(vec![r.technique.clone(), r.cut.clone(), "failed".into()]);
            continue;
        }
        t.row(vec![
            r.technique.clone(),
            r.cut.clone(),
            r.client_class.map_or("", |c| c.name()).into(),
            r.clients.to_string(),
            opt(r.relmse, 3),
            opt(r.flip, 3),
            opt(r.energy_ratio, 2),
            format!("{:.0} / {:.0}", r.age_ms_p50, r.age_ms_p99),
            opt(r.server_update_ms, 1),
            opt(r.cloud_frame_ms, 1),
            format!("{:.1}", r.client_frame_ms_p50),
            format!("{:.1}", r.fps),
            format!("{:.2}", r.mbps_per_client),
            format!("{:.2}", r.mbps_total),
        ]);
        let Some(e) = r.relmse else { continue };
        for (series, x, tag) in [
            (&mut by_technique, r.age_ms_p50.max(1.0), r.cut.clone()),
            (
                &mut by_technique_bw,
                r.mbps_per_client.max(0.01),
                if r.mbps_per_client < 0.01 {
                    format!("{} (0)", r.cut)
                } else {
                    r.cut.clone()
                },
            ),
        ] {
            match series.iter_mut().find(|s| s.label == r.technique) {
                Some(s) => s.points.push((x, e, tag)),
                None => series.push(plot::Series {
                    label: r.technique.clone(),
                    points: vec![(x, e, tag)],
                }),
            }
        }
    }
    b.push(Block::Table(t));
    if !by_technique.is_empty() {
        let name = format!("error-{link}.png");
        let path = plot::pareto(
            &out.join(&name),
            &format!(
                "{}: what clients show against the reference, over `{link}`",
                experiment.name
            ),
            &[
                plot::ParetoPanel {
                    x_label: "age of the indirect light, p50 (ms)".into(),
                    y_label: "relMSE".into(),
                    series: by_technique,
                    marker: Some(plot::Marker {
                        x: Budget::default().indirect_age_ms,
                        label: "0.5 s".into(),
                    }),
                    floor: None,
                },
                plot::ParetoPanel {
                    x_label: "Mbit/s per client (local cuts at 0.01)".into(),
                    y_label: "relMSE".into(),
                    series: by_technique_bw,
                    marker: LinkProfile::named(link)
                        .and_then(|l| l.bandwidth_mbps)
                        .map(|bw| plot::Marker {
                            x: bw,
                            label: "link".into(),
                        }),
                    floor: None,
                },
            ],
        )?;
        plots.push(path);
        b.push(Block::Image(
            name,
            format!("error against latency and bandwidth over {link}"),
        ));
    }
    let runs = plain_runs(experiment, results, link);
    // The last sample time every run has, pictured side by side.
    let last = runs
        .iter()
        .filter(|r| r.ok() && !r.samples.is_empty())
        .map(|r| r.samples.iter().map(|s| s.time_s).fold(0.0, f64::max))
        .fold(f64::INFINITY, f64::min);
    if last.is_finite() {
        let mut pictures = Vec::new();
        for r in &runs {
            if let Some(s) = r.samples.iter().find(|s| (s.time_s - last).abs() < 1e-6) {
                if pictures.is_empty() {
                    pictures.push(("reference".to_string(), s.reference.clone()));
                }
                pictures.push((format!("{} {}", r.technique, r.cut), s.picture.clone()));
            }
        }
        b.push(Block::Pictures(
            format!("client 0 at scene time {last} s, each cut beside the reference"),
            pictures,
        ));
    }
    let mut videos = vec![("reference".to_string(), REFERENCE_VIDEO.to_string())];
    videos.extend(runs.iter().filter_map(|r| {
        r.recording
            .clone()
            .map(|p| (format!("{} {}", r.technique, r.cut), p))
    }));
    b.push(Block::Videos(
        format!("what client 0 showed over `{link}`, beside the reference tracer's frames of the same camera path"),
        videos,
    ));
    Ok(())
}

/// The reference's video, relative to the output folder.
pub const REFERENCE_VIDEO: &str = "reference/reference.mp4";

fn latency_section(
    b: &mut Vec<Block>,
    experiment: &Experiment,
    results: &[RunResult],
    out: &Path,
    plots: &mut Vec<PathBuf>,
) -> anyhow::Result<()> {
    if experiment.extra_latency_ms.len() < 2 {
        return Ok(());
    }
    b.push(Block::Heading(2, "Error against injected latency".into()));
    b.push(Block::Text(format!(
        "The link's one-way latency lengthened by each amount (the paper's latency video). Where only the \
         indirect light crosses the network, the latency ages the indirect light alone; where frames cross, the \
         whole picture. Each cell: relMSE over the sample moments every run of the row has (a longer link \
         starts showing light later; a moving light makes some moments harder than others), and the age of the \
         light (p50). Scene `{}`{}.",
        experiment.scene,
        if cloudlight_scenes::load(&experiment.scene).is_ok_and(|s| s.is_animated()) {
            " (animated)"
        } else {
            " (nothing in it moves: latency should cost nothing where the client renders)"
        }
    )));
    let mut header = vec!["technique".to_string(), "cut".into(), "link".into()];
    header.extend(
        experiment
            .extra_latency_ms
            .iter()
            .map(|ms| format!("+{ms} ms")),
    );
    header.push("moments compared".into());
    let header: Vec<&str> = header.iter().map(String::as_str).collect();
    let mut t = Markdown::new(&header);
    let mut series = Vec::new();
    let mut answers = Vec::new();
    let mut rows_of_videos = Vec::new();
    let clients = experiment.clients.first().copied().unwrap_or(1);
    for tech in &experiment.techniques {
        for cut in &tech.cuts {
            for link in &experiment.links {
                let row: Vec<Option<&RunResult>> = experiment
                    .extra_latency_ms
                    .iter()
                    .map(|ms| {
                        results.iter().find(|r| {
                            r.technique == tech.name
                                && &r.cut == cut
                                && &r.link == link
                                && r.clients == clients
                                && f64::from(r.extra_latency_ms) == *ms
                        })
                    })
                    .collect();
                let measured: Vec<&RunResult> =
                    row.iter().flatten().copied().filter(|r| r.ok()).collect();
                let times = common_times(&measured);
                let mut cells = vec![tech.name.clone(), cut.clone(), link.clone()];
                cells.extend(row.iter().map(|r| {
                    r.and_then(|r| {
                        Some(format!(
                            "{:.3} ({:.0} ms)",
                            r.relmse_at(&times)?,
                            r.age_ms_p50
                        ))
                    })
                    .unwrap_or("–".into())
                }));
                cells.push(format!("{}", times.len()));
                t.row(cells);
                let points: Vec<(f64, f64)> = measured
                    .iter()
                    .filter_map(|r| Some((f64::from(r.extra_latency_ms), r.relmse_at(&times)?)))
                    .collect();
                if points.len() >= 2 {
                    answers.push(latency_answer(&tech.name, cut, link, &points));
                    series.push((format!("{} {cut} over {link}", tech.name), points));
                }
                let videos: Vec<(String, String)> = row
                    .iter()
                    .flatten()
                    .filter_map(|r| {
                        Some((format!("+{} ms", r.extra_latency_ms), r.recording.clone()?))
                    })
                    .collect();
                if !videos.is_empty() {
                    rows_of_videos.push(Block::Videos(
                        format!("{} {cut} over {link}, latency added", tech.name),
                        videos,
                    ));
                }
            }
        }
    }
    b.push(Block::Table(t));
    for a in answers {
        b.push(Block::Text(a));
    }
    if !series.is_empty() {
        let name = "latency.png".to_string();
        plots.push(plot::linear(
            &out.join(&name),
            &format!("{}: error against injected latency", experiment.name),
            "latency added one way (ms)",
            "relMSE of what the client shows",
            &series,
        )?);
        b.push(Block::Image(name, "error against injected latency".into()));
    }
    b.extend(rows_of_videos);
    Ok(())
}

/// One sentence on how `points` (latency added, relMSE) grow.
fn latency_answer(technique: &str, cut: &str, link: &str, points: &[(f64, f64)]) -> String {
    let (_, e0) = points[0];
    let within = points
        .iter()
        .take_while(|(_, e)| *e <= e0 * 1.1 + 1e-3)
        .last()
        .map_or(0.0, |p| p.0);
    let path: Vec<String> = points
        .iter()
        .map(|(ms, e)| format!("{e:.3} at +{ms:.0} ms"))
        .collect();
    format!(
        "{technique} {cut} over {link}: relMSE {}; within 10% of its error without added latency up to +{within:.0} ms.",
        path.join(" → ")
    )
}

fn to_markdown(blocks: &[Block]) -> String {
    let mut s = String::new();
    for b in blocks {
        match b {
            Block::Heading(level, text) => {
                s += &format!("{} {text}\n\n", "#".repeat(*level as usize))
            }
            Block::Text(text) => s += &format!("{text}\n\n"),
            Block::Table(t) => s += &format!("{}\n", t.render()),
            Block::Image(path, alt) => s += &format!("![{alt}]({path})\n\n"),
            Block::Pictures(caption, items) => {
                s += &format!("{caption}:\n\n");
                for (label, path) in items {
                    s += &format!("![{label}]({path}) ");
                }
                s += "\n\n";
            }
            Block::Videos(caption, items) => {
                s += &format!("Videos, {caption}: ");
                let links: Vec<String> = items
                    .iter()
                    .map(|(label, path)| format!("[{label}]({path})"))
                    .collect();
                s += &format!("{}\n\n", links.join(", "));
            }
        }
    }
    s
}

fn to_html(title: &str, blocks: &[Block]) -> String {
    let mut s = format!(
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{}</title>\n<style>\n\
         body {{ font-family: sans-serif; margin: 2em; max-width: 1400px; }}\n\
         table {{ border-collapse: collapse; margin: 1em 0; }}\n\
         td, th {{ border: 1px solid #bbb; padding: 0.25em 0.5em; text-align: left; }}\n\
         .row {{ display: flex; flex-wrap: wrap; gap: 0.75em; }}\n\
         figure {{ margin: 0; }} figcaption {{ font-size: 0.9em; }}\n\
         img.plot {{ max-width: 100%; }}\n</style></head><body>\n",
        escape_html(title)
    );
    for b in blocks {
        match b {
            Block::Heading(level, text) => {
                s += &format!(
                    "<h{level}>{}</h{level}>\n",
                    escape_html(text).replace('`', "")
                )
            }
            Block::Text(text) => s += &format!("<p>{}</p>\n", escape_html(text).replace('`', "")),
            Block::Table(t) => s += &t.html(),
            Block::Image(path, alt) => {
                s += &format!(
                    "<p><img class=\"plot\" src=\"{}\" alt=\"{}\"></p>\n",
                    escape_html(path),
                    escape_html(alt)
                )
            }
            Block::Pictures(caption, items) => {
                s += &format!("<p>{}</p>\n<div class=\"row\">\n", escape_html(caption));
                for (label, path) in items {
                    s += &format!(
                        "<figure><img src=\"{}\" alt=\"{l}\"><figcaption>{l}</figcaption></figure>\n",
                        escape_html(path),
                        l = escape_html(label)
                    );
                }
                s += "</div>\n";
            }
            Block::Videos(caption, items) => {
                s += &format!(
                    "<p>Videos: {}</p>\n<div class=\"row\">\n",
                    escape_html(caption).replace('`', "")
                );
                for (label, path) in items {
                    s += &format!(
                        "<figure><video src=\"{}\" controls muted loop autoplay playsinline></video><figcaption>{}</figcaption></figure>\n",
                        escape_html(path),
                        escape_html(label)
                    );
                }
                s += "</div>\n";
            }
        }
    }
    s + "</body></html>\n"
}

/// Every file `report.html` in `out` names (images and videos), relative to `out`.
pub fn html_files(html: &str) -> Vec<String> {
    let mut files = Vec::new();
    for part in html.split("src=\"").skip(1) {
        if let Some(end) = part.find('"') {
            files.push(part[..end].replace("&amp;", "&").replace("&quot;", "\""));
        }
    }
    files
}
