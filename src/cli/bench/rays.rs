//! `cloudlight bench rays`: BVH build and ray casting speed, against Embree in the same run.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use cloudlight::render::raybench::{self, Backend, RayBenchReport, RayBenchRow};

/// The targets of TARGETS.md as a fraction of Embree's best mode on the same rays.
fn target(coherent: bool) -> f64 {
    if coherent { 0.5 } else { 0.8 }
}

pub fn run(
    scene: &str,
    threads: &[usize],
    passes: usize,
    against_embree: bool,
    json_path: Option<&PathBuf>,
) -> ExitCode {
    let t = Instant::now();
    let scene = match cloudlight::scenes::load(scene) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(2);
        }
    };
    eprintln!(
        "{}: {} triangles, generated in {:.2} s; {} timed passes (and builds) per figure after a warm-up, backends in turn",
        scene.name,
        scene.triangle_count(),
        t.elapsed().as_secs_f64(),
        passes
    );
    let report = raybench::run(&scene, threads, passes, against_embree, |r| {
        eprintln!(
            "  {:>6} rays, {} thread(s), {:<20} {:7.2} Mrays/s",
            r.rays,
            r.threads,
            r.backend.name(),
            r.mrays_s
        )
    });
    if let Some(why) = &report.embree_unavailable {
        eprintln!("--against-embree: {why}; measured without it");
    }
    print_report(&report);
    let json = serde_json::json!({
        "scene": scene.name,
        "triangles": scene.triangle_count(),
        "passes": passes,
        "ray_sets": report.sets.iter().map(|(n, c)| serde_json::json!({"name": n, "rays": c})).collect::<Vec<_>>(),
        "builds": report.builds.iter().map(|b| serde_json::json!({
            "what": b.what, "threads": b.threads, "seconds": b.seconds})).collect::<Vec<_>>(),
        "reference": report.reference.name(),
        "work_per_ray": report.work.iter().map(|w| serde_json::json!({
            "rays": w.rays, "nodes": w.nodes, "blocks": w.blocks})).collect::<Vec<_>>(),
        "sah": {"nodes": report.sah.0.0, "blocks": report.sah.0.1,
                "inner_nodes": report.sah.1.0, "leaf_blocks": report.sah.1.1},
        "embree_unavailable": report.embree_unavailable,
        "rows": report.rows.iter().map(|r| serde_json::json!({
            "backend": r.backend.name(), "rays": r.rays, "threads": r.threads,
            "mrays_s": r.mrays_s, "min_mrays_s": r.range.0, "max_mrays_s": r.range.1,
            "agreement": r.agreement,
            "of_embree_best": best_embree(&report.rows, r).map(|b| r.mrays_s / b.mrays_s),
        })).collect::<Vec<_>>(),
    });
    println!("{json}");
    if let Err(e) = super::write_json(json_path, &json.to_string()) {
        eprintln!("error: {e}");
        return ExitCode::from(1);
    }
    ExitCode::SUCCESS
}

/// Embree's fastest mode on the same rays at the same thread count.
fn best_embree<'a>(rows: &'a [RayBenchRow], r: &RayBenchRow) -> Option<&'a RayBenchRow> {
    rows.iter()
        .filter(|e| e.backend.is_embree() && e.rays == r.rays && e.threads == r.threads)
        .max_by(|a, b| a.mrays_s.total_cmp(&b.mrays_s))
}

fn print_report(report: &RayBenchReport) {
    let mut builds = crate::cli::table([
        "build",
        "threads",
        "seconds",
        "of Embree MEDIUM (target <= 1.5)",
    ]);
    for b in &report.builds {
        let embree = report
            .builds
            .iter()
            .find(|e| e.what == "Embree MEDIUM" && e.threads == b.threads);
        builds.add_row([
            b.what.to_owned(),
            b.threads.to_string(),
            format!("{:.3}", b.seconds),
            match embree {
                Some(e) if b.what != e.what => format!("{:.2}x", b.seconds / e.seconds),
                _ => String::new(),
            },
        ]);
    }
    println!("{builds}");
    let agrees = format!("agrees with {}", report.reference.name());
    let mut table = crate::cli::table([
        "rays",
        "backend",
        "threads",
        "Mrays/s (median)",
        "min-max",
        &agrees,
        "of Embree's best (target)",
    ]);
    for r in &report.rows {
        let coherent = r.rays == "camera";
        let ratio = match best_embree(&report.rows, r) {
            Some(b) if !r.backend.is_embree() => {
                let x = r.mrays_s / b.mrays_s;
                let met = if x >= target(coherent) {
                    "met"
                } else {
                    "not met"
                };
                format!(
                    "{x:.2} of {} ({} {met})",
                    short(b.backend),
                    target(coherent)
                )
            }
            _ => String::new(),
        };
        table.add_row([
            format!("{} ({})", r.rays, count(report, r.rays)),
            r.backend.name().to_owned(),
            r.threads.to_string(),
            format!("{:.2}", r.mrays_s),
            format!("{:.2}-{:.2}", r.range.0, r.range.1),
            format!("{:.4}%", 100.0 * r.agreement),
            ratio,
        ]);
    }
    println!("{table}");
    let ((sah_nodes, sah_blocks), (nodes, blocks)) = report.sah;
    let mut work = crate::cli::table([
        "BVH8 work per ray",
        "inner nodes (8 boxes each)",
        "leaf blocks (4 triangles each)",
    ]);
    for w in &report.work {
        work.add_row([
            w.rays.to_owned(),
            format!("{:.1}", w.nodes),
            format!("{:.1}", w.blocks),
        ]);
    }
    work.add_row([
        format!("SAH: a line through the root box, no early exit ({nodes} nodes, {blocks} blocks)"),
        format!("{sah_nodes:.1}"),
        format!("{sah_blocks:.1}"),
    ]);
    println!("{work}");
}

fn short(b: Backend) -> &'static str {
    match b {
        Backend::EmbreeOne => "1 ray",
        Backend::EmbreePackets => "packets",
        Backend::EmbreeStream => "streams",
        other => other.name(),
    }
}

fn count(report: &RayBenchReport, set: &str) -> String {
    let n = report
        .sets
        .iter()
        .find(|(s, _)| *s == set)
        .map_or(0, |(_, n)| *n);
    if n >= 1_000_000 {
        format!("{:.2}M", n as f64 / 1e6)
    } else {
        format!("{}k", n / 1000)
    }
}
