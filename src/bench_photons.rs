//! The photon technique's benchmarks: the paper's Table 2 rows, scaling over clients
//! (Figure 5) and the speed/accuracy trade over photon budgets.
//!
//! Table 2 and scaling run the real stages in an in-process cluster — a cloud node and a
//! client node with their own UDP sockets on loopback — and read the stages' reports and the
//! cut edges' transport figures; the client's indirect time and the quality sweep call the
//! kernels directly.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::Context;
use cloudlight::actors::wire::PhotonMsg;
use cloudlight::render::photon::{PackFormat, PhotonSettings, trace_iteration};
use cloudlight::render::raster::{Raster, ShadowSettings, SplatSettings};
use cloudlight::render::{BvhKind, SceneBvh};
use cloudlight::runtime::{MetricsSnapshot, Plan, RunOptions};
use serde_json::{Value, json};

/// Options shared by the cluster benchmarks.
#[derive(Clone, Debug)]
pub struct ClusterBench {
    /// Scene spec.
    pub scene: String,
    /// Photons per iteration.
    pub photons: u64,
    /// Photons per batch.
    pub batch_size: u32,
    /// Iteration period, ms.
    pub interval_ms: f64,
    /// Run length, seconds.
    pub seconds: f64,
    /// Packing.
    pub format: PackFormat,
    /// `[[link]]` profile between cloud and clients (TOML keys), or empty for none.
    pub link: String,
}

/// What one cluster run measured.
pub struct ClusterResult {
    /// The batcher's report.
    pub batcher: Value,
    /// Each client's report.
    pub clients: Vec<Value>,
    /// Final metrics.
    pub metrics: MetricsSnapshot,
}

impl ClusterResult {
    /// Total wire megabits per second leaving the cloud (headers and retransmissions in).
    pub fn wire_mbps(&self) -> f64 {
        self.sending_edges()
            .filter_map(|e| e.wire.as_ref())
            .map(|w| w.wire_mbps)
            .sum()
    }

    /// Total payload megabits per second leaving the cloud.
    pub fn payload_mbps(&self) -> f64 {
        self.sending_edges().map(|e| e.mbps).sum()
    }

    fn sending_edges(&self) -> impl Iterator<Item = &cloudlight::runtime::metrics::EdgeSnapshot> {
        self.metrics
            .edges
            .iter()
            .filter(|e| e.wire.is_some() && !e.name.ends_with("(rx)"))
    }
}

fn num(v: &Value, key: &str) -> f64 {
    v.get(key).and_then(Value::as_f64).unwrap_or(f64::NAN)
}

/// Runs the batcher on a cloud node and `clients` reconstructors (not rendering) on a client
/// node for `b.seconds`.
pub fn run_cluster(
    runtime: &tokio::runtime::Runtime,
    b: &ClusterBench,
    clients: usize,
) -> anyhow::Result<ClusterResult> {
    let format = match b.format {
        PackFormat::Compact12 => "compact12",
        PackFormat::Wide20 => "wide20",
    };
    let mut text = format!(
        r#"techniques = ["photons"]
scene = "{scene}"
seed = 1
duration_s = {seconds}
cluster = "photon-bench"
secret = "photon-bench"
[[node]]
name = "cloud"
address = "127.0.0.1:0"
[[node]]
name = "home"
address = "127.0.0.1:0"
[[stage]]
name = "batcher"
kind = "photon_batcher"
node = "cloud"
params = {{ photons = {photons}, batch_size = {batch}, interval_ms = {interval}, retrace = "always", resend_s = 0.0, format = "{format}" }}
"#,
        scene = b.scene,
        seconds = b.seconds,
        photons = b.photons,
        batch = b.batch_size,
        interval = b.interval_ms,
    );
    if clients > 0 {
        text += &format!(
            r#"[[stage]]
name = "client"
kind = "photon_reconstructor"
node = "home"
replicas = {clients}
params = {{ render = false, fps = 20.0 }}
[[edge]]
from = "batcher.out"
to = "client.in"
capacity = 64
policy = "latest"
"#
        );
    }
    if !b.link.is_empty() {
        text += &format!("[[link]]\nbetween = [\"cloud\", \"home\"]\n{}\n", b.link);
    }
    let registry = cloudlight::actors::registry();
    let plan =
        Plan::from_str("<photon bench>", &text, &registry).map_err(|e| anyhow::anyhow!("{e}"))?;
    let report = runtime
        .block_on(cloudlight::runtime::run(
            &plan,
            &registry,
            RunOptions {
                duration: Some(Duration::from_secs_f64(b.seconds)),
                ..RunOptions::default()
            },
            std::future::pending(),
        ))
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let find = |name: &str| {
        report
            .metrics
            .stages
            .iter()
            .find(|s| s.name == name)
            .and_then(|s| s.report.clone())
            .unwrap_or(Value::Null)
    };
    let single = clients == 1;
    Ok(ClusterResult {
        batcher: find("batcher"),
        clients: (0..clients)
            .map(|i| {
                if single {
                    find("client")
                } else {
                    find(&format!("client[{i}]"))
                }
            })
            .collect(),
        metrics: report.metrics,
    })
}

/// Median wall time of the client's indirect light (G-buffer + splat + upsample, minus the
/// same frame without photons) at `width`×`height`, milliseconds.
fn client_indirect_ms(
    raster: &Raster,
    scene: &cloudlight::scenes::Scene,
    photons: &[cloudlight::render::photon::Photon],
    width: u32,
    height: u32,
    rounds: usize,
) -> anyhow::Result<f64> {
    let tris = scene.triangles_at(0.0);
    let camera = scene
        .cameras
        .first()
        .map(|c| c.at(0.0))
        .context("scene has no camera")?;
    let shadows = ShadowSettings {
        size: 16,
        ..Default::default()
    };
    let time = |p: &[cloudlight::render::photon::Photon]| -> anyhow::Result<f64> {
        let mut v = Vec::new();
        for i in 0..=rounds.max(1) {
            let t = Instant::now();
            raster.photon_frame(
                scene,
                &tris,
                &[],
                &camera,
                width,
                height,
                shadows,
                p,
                SplatSettings::default(),
            )?;
            if i > 0 {
                v.push(t.elapsed().as_secs_f64() * 1000.0);
            }
        }
        v.sort_by(f64::total_cmp);
        Ok(v[v.len() / 2])
    };
    let with = time(photons)?;
    let without = time(&[])?;
    Ok((with - without).max(0.0))
}

/// A Table 2 row: label, JSON key, formatter.
type Row = (&'static str, &'static str, fn(f64) -> String);

/// `cloudlight bench table2 --technique photons`: one column per scene.
#[allow(clippy::too_many_arguments)]
pub fn table2(
    runtime: &tokio::runtime::Runtime,
    scenes: &[String],
    photons: &[u64],
    batch_size: u32,
    interval_ms: f64,
    seconds: f64,
    width: u32,
    height: u32,
    json_path: Option<&Path>,
) -> anyhow::Result<()> {
    let raster = Raster::new()?;
    let mut columns = Vec::new();
    for (i, spec) in scenes.iter().enumerate() {
        let budget = photons.get(i).or(photons.last()).copied().unwrap_or(10_000);
        eprintln!(
            "{spec}: {budget} photons per iteration, running the cloud and a client for {seconds} s..."
        );
        let b = ClusterBench {
            scene: spec.clone(),
            photons: budget,
            batch_size,
            interval_ms,
            seconds,
            format: PackFormat::Compact12,
            link: String::new(),
        };
        let run = run_cluster(runtime, &b, 1)?;
        let bt = &run.batcher;
        let client = run.clients.first().cloned().unwrap_or(Value::Null);
        let batches = num(bt, "batches");
        // Encoding every message of one iteration (what the batcher hands the transport).
        let scene = cloudlight::scenes::load(spec)?;
        let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
        let settings = PhotonSettings::for_budget(&scene, budget, batch_size);
        let it = trace_iteration(&scene, &bvh, 0.0, settings, 1, PackFormat::Compact12);
        let start = Instant::now();
        let mut encoded = 0usize;
        for batch in &it.batches {
            encoded += cloudlight::runtime::codec::encode(&PhotonMsg::Batch(batch.clone()))?.len();
        }
        let encode_ms = start.elapsed().as_secs_f64() * 1000.0;
        let indirect_ms = client_indirect_ms(&raster, &scene, &it.unpacked(), width, height, 3)?;
        columns.push(json!({
            "scene": spec,
            "triangles": scene.triangle_count(),
            "batches": batches,
            "photons_per_batch": num(bt, "batch_size"),
            "photons_per_iteration": budget,
            "memory_footprint_bytes": num(bt, "footprint_bytes"),
            "iteration_interval_ms": num(bt, "iteration_ms_mean"),
            "trace_ms": num(bt, "trace_ms_mean") * batches,
            "packing_ms": num(bt, "pack_ms_mean") * batches,
            "send_ms": encode_ms + num(bt, "send_ms_mean") * (batches + 1.0),
            "encoded_bytes": encoded,
            "iterations": num(bt, "iterations"),
            "interval_target_ms": interval_ms,
            "server_to_client_mbps": run.wire_mbps(),
            "payload_mbps": run.payload_mbps(),
            "client_stored_photons": num(&client, "photons_stored"),
            "client_indirect_ms": indirect_ms,
            "client_resolution": format!("{width}x{height}"),
            "bytes_per_photon": num(bt, "bytes_per_photon"),
        }));
    }
    let rows: [Row; 11] = [
        ("Number of batches", "batches", |v| format!("{v:.0}")),
        ("Photons per batch", "photons_per_batch", |v| {
            format!("{v:.0}")
        }),
        ("Memory footprint", "memory_footprint_bytes", |v| {
            if v >= 1e6 {
                format!("{:.1} MB", v / 1e6)
            } else {
                format!("{:.0} kB", v / 1e3)
            }
        }),
        ("Iteration interval (total)", "iteration_interval_ms", |v| {
            format!("{v:.1} ms")
        }),
        ("Photon trace", "trace_ms", |v| format!("{v:.1} ms")),
        ("Photon packing (12 B/photon)", "packing_ms", |v| {
            format!("{v:.2} ms")
        }),
        ("Send (encode + hand-off)", "send_ms", |v| {
            format!("{v:.2} ms")
        }),
        (
            "Server-to-client bandwidth (mean, wire)",
            "server_to_client_mbps",
            |v| format!("{v:.1} Mbps"),
        ),
        (
            "Local device stored photons",
            "client_stored_photons",
            |v| {
                if v >= 1e3 {
                    format!("{:.1}k", v / 1e3)
                } else {
                    format!("{v:.0}")
                }
            },
        ),
        (
            "Client indirect (splat + upsample)",
            "client_indirect_ms",
            |v| format!("{v:.1} ms"),
        ),
        ("Iterations measured", "iterations", |v| format!("{v:.0}")),
    ];
    let mut md = String::from("| Photons |");
    for c in &columns {
        md += &format!(" {} |", c["scene"].as_str().unwrap_or("?"));
    }
    md += "\n|---|";
    md += &"---|".repeat(columns.len());
    md += "\n";
    md += "| Triangles |";
    for c in &columns {
        md += &format!(" {} |", c["triangles"]);
    }
    md += "\n";
    for (label, key, fmt) in rows {
        md += &format!("| {label} |");
        for c in &columns {
            md += &format!(" {} |", fmt(num(c, key)));
        }
        md += "\n";
    }
    println!("{md}");
    println!(
        "Iterations every {interval_ms} ms with every light re-traced (the paper's continuous stream), \
         1 client over loopback; client indirect at {width}x{height} on {}.",
        raster.adapter().name
    );
    let report = json!({ "technique": "photons", "columns": columns });
    println!("{}", serde_json::to_string_pretty(&report)?);
    if let Some(p) = json_path {
        std::fs::write(p, serde_json::to_string_pretty(&report)?)
            .with_context(|| format!("writing {}", p.display()))?;
    }
    Ok(())
}

/// The campus-like link of the scaling runs.
pub const CAMPUS_LINK: &str =
    "latency_ms = 5.0\njitter_ms = 1.0\nbandwidth_mbps = 1000.0\nloss = 0.001";

/// `cloudlight bench scaling --technique photons`.
pub fn scaling(
    runtime: &tokio::runtime::Runtime,
    b: &ClusterBench,
    counts: &[usize],
    out: &Path,
) -> anyhow::Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let mut rows = Vec::new();
    for &n in counts {
        eprintln!("{n} clients: running for {} s...", b.seconds);
        let run = run_cluster(runtime, b, n)?;
        let ages: Vec<f64> = run.clients.iter().map(|c| num(c, "age_ms_p50")).collect();
        let p99: f64 = run
            .clients
            .iter()
            .map(|c| num(c, "age_ms_p99"))
            .fold(0.0, f64::max);
        let shown = run
            .clients
            .iter()
            .filter(|c| c["indirect_shown"] == true)
            .count();
        rows.push(json!({
            "clients": n,
            "server_iteration_ms": num(&run.batcher, "iteration_ms_mean"),
            "server_trace_ms": num(&run.batcher, "trace_ms_mean") * num(&run.batcher, "batches"),
            "iterations": num(&run.batcher, "iterations"),
            "total_wire_mbps": run.wire_mbps(),
            "total_payload_mbps": run.payload_mbps(),
            "age_ms_p50_mean": ages.iter().sum::<f64>() / ages.len().max(1) as f64,
            "age_ms_p99_max": p99,
            "clients_showing_indirect": shown,
        }));
    }
    println!(
        "| clients | server ms / iteration | trace ms | total Mbps (wire) | age p50 ms (mean over clients) | age p99 ms (worst) | clients showing indirect |"
    );
    println!("|---|---|---|---|---|---|---|");
    for r in &rows {
        println!(
            "| {} | {:.2} | {:.2} | {:.1} | {:.0} | {:.0} | {} |",
            r["clients"],
            num(r, "server_iteration_ms"),
            num(r, "server_trace_ms"),
            num(r, "total_wire_mbps"),
            num(r, "age_ms_p50_mean"),
            num(r, "age_ms_p99_max"),
            r["clients_showing_indirect"]
        );
    }
    let report = json!({ "technique": "photons", "scene": b.scene, "photons": b.photons,
        "interval_ms": b.interval_ms, "seconds": b.seconds, "link": b.link, "rows": rows });
    std::fs::write(
        out.join("scaling.json"),
        serde_json::to_string_pretty(&report)?,
    )?;
    let series = |key: &str| -> Vec<(f64, f64)> {
        rows.iter()
            .map(|r| (num(r, "clients"), num(r, key)))
            .collect()
    };
    let plot = crate::plot::lines(
        &out.join("scaling.png"),
        &format!("Photons, {}: cost per client count", b.scene),
        "clients",
        true,
        &[
            ("server ms per iteration", series("server_iteration_ms")),
            ("total Mbps (wire)", series("total_wire_mbps")),
            ("age of indirect light, p50 ms", series("age_ms_p50_mean")),
        ],
    )?;
    println!(
        "wrote {} and {}",
        out.join("scaling.json").display(),
        plot.display()
    );
    Ok(())
}

/// `cloudlight bench quality --technique photons`.
#[allow(clippy::too_many_arguments)]
pub fn quality(
    scene_spec: &str,
    budgets: &[u64],
    batch_size: u32,
    spp: u32,
    width: u32,
    height: u32,
    rate_hz: f64,
    out: &Path,
) -> anyhow::Result<()> {
    use cloudlight::render::metrics::{PIXELS_PER_DEGREE, REL_MSE_EPSILON, flip_hdr, relmse};
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let scene = cloudlight::scenes::load(scene_spec)?;
    let camera = scene
        .cameras
        .first()
        .map(|c| c.at(0.0))
        .context("scene has no camera")?;
    let tris = scene.triangles_at(0.0);
    let bvh = SceneBvh::build(tris.clone(), BvhKind::default());
    eprintln!("reference: {width}x{height}, {spp} spp, indirect only...");
    let start = Instant::now();
    let reference = cloudlight::render::render(
        &scene,
        &bvh,
        cloudlight::render::RenderSettings {
            width,
            height,
            camera,
            time_s: 0.0,
            seed: 77,
            max_bounces: 64,
        },
        spp,
    )
    .indirect();
    eprintln!("reference took {:.1} s", start.elapsed().as_secs_f64());
    cloudlight::render::image_io::write_exr(
        &out.join("reference_indirect.exr"),
        width,
        height,
        &reference,
    )?;
    let raster = Raster::new()?;
    let mut rows = Vec::new();
    for &budget in budgets {
        let mut row = json!({ "photons": budget });
        // 12-byte photons; 20-byte photons of the same budget (the packing's own error);
        // 20-byte photons of the same bytes (12/20 of the budget: what the bandwidth buys).
        let equal_bytes = (budget * 12 / 20).max(1);
        for (format, photons, tag) in [
            (PackFormat::Compact12, budget, "12"),
            (PackFormat::Wide20, budget, "20"),
            (PackFormat::Wide20, equal_bytes, "20_equal_bytes"),
        ] {
            let settings =
                PhotonSettings::for_budget(&scene, photons, batch_size.min(photons as u32));
            let it = trace_iteration(&scene, &bvh, 0.0, settings, 5, format);
            let frame = raster.photon_frame(
                &scene,
                &tris,
                &[],
                &camera,
                width,
                height,
                ShadowSettings {
                    size: 16,
                    ..Default::default()
                },
                &it.unpacked(),
                SplatSettings::default(),
            )?;
            let e = relmse(&frame.indirect, &reference, REL_MSE_EPSILON);
            let update_ms = (it.trace_time + it.pack_time).as_secs_f64() * 1000.0;
            let bytes = it.data_bytes() as f64;
            let rate = rate_hz.min(1000.0 / update_ms.max(1e-3));
            row[format!("relmse_{tag}")] = json!(e);
            row[format!("kbytes_{tag}")] = json!(bytes / 1e3);
            row[format!("mbps_{tag}")] = json!(bytes * 8.0 * rate / 1e6);
            if tag == "12" {
                let flip = flip_hdr(
                    &frame.indirect,
                    &reference,
                    width,
                    height,
                    PIXELS_PER_DEGREE,
                );
                row["flip"] = json!(flip.mean);
                row["stored"] = json!(it.stored);
                row["radius_m"] = json!(it.radius);
                row["update_ms"] = json!(update_ms);
                row["trace_ms"] = json!(it.trace_time.as_secs_f64() * 1000.0);
                cloudlight::render::image_io::write_exr(
                    &out.join(format!("indirect_{budget}.exr")),
                    width,
                    height,
                    &frame.indirect,
                )?;
            }
        }
        eprintln!("{budget} photons: relMSE {:.5}", num(&row, "relmse_12"));
        rows.push(row);
    }
    println!(
        "| photons | stored | radius cm | update ms | KB/update (12 B) | Mbps @ {rate_hz} Hz (12 B) | relMSE (12 B) | relMSE (20 B) | relMSE (20 B, same bytes) | HDR-FLIP (12 B) |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for r in &rows {
        println!(
            "| {} | {} | {:.2} | {:.1} | {:.1} | {:.2} | {:.5} | {:.5} | {:.5} | {:.4} |",
            r["photons"],
            r["stored"],
            num(r, "radius_m") * 100.0,
            num(r, "update_ms"),
            num(r, "kbytes_12"),
            num(r, "mbps_12"),
            num(r, "relmse_12"),
            num(r, "relmse_20"),
            num(r, "relmse_20_equal_bytes"),
            num(r, "flip"),
        );
    }
    println!(
        "relMSE with ε = {REL_MSE_EPSILON} of the client's indirect radiance ({width}x{height}) against the path tracer's \
         indirect image ({spp} spp), same view and time; Mbps if updated at {rate_hz} Hz or as fast as the update time allows."
    );
    let report = json!({ "technique": "photons", "scene": scene_spec, "spp": spp,
        "width": width, "height": height, "rate_hz": rate_hz, "rows": rows });
    std::fs::write(
        out.join("quality.json"),
        serde_json::to_string_pretty(&report)?,
    )?;
    let points = |x: &str, y: &str| -> Vec<(f64, f64)> {
        rows.iter().map(|r| (num(r, x), num(r, y))).collect()
    };
    let plot = crate::plot::lines(
        &out.join("quality.png"),
        &format!("Photons, {scene_spec}: accuracy, bandwidth and update time per budget"),
        "photons per iteration",
        true,
        &[
            ("relMSE (12 B photons)", points("photons", "relmse_12")),
            ("HDR-FLIP", points("photons", "flip")),
            (
                &format!("Mbps at {rate_hz} Hz (12 B)"),
                points("photons", "mbps_12"),
            ),
            ("update ms (trace + pack)", points("photons", "update_ms")),
        ],
    )?;
    println!(
        "wrote {} and {}",
        out.join("quality.json").display(),
        plot.display()
    );
    Ok(())
}

/// Default output folder of a benchmark.
pub fn default_out(name: &str) -> PathBuf {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    PathBuf::from("runs").join(format!("bench-{name}-{secs}"))
}
