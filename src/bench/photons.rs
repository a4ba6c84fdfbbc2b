//! The photon technique's benchmarks: its [`Technique`] descriptor, the paper's Table 2 rows
//! ([`table2_column`]), the client's frame ([`client_frame`]) and the speed/accuracy sweep over
//! photon budgets ([`quality`]).

use std::path::Path;
use std::time::Instant;

use anyhow::Context;
use cloudlight_actors::client::{ClientParams, ClientReport, Params};
use cloudlight_actors::photon_batcher::{BatcherParams, BatcherReport, Retrace};
use cloudlight_actors::photon_reconstructor::{PhotonClientParams, PhotonClientReport};
use cloudlight_actors::wire::PhotonMsg;
use cloudlight_render::metrics::{ImageErrors, compare};
use cloudlight_render::photon::splat::{PhotonSplatPass, SplatSettings};
use cloudlight_render::photon::{
    Emitter, LightYield, PackFormat, Photon, PhotonSet, PhotonSettings, PhotonStream, Receive,
    View, trace_iteration,
};
use cloudlight_render::raster::{OneFrame, Raster, ShadowSettings};
use cloudlight_render::{BvhKind, SceneBvh};
use cloudlight_scenes::Scene;
use cloudlight_scenes::glam::Vec3;
use serde::{Deserialize, Serialize};

use super::client::{ClientBench, ClientBenchOptions};
use super::table::{Markdown, bytes, count, short};
use super::{
    Bench, CLIENT, ClusterOptions, ClusterRun, Placement, QualityCommon, Row, ScalingRow,
    ServerCost, Side, StageGraph, Sweep, Technique, beside_paper, paper,
};

/// The photon technique.
pub struct Photons;

/// The photon benchmarks' knobs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct PhotonOptions {
    /// Photons per iteration over all lights.
    pub photons: u64,
    /// Photons per batch.
    pub batch_size: u32,
    /// Iteration period, ms (every light is re-traced each iteration).
    pub interval_ms: f64,
    /// Packing.
    pub format: PackFormat,
    /// The client's accumulation buffer downsampling per axis (1, 2 or 4).
    pub downsample: u32,
    /// Photons expected in one splat disk (sets the reference radius).
    pub photons_per_disk: f32,
    /// Each photon's radius from the density of photons around it (false: the reference
    /// radius for all, as before issue 34).
    pub density_radius: bool,
    /// What photons carry to tell which surfaces they light (`normal` or `direction`).
    pub receive: Receive,
    /// The client's accumulation levels (1: every photon at `downsample`; see
    /// [`SplatSettings::levels`]).
    pub levels: u32,
    /// Least radius in texels of a photon's disk at its level ([`SplatSettings::min_texels`]).
    pub min_texels: f32,
    /// The client splats with a compute shader where it can ([`SplatSettings::compute`]).
    pub compute: bool,
    /// The compute splat adds every photon to edge pixels at full resolution
    /// ([`SplatSettings::edges`]).
    pub edges: bool,
    /// The client merges photons within this fraction of their radius before splatting
    /// ([`SplatSettings::merge`]; 0: none).
    pub splat_merge: f32,
    /// The batcher merges each batch's photons within this fraction of their radius
    /// before packing ([`PhotonSettings::merge`]; 0: none).
    pub merge: f32,
    /// Refinement passes of a still light (progressive photon mapping); `bench quality`
    /// measures the error pass by pass when above 1.
    pub passes: u32,
    /// Share of a sun's photons sent toward what the client sees (its view goes upstream
    /// to the batcher; [`PhotonSettings::guide_share`]); 0: uniform over the footprint.
    pub guide: f32,
    /// Reach of the guide, a fraction of the scene's half diagonal
    /// ([`PhotonSettings::guide_reach`]).
    pub guide_reach: f32,
    /// Rounds of photon relaxation per batch ([`PhotonSettings::relax`]; 0: none).
    pub relax: u32,
    /// Halvings of a disk that overhangs its surface at most ([`PhotonSettings::fit`]).
    pub fit: u32,
    /// The client draws a moving light's last `window` generations together; `bench
    /// quality` measures the error generation by generation when above 1.
    pub window: u32,
}

impl Default for PhotonOptions {
    fn default() -> Self {
        PhotonOptions {
            photons: 10_000,
            batch_size: 10_000,
            interval_ms: 33.0,
            format: PackFormat::Compact8,
            downsample: PhotonClientParams::default().downsample,
            photons_per_disk: PhotonSettings::default().photons_per_disk,
            density_radius: PhotonSettings::default().density_radius,
            receive: PhotonSettings::default().receive,
            levels: SplatSettings::default().levels,
            min_texels: SplatSettings::default().min_texels,
            compute: SplatSettings::default().compute,
            edges: SplatSettings::default().edges,
            splat_merge: SplatSettings::default().merge,
            merge: PhotonSettings::default().merge,
            passes: PhotonSettings::default().passes,
            guide: PhotonSettings::default().guide_share,
            guide_reach: PhotonSettings::default().guide_reach,
            relax: PhotonSettings::default().relax,
            fit: PhotonSettings::default().fit,
            window: PhotonClientParams::default().window,
        }
    }
}

impl Photons {
    /// Stage kind computing the photons in the cloud.
    pub const SERVER_KIND: &'static str = "photon_batcher";
    /// Stage kind of a client.
    pub const CLIENT_KIND: &'static str = "photon_reconstructor";

    /// The batcher's `params`.
    pub fn server_params(o: &PhotonOptions) -> anyhow::Result<toml::Table> {
        Ok(toml::Table::try_from(Self::batcher_params(o))?)
    }

    fn batcher_params(o: &PhotonOptions) -> BatcherParams {
        BatcherParams {
            photons: Some(o.photons),
            batch_size: o.batch_size,
            interval_ms: o.interval_ms,
            retrace: Retrace::Always,
            resend_s: 0.0,
            photons_per_disk: o.photons_per_disk,
            density_radius: o.density_radius,
            receive: o.receive,
            passes: o.passes,
            relax: o.relax,
            fit: o.fit,
            merge: o.merge,
            format: o.format.name().into(),
            ..BatcherParams::default()
        }
    }

    /// Refuses options a batcher or a client would refuse, naming the knob and its range.
    fn check(o: &PhotonOptions) -> anyhow::Result<()> {
        use cloudlight_runtime::CheckParams;
        Self::batcher_params(o)
            .check()
            .and_then(|()| Self::client(o).check())
            .map_err(|e| anyhow::anyhow!("--set: {e}"))
    }

    /// The client's own knobs among `o`.
    fn client(o: &PhotonOptions) -> PhotonClientParams {
        PhotonClientParams {
            downsample: o.downsample,
            levels: o.levels,
            min_texels: o.min_texels,
            compute: o.compute,
            edges: o.edges,
            splat_merge: o.splat_merge,
            window: o.window,
        }
    }

    /// A client's `params`: `render` false for a cluster benchmark's clients (they measure,
    /// they do not render); `frame` the shell's settings otherwise.
    pub fn client_params(o: &PhotonOptions, frame: ClientParams) -> anyhow::Result<toml::Table> {
        let params = Params {
            client: frame,
            technique: Self::client(o),
        };
        Ok(params.to_table()?)
    }

    /// The shell settings of a cluster benchmark's clients: no rendering, 20 frames/s.
    pub fn measuring_client() -> ClientParams {
        ClientParams {
            render: false,
            fps: 20.0,
            ..ClientParams::default()
        }
    }
}

impl Technique for Photons {
    const NAME: &'static str = "photons";
    type Options = PhotonOptions;
    type Column = PhotonColumn;

    fn graph(o: &PhotonOptions) -> anyhow::Result<StageGraph> {
        Ok(StageGraph::new(&[Self::NAME])
            .stage(
                "server",
                Self::SERVER_KIND,
                Placement::Shared,
                Self::server_params(o)?,
            )
            .stage(
                CLIENT,
                Self::CLIENT_KIND,
                Placement::PerClient(Side::Home),
                Self::client_params(o, Self::measuring_client())?,
            )
            .edge("server", CLIENT))
    }

    fn scaling_row(run: &ClusterRun, clients: usize) -> anyhow::Result<ScalingRow> {
        let server: BatcherReport = run.report("server")?;
        let reports: Vec<ClientReport<PhotonClientReport>> = run.per_client(CLIENT)?;
        let cost = ServerCost {
            update_ms: server.iteration_ms_mean,
            kernel_ms: server.trace_ms_mean * server.batches as f64,
            updates: server.iterations,
            per_client_ms: None,
        };
        Ok(ScalingRow::of(run, clients, cost, &reports))
    }

    fn scaling_figure() -> (&'static str, &'static str) {
        paper::SCALING_FIGURE
    }

    fn table2_column(
        bench: &Bench,
        options: &PhotonOptions,
        cluster: &ClusterOptions,
        size: (u32, u32),
    ) -> anyhow::Result<PhotonColumn> {
        eprintln!(
            "{}: {} photons per iteration, running the cloud and a client for {} s...",
            cluster.scene, options.photons, cluster.seconds
        );
        table2_column(bench, options, cluster, size)
    }

    fn table2_markdown(columns: &[PhotonColumn]) -> String {
        table2_markdown(columns)
    }

    fn table2_note(o: &PhotonOptions, (width, height): (u32, u32), adapter: &str) -> String {
        format!(
            "Iterations every {} ms with every light re-traced (the paper's continuous stream), 1 client over loopback; \
             client indirect at {width}x{height} on {adapter}. Paper: GeForce Titan cloud, GeForce 670 client.",
            o.interval_ms
        )
    }

    fn client_frame(
        raster: &Raster,
        scene: &Scene,
        o: &PhotonOptions,
        frame: ClientBenchOptions,
    ) -> anyhow::Result<ClientBench> {
        let passes = o.passes.max(1);
        eprintln!(
            "{}: tracing {} photons{}...",
            scene.name,
            o.photons,
            if passes > 1 {
                format!(" a pass, {passes} passes")
            } else {
                String::new()
            }
        );
        let bvh = SceneBvh::at(scene, 0.0, BvhKind::default());
        let settings = PhotonSettings {
            photons_per_disk: o.photons_per_disk,
            density_radius: o.density_radius,
            receive: o.receive,
            passes,
            relax: o.relax,
            fit: o.fit,
            merge: o.merge,
            ..PhotonSettings::for_budget(
                scene,
                o.photons,
                o.batch_size.min(o.photons.max(1) as u32),
            )
        };
        let photons: Vec<Photon> = if passes > 1 {
            // A still light's refinement passes, drawn together as its client draws them
            // (radii shrunk, powers divided by their number).
            let mut stream = PhotonStream::new(settings, o.format, Retrace::Changed, 1);
            let mut set = PhotonSet::new();
            for _ in 0..passes {
                still_pass(&mut stream, &mut set, scene, &bvh);
            }
            set.photons().collect()
        } else if o.window > 1 {
            // A moving light's last generations, drawn together as its client draws them.
            let mut stream = PhotonStream::new(settings, o.format, Retrace::Always, 1);
            let mut set = [PhotonSet::with_window(o.window)];
            generations(
                &mut stream,
                &mut set,
                scene,
                &bvh,
                o.window,
                1000.0 / o.interval_ms,
            );
            set[0].photons().collect()
        } else {
            trace_iteration(scene, &bvh, 0.0, settings, 1, o.format).unpacked()
        };
        let mut bench = client_frame_with(raster, scene, &photons, Self::client(o).splat(), frame)?;
        if passes > 1 {
            bench.indirect =
                bench
                    .indirect
                    .replacen(" photons", &format!(" photons in {passes} passes"), 1);
        } else if o.window > 1 {
            bench.indirect = bench.indirect.replacen(
                " photons",
                &format!(" photons in {} generations", o.window),
                1,
            );
        }
        Ok(bench)
    }

    fn default_sweep() -> Sweep {
        vec![(
            "photons".into(),
            [2500, 5000, 10_000, 40_000, 160_000]
                .into_iter()
                .map(toml::Value::Integer)
                .collect(),
        )]
    }

    fn quality(
        raster: &Raster,
        scene: &str,
        common: &QualityCommon,
        options: &PhotonOptions,
        sweep: &Sweep,
        out: &Path,
    ) -> anyhow::Result<serde_json::Value> {
        let mut budgets = Vec::new();
        let mut knobs = Sweep::new();
        for (key, values) in sweep {
            if key != "photons" {
                knobs.push((key.clone(), values.clone()));
                continue;
            }
            for v in values {
                let n = v.as_integer().filter(|&n| n >= 1).with_context(|| {
                    format!("photon budget `{v}` is not a whole number of at least 1")
                })?;
                budgets.push(n as u64);
            }
        }
        if budgets.is_empty() {
            // A knob sweep alone: `--set photons=N`'s budget, else the default budgets.
            budgets = if options.photons != PhotonOptions::default().photons {
                vec![options.photons]
            } else {
                Self::default_sweep()[0]
                    .1
                    .iter()
                    .filter_map(|v| v.as_integer().map(|n| n as u64))
                    .collect()
            };
        }
        let quality_options = |options: &PhotonOptions| QualityOptions {
            budgets: budgets.clone(),
            batch_size: options.batch_size,
            camera: common.camera.clone(),
            spp: common.spp,
            width: common.width,
            height: common.height,
            rate_hz: common.rate_hz,
            seed: common.seed,
            photons_per_disk: options.photons_per_disk,
            density_radius: options.density_radius,
            receive: options.receive,
            downsample: options.downsample,
            levels: options.levels,
            min_texels: options.min_texels,
            compute: options.compute,
            edges: options.edges,
            splat_merge: options.splat_merge,
            merge: options.merge,
            passes: options.passes,
            guide: options.guide,
            guide_reach: options.guide_reach,
            relax: options.relax,
            fit: options.fit,
            window: options.window,
            still_frames: common.still_frames,
        };
        if knobs.is_empty() {
            Self::check(options)?;
            let o = quality_options(options);
            let rows = quality(raster, scene, &o, out)?;
            return Ok(
                serde_json::json!({ "technique": Self::NAME, "scene": scene, "options": o, "rows": rows }),
            );
        }
        // Every combination of the swept knobs over the others, each checked before any
        // renders, measured into its own folder, and their fronts drawn together.
        let table = toml::Table::try_from(options)?;
        let variants = super::expand::<Self>(&table, &knobs)?;
        let mut labelled = Vec::new();
        for v in &variants {
            Self::check(v)?;
            let t = toml::Table::try_from(v)?;
            let label = knobs
                .iter()
                .map(|(key, _)| format!("{key}={}", t.get(key).map_or(String::new(), show_knob)))
                .collect::<Vec<_>>()
                .join(",");
            labelled.push((label, quality_options(v)));
        }
        let mut fronts = Vec::new();
        for (label, o) in &labelled {
            println!("## {label}\n");
            fronts.push((label.clone(), quality(raster, scene, o, &out.join(label))?));
        }
        let results: Vec<serde_json::Value> = labelled
            .iter()
            .zip(&fronts)
            .map(|((label, o), (_, rows))| serde_json::json!({ "label": label, "options": o, "rows": rows }))
            .collect();
        let report = serde_json::json!({ "technique": Self::NAME, "scene": scene,
            "swept": knobs.iter().map(|(k, _)| k.clone()).collect::<Vec<_>>(), "variants": results });
        let json = out.join("quality.json");
        std::fs::write(&json, serde_json::to_string_pretty(&report)?)
            .with_context(|| format!("writing {}", json.display()))?;
        let png = variants_plot(&out.join("quality.png"), scene, &fronts)?;
        println!(
            "wrote {}, {} (the 8-byte fronts of every combination) and a folder per combination",
            json.display(),
            png.display()
        );
        Ok(report)
    }
}

/// A knob's value as `--sweep` takes it (strings bare).
fn show_knob(v: &toml::Value) -> String {
    match v {
        toml::Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}

/// One column of the photon block of Table 2.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PhotonColumn {
    /// Scene.
    pub scene: String,
    /// Triangles.
    pub triangles: usize,
    /// The paper's scene it is compared with.
    pub paper_scene: &'static str,
    /// Photons per iteration asked for.
    pub photons_per_iteration: u64,
    /// Batches per iteration.
    pub batches: usize,
    /// Photons per batch.
    pub photons_per_batch: u32,
    /// Packed photons held by the server, bytes.
    pub memory_footprint_bytes: usize,
    /// Iteration time, mean, ms.
    pub iteration_interval_ms: f64,
    /// Trace time per iteration, ms.
    pub trace_ms: f64,
    /// Packing time per iteration, ms.
    pub packing_ms: f64,
    /// Encoding an iteration's messages and handing them to the transport, ms.
    pub send_ms: f64,
    /// Encoded bytes per iteration.
    pub encoded_bytes: usize,
    /// Iterations measured.
    pub iterations: u64,
    /// Iteration period asked for, ms.
    pub interval_target_ms: f64,
    /// Server-to-client wire bandwidth, Mbps.
    pub server_to_client_mbps: f64,
    /// Server-to-client payload bandwidth, Mbps.
    pub payload_mbps: f64,
    /// Photons held by the client.
    pub client_stored_photons: usize,
    /// The client's indirect pass (splat + upsample), median, ms.
    pub client_indirect_ms: f64,
    /// Its frame size.
    pub client_resolution: String,
    /// Bytes of data per photon held by the batcher.
    pub bytes_per_photon: f64,
    /// Age of the indirect light at the client, p50, ms.
    pub age_ms_p50: f64,
    /// Age, p99, ms.
    pub age_ms_p99: f64,
}

/// Measures one Table 2 column: the cloud and one client over loopback for
/// `cluster.seconds`, then the client's indirect pass at `width × height` on `raster`.
pub fn table2_column(
    bench: &Bench,
    options: &PhotonOptions,
    cluster: &ClusterOptions,
    (width, height): (u32, u32),
) -> anyhow::Result<PhotonColumn> {
    let raster = bench.raster;
    let run = super::run_cluster::<Photons>(bench.runtime, options, cluster, 1)?;
    let bt: BatcherReport = run.report("server")?;
    let client: ClientReport<PhotonClientReport> = run.report(CLIENT)?;
    let scene = cloudlight_scenes::load(&cluster.scene)?;
    let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
    let settings = PhotonSettings::for_budget(&scene, options.photons, options.batch_size);
    let it = trace_iteration(&scene, &bvh, 0.0, settings, cluster.seed, options.format);
    let start = Instant::now();
    let mut encoded = 0;
    for batch in &it.batches {
        encoded += cloudlight_runtime::codec::encode(&PhotonMsg::Batch(batch.clone()))?.len();
    }
    let encode_ms = start.elapsed().as_secs_f64() * 1000.0;
    let frame = client_frame(
        raster,
        &scene,
        &it.unpacked(),
        ClientBenchOptions {
            width,
            height,
            frames: 5,
            ..Default::default()
        },
    )?;
    let batches = bt.batches as f64;
    Ok(PhotonColumn {
        scene: cluster.scene.clone(),
        triangles: scene.triangle_count(),
        paper_scene: paper::SCENES[paper::nearest_scene(scene.triangle_count() as u64)].name,
        photons_per_iteration: options.photons,
        batches: bt.batches,
        photons_per_batch: bt.batch_size,
        memory_footprint_bytes: bt.footprint_bytes,
        iteration_interval_ms: bt.iteration_ms_mean,
        trace_ms: bt.trace_ms_mean * batches,
        packing_ms: bt.pack_ms_mean * batches,
        send_ms: encode_ms + bt.send_ms_mean * (batches + 1.0),
        encoded_bytes: encoded,
        iterations: bt.iterations,
        interval_target_ms: options.interval_ms,
        server_to_client_mbps: run.wire_mbps(),
        payload_mbps: run.payload_mbps(),
        client_stored_photons: client.technique.photons_stored,
        client_indirect_ms: frame
            .passes
            .iter()
            .find(|p| p.pass == "indirect")
            .map_or(0.0, |p| p.p50_ms),
        client_resolution: format!("{width}x{height}"),
        bytes_per_photon: bt.bytes_per_photon,
        age_ms_p50: client.age_ms_p50,
        age_ms_p99: client.age_ms_p99,
    })
}

/// The photon block of Table 2: our columns, each followed by the paper's column of the
/// nearest scene.
pub fn table2_markdown(columns: &[PhotonColumn]) -> String {
    let rows: [Row<PhotonColumn>; 11] = [
        Row {
            label: "Triangles",
            paper: None,
            cell: |c| c.triangles.to_string(),
        },
        Row {
            label: "Number of batches",
            paper: Some(0),
            cell: |c| c.batches.to_string(),
        },
        Row {
            label: "Photons per batch",
            paper: Some(1),
            cell: |c| c.photons_per_batch.to_string(),
        },
        Row {
            label: "Memory footprint",
            paper: Some(2),
            cell: |c| bytes(c.memory_footprint_bytes as f64),
        },
        Row {
            label: "Iteration interval (total)",
            paper: Some(3),
            cell: |c| format!("{:.1} ms", c.iteration_interval_ms),
        },
        Row {
            label: "Photon trace",
            paper: Some(4),
            cell: |c| format!("{:.1} ms", c.trace_ms),
        },
        Row {
            label: "Photon packing (paper: compaction)",
            paper: Some(5),
            cell: |c| {
                format!(
                    "{:.2} ms ({:.1} B/photon)",
                    c.packing_ms, c.bytes_per_photon
                )
            },
        },
        Row {
            label: "Send: encode + hand-off (paper: GPU to CPU to NIC)",
            paper: Some(6),
            cell: |c| format!("{:.2} ms", c.send_ms),
        },
        Row {
            label: "Server-to-client bandwidth (mean, wire)",
            paper: Some(7),
            cell: |c| format!("{:.1} Mbps", c.server_to_client_mbps),
        },
        Row {
            label: "Local device stored photons",
            paper: Some(8),
            cell: |c| count(c.client_stored_photons as f64),
        },
        Row {
            label: "Client indirect: splat + upsample (paper: local device indirect time)",
            paper: Some(9),
            cell: |c| format!("{:.1} ms at {}", c.client_indirect_ms, c.client_resolution),
        },
    ];
    beside_paper(
        "Photons",
        columns,
        |c| (&c.scene, c.paper_scene),
        &rows,
        &paper::PHOTONS,
    )
}

/// The client's frame with `photons` splatted at the default settings (see
/// [`super::client::measure`]).
pub fn client_frame(
    raster: &Raster,
    scene: &Scene,
    photons: &[Photon],
    options: ClientBenchOptions,
) -> anyhow::Result<ClientBench> {
    client_frame_with(raster, scene, photons, SplatSettings::default(), options)
}

/// [`client_frame`] with these splat settings.
pub fn client_frame_with(
    raster: &Raster,
    scene: &Scene,
    photons: &[Photon],
    splat: SplatSettings,
    options: ClientBenchOptions,
) -> anyhow::Result<ClientBench> {
    let mut pass = PhotonSplatPass::new(raster, splat)?;
    pass.set_photons(raster, photons)?;
    let mut bench = super::client::measure(raster, scene, &mut pass, options)?;
    bench.indirect = format!("{} photons", pass.received_count());
    if pass.photon_count() != pass.received_count() {
        bench.indirect += &format!(", {} splatted (merged)", pass.photon_count());
    }
    Ok(bench)
}

/// The speed/accuracy sweep's settings.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct QualityOptions {
    /// Photon budgets per iteration.
    pub budgets: Vec<u64>,
    /// Photons per batch (at most the budget).
    pub batch_size: u32,
    /// The view ([`QualityCommon::camera`]).
    pub camera: String,
    /// Reference samples per pixel.
    pub spp: u32,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Updates per second the Mbps assume (capped by the update time).
    pub rate_hz: f64,
    /// Seed of the photon streams.
    pub seed: u64,
    /// Photons expected in one splat disk.
    pub photons_per_disk: f32,
    /// Per-photon density radii.
    pub density_radius: bool,
    /// What photons carry to tell which surfaces they light.
    pub receive: Receive,
    /// The client's finest accumulation buffer is this many times smaller per axis.
    pub downsample: u32,
    /// The client's accumulation levels.
    pub levels: u32,
    /// Least radius in texels of a photon's disk at its level.
    pub min_texels: f32,
    /// The client's splat is a compute shader (where the device runs them).
    pub compute: bool,
    /// Its edge pixels splatted at full resolution.
    pub edges: bool,
    /// The client merges photons within this fraction of their radius before splatting
    /// (0: none).
    pub splat_merge: f32,
    /// The batcher merges each batch's photons within this fraction of their radius (0:
    /// none).
    pub merge: f32,
    /// Above 1: the first budget is also measured pass by pass while its lights stand
    /// still, up to this many passes (progressive photon mapping).
    pub passes: u32,
    /// Share of a sun's photons guided toward the view.
    pub guide: f32,
    /// Reach of the guide (fraction of the scene's half diagonal).
    pub guide_reach: f32,
    /// Rounds of photon relaxation per batch.
    pub relax: u32,
    /// Halvings of a disk that overhangs its surface at most.
    pub fit: u32,
    /// Above 1: the first budget is also measured with the client drawing the last 1, 2,
    /// 4, … up to this many generations of a light that changes every iteration.
    pub window: u32,
    /// Frames of the still view the client's image averages, jittered over its pixels.
    pub still_frames: u32,
}

/// One point of the trade: a budget in one packing.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct QualityPoint {
    /// `8 B`, `12 B` or `20 B`.
    pub packing: String,
    /// Photons emitted per update.
    pub photons: u64,
    /// Photons stored.
    pub stored: usize,
    /// Photons sent: those stored, merged by the batcher ([`PhotonSettings::merge`]).
    #[serde(default)]
    pub sent: usize,
    /// Splat radius, m.
    pub radius_m: f32,
    /// Trace + pack time of one update, ms.
    pub update_ms: f64,
    /// Trace time, ms.
    pub trace_ms: f64,
    /// Photon bytes per update, kB.
    pub kbytes: f64,
    /// Bytes of data per photon sent (Compact8's varies with the batch).
    pub bytes_per_photon: f64,
    /// Megabits per second at the update rate.
    pub mbps: f64,
    /// Errors of the client's indirect light against the reference.
    pub errors: ImageErrors,
    /// Photons each light emitted and stored.
    #[serde(default)]
    pub lights: Vec<LightYield>,
}

/// One budget in the three packings (the same photons: each packing's own error and bytes).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct QualityRow {
    /// Photons per update.
    pub photons: u64,
    /// Compact8: ~8 bytes or fewer, coded against neighbours (the default).
    pub eight: QualityPoint,
    /// 12-byte photons.
    pub twelve: QualityPoint,
    /// 20-byte photons (the paper's size).
    pub twenty: QualityPoint,
}

pub use super::QualityView;

impl QualityView {
    /// One update of `photons` in `format`, splatted and compared with the reference;
    /// returns the point and the client's indirect image.
    #[allow(clippy::too_many_arguments)]
    pub fn point(
        &self,
        raster: &Raster,
        packing: &str,
        photons: u64,
        format: PackFormat,
        o: &QualityOptions,
    ) -> anyhow::Result<(QualityPoint, Vec<Vec3>)> {
        let mut stream = self.stream(photons, o, 1, Retrace::Always, format);
        let it = stream.iterate(&self.scene, &self.bvh, 0.0);
        let (errors, indirect) = self.client_errors(raster, &it.unpacked(), o)?;
        let update_ms = (it.trace_time + it.pack_time).as_secs_f64() * 1000.0;
        let bytes = it.data_bytes() as f64;
        let rate = o.rate_hz.min(1000.0 / update_ms.max(1e-3));
        let point = QualityPoint {
            packing: packing.to_string(),
            photons,
            stored: it.stored,
            sent: it.sent,
            radius_m: it.radius,
            update_ms,
            trace_ms: it.trace_time.as_secs_f64() * 1000.0,
            kbytes: bytes / 1e3,
            bytes_per_photon: bytes / it.sent.max(1) as f64,
            mbps: bytes * 8.0 * rate / 1e6,
            errors,
            lights: it.lights.clone(),
        };
        Ok((point, indirect))
    }

    /// The view the client reports upstream: the reference's camera.
    fn view(&self, o: &QualityOptions) -> View {
        View {
            camera: self.camera,
            aspect: o.width as f32 / o.height.max(1) as f32,
        }
    }

    /// The client's indirect light of `photons` (its splat as `o` sets it) against the
    /// reference: the errors and the image.
    fn client_errors(
        &self,
        raster: &Raster,
        photons: &[Photon],
        o: &QualityOptions,
    ) -> anyhow::Result<(ImageErrors, Vec<Vec3>)> {
        let mut pass = PhotonSplatPass::new(
            raster,
            SplatSettings {
                downsample: o.downsample,
                levels: o.levels,
                min_texels: o.min_texels,
                compute: o.compute,
                edges: o.edges,
                merge: o.splat_merge,
                ..SplatSettings::default()
            },
        )?;
        pass.set_photons(raster, photons)?;
        let shadows = ShadowSettings {
            size: 16,
            ..Default::default()
        };
        let size = (o.width, o.height);
        let triangles = self.bvh.triangles();
        let view = OneFrame::new(&self.scene, triangles, &[], &self.camera, size, shadows)
            .with_samples(o.still_frames);
        let frame = raster.read_frame(&view, &mut pass)?;
        let mask: Vec<bool> = frame.coverage.iter().map(|&c| c > 0.0).collect();
        let errors = compare(&frame.indirect, &self.reference, &mask, o.width, o.height);
        Ok((errors, frame.indirect))
    }

    /// One budget in the three packings; the 8-byte (default) client image too.
    pub fn row(
        &self,
        raster: &Raster,
        photons: u64,
        o: &QualityOptions,
    ) -> anyhow::Result<(QualityRow, Vec<Vec3>)> {
        let (eight, image) = self.point(raster, "8 B", photons, PackFormat::Compact8, o)?;
        let (twelve, _) = self.point(raster, "12 B", photons, PackFormat::Compact12, o)?;
        let (twenty, _) = self.point(raster, "20 B", photons, PackFormat::Wide20, o)?;
        Ok((
            QualityRow {
                photons,
                eight,
                twelve,
                twenty,
            },
            image,
        ))
    }
}

/// The error after a number of progressive passes of a still scene.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProgressivePoint {
    /// Passes drawn.
    pub passes: u32,
    /// Scene time they took at the update rate, seconds (passes / rate).
    pub scene_time_s: f64,
    /// Photons drawn.
    pub photons: usize,
    /// Of them, photons splatted after merging ([`SplatSettings::merge`]).
    #[serde(default)]
    pub splatted: usize,
    /// Bytes sent so far, kB.
    pub kbytes: f64,
    /// Errors against the reference.
    pub errors: ImageErrors,
}

impl QualityView {
    /// The scene standing still at time 0, `photons` per iteration: after each pass the
    /// batcher sends (up to `o.passes`), the client's set drawn with its progressive radii
    /// and compared with the reference; measured after 1, 2, 4, … passes and the last:
    /// each point and the client's image then.
    pub fn progressive(
        &self,
        raster: &Raster,
        photons: u64,
        o: &QualityOptions,
    ) -> anyhow::Result<Vec<(ProgressivePoint, Vec<Vec3>)>> {
        let mut stream = self.stream(photons, o, o.passes, Retrace::Changed, PackFormat::Compact8);
        let mut set = PhotonSet::new();
        let (mut points, mut bytes) = (Vec::new(), 0usize);
        for pass in 1..=o.passes {
            bytes += still_pass(&mut stream, &mut set, &self.scene, &self.bvh);
            if !(pass.is_power_of_two() || pass == o.passes) {
                continue;
            }
            let time = pass as f64 / o.rate_hz;
            points.push(self.drawn(raster, &set, o, (pass, "passes"), time, bytes)?);
        }
        Ok(points)
    }

    /// A photon stream of `photons` an iteration as `o` sets it (`passes` for a still
    /// light), its views the reference's.
    fn stream(
        &self,
        photons: u64,
        o: &QualityOptions,
        passes: u32,
        retrace: Retrace,
        format: PackFormat,
    ) -> PhotonStream {
        let settings = PhotonSettings {
            photons_per_disk: o.photons_per_disk,
            density_radius: o.density_radius,
            receive: o.receive,
            passes,
            guide_share: o.guide,
            guide_reach: o.guide_reach,
            relax: o.relax,
            fit: o.fit,
            merge: o.merge,
            ..PhotonSettings::for_budget(
                &self.scene,
                photons,
                o.batch_size.min(photons as u32).max(1),
            )
        };
        let mut stream = PhotonStream::new(settings, format, retrace, o.seed);
        stream.set_views(vec![self.view(o)]);
        stream
    }

    /// One untimed iteration of `photons`: a process's first pays for its thread pool and
    /// its first allocations (Cornell box, 2,500 photons: 15–25 ms against 6 ms after).
    pub fn warm_up(&self, photons: u64, o: &QualityOptions) {
        self.stream(photons, o, 1, Retrace::Always, PackFormat::Compact8)
            .iterate(&self.scene, &self.bvh, 0.0);
    }

    /// What a client holding `set` draws, against the reference: `count` (passes or
    /// generations, as `what` says) drawn, over `scene_time_s`, `bytes` sent.
    fn drawn(
        &self,
        raster: &Raster,
        set: &PhotonSet,
        o: &QualityOptions,
        (count, what): (u32, &str),
        scene_time_s: f64,
        bytes: usize,
    ) -> anyhow::Result<(ProgressivePoint, Vec<Vec3>)> {
        let drawn: Vec<Photon> = set.photons().collect();
        let (errors, image) = self.client_errors(raster, &drawn, o)?;
        let splatted = cloudlight_render::photon::merge::merge(&drawn, o.splat_merge).len();
        eprintln!(
            "{count} {what}: {} photons ({splatted} splatted), relMSE {:.4}, energy {:.3}, worst 1% of pixels {:.0}% of it",
            drawn.len(),
            errors.relmse,
            errors.energy_ratio,
            errors.worst_share * 100.0
        );
        let point = ProgressivePoint {
            passes: count,
            scene_time_s,
            photons: drawn.len(),
            splatted,
            kbytes: bytes as f64 / 1e3,
            errors,
        };
        Ok((point, image))
    }
}

impl QualityView {
    /// Light that changes every iteration (the paper's continuous stream, `retrace =
    /// "always"`; the scene's own animation moves its lights), `photons` per iteration: the
    /// `o.window` iterations up to time 0, one `1 / rate_hz` apart, each into clients that
    /// draw their last 1, 2, 4, … `o.window` generations together; each one's error at time
    /// 0 against the reference (`passes` counts the generations drawn, `scene_time_s` the
    /// span they were traced over, `kbytes` one update's).
    pub fn window(
        &self,
        raster: &Raster,
        photons: u64,
        o: &QualityOptions,
    ) -> anyhow::Result<Vec<(ProgressivePoint, Vec<Vec3>)>> {
        let mut stream = self.stream(photons, o, 1, Retrace::Always, PackFormat::Compact8);
        let windows: Vec<u32> = (1..=o.window)
            .filter(|k| k.is_power_of_two() || *k == o.window)
            .collect();
        let mut sets: Vec<PhotonSet> = windows.iter().map(|&k| PhotonSet::with_window(k)).collect();
        let bytes = generations(
            &mut stream,
            &mut sets,
            &self.scene,
            &self.bvh,
            o.window,
            o.rate_hz,
        );
        let mut points = Vec::new();
        for (&generations, set) in windows.iter().zip(&sets) {
            let span = f64::from(generations - 1) / o.rate_hz;
            points.push(self.drawn(raster, set, o, (generations, "generations"), span, bytes)?);
        }
        Ok(points)
    }
}

/// `count` iterations of `stream` (`bvh` the scene's at time 0) up to time 0, `1 / rate_hz`
/// apart, each into every one of `sets` as a client holds it (the batches, then the
/// manifest): a moving light's generations. The last update's bytes.
fn generations(
    stream: &mut PhotonStream,
    sets: &mut [PhotonSet],
    scene: &Scene,
    bvh: &SceneBvh,
    count: u32,
    rate_hz: f64,
) -> usize {
    let mut bytes = 0;
    for k in 0..count {
        let t = -f64::from(count - 1 - k) / rate_hz;
        let moved;
        let bvh = if scene.has_moving_geometry() {
            moved = SceneBvh::at(scene, t, BvhKind::default());
            &moved
        } else {
            bvh
        };
        let it = stream.iterate(scene, bvh, t);
        bytes = it.data_bytes();
        let manifest = stream.manifest(t);
        for set in sets.iter_mut() {
            for b in &it.batches {
                set.insert(b);
            }
            set.apply_manifest(manifest.clone());
        }
    }
    bytes
}

/// One more iteration of `stream` over a still scene (time 0) into `set`, as a client holds
/// it (the batches, then the manifest): a still light's next refinement pass. Its bytes.
fn still_pass(
    stream: &mut PhotonStream,
    set: &mut PhotonSet,
    scene: &Scene,
    bvh: &SceneBvh,
) -> usize {
    let it = stream.iterate(scene, bvh, 0.0);
    for b in &it.batches {
        set.insert(b);
    }
    set.apply_manifest(stream.manifest(0.0));
    it.data_bytes()
}

/// A table of [`ProgressivePoint`]s under `title`, its first two columns named `first`.
fn points_markdown(points: &[ProgressivePoint], title: &str, first: [&str; 3]) -> String {
    let mut t = Markdown::new(&[
        first[0],
        first[1],
        "photons drawn",
        "splatted (merged)",
        first[2],
        "relMSE",
        "HDR-FLIP",
        "energy ours / reference",
        "worst 1% of pixels' share",
    ]);
    for p in points {
        t.row(vec![
            p.passes.to_string(),
            format!("{:.2}", p.scene_time_s),
            p.photons.to_string(),
            p.splatted.to_string(),
            format!("{:.0}", p.kbytes),
            format!("{:.4}", p.errors.relmse),
            format!("{:.3}", p.errors.flip),
            format!("{:.3}", p.errors.energy_ratio),
            format!("{:.2}", p.errors.worst_share),
        ]);
    }
    format!("{title}:\n\n{}", t.render())
}

/// The moving light's window table.
pub fn window_markdown(points: &[ProgressivePoint], photons: u64) -> String {
    points_markdown(
        points,
        &format!(
            "Light that changes every iteration, {photons} photons an iteration, the client drawing its last \
             generations together (`window`)"
        ),
        ["generations drawn", "traced over s", "KB an update"],
    )
}

/// The progressive table.
pub fn progressive_markdown(points: &[ProgressivePoint], photons: u64) -> String {
    points_markdown(
        points,
        &format!("Still scene, {photons} photons an iteration (progressive photon mapping)"),
        ["passes", "scene time s", "KB sent"],
    )
}

/// The quality table.
pub fn quality_markdown(rows: &[QualityRow], rate_hz: f64) -> String {
    let mut t = Markdown::new(&[
        "photons",
        "stored",
        "sent (merged)",
        "radius cm",
        "update ms (8 B)",
        "B/photon sent (8 B)",
        "KB/update (8 B)",
        &format!("Mbps @ {rate_hz} Hz: 8 B / 12 B"),
        "relMSE (8 B)",
        "relMSE (12 B)",
        "relMSE (20 B)",
        "HDR-FLIP (8 B)",
        "energy ours / reference",
    ]);
    for r in rows {
        let p = &r.eight;
        t.row(vec![
            r.photons.to_string(),
            p.stored.to_string(),
            p.sent.to_string(),
            format!("{:.2}", p.radius_m * 100.0),
            format!("{:.1}", p.update_ms),
            format!("{:.2}", p.bytes_per_photon),
            format!("{:.1}", p.kbytes),
            format!("{:.1} / {:.1}", p.mbps, r.twelve.mbps),
            format!("{:.4}", p.errors.relmse),
            format!("{:.4}", r.twelve.errors.relmse),
            format!("{:.4}", r.twenty.errors.relmse),
            format!("{:.3}", p.errors.flip),
            format!("{:.3}", p.errors.energy_ratio),
        ]);
    }
    t.render()
}

/// Photons stored per photon emitted, budget by budget: over all lights and by kind of
/// light (what a sun's emission over its footprint buys shows apart from its lamps').
pub fn yield_markdown(rows: &[QualityRow]) -> String {
    let kinds: Vec<&str> = Emitter::KINDS
        .into_iter()
        .filter(|k| {
            rows.iter()
                .any(|r| r.eight.lights.iter().any(|l| l.kind == *k))
        })
        .collect();
    let mut header = vec!["photons".to_string(), "all lights".to_string()];
    header.extend(kinds.iter().map(|k| format!("{k} lights")));
    let header: Vec<&str> = header.iter().map(String::as_str).collect();
    let mut t = Markdown::new(&header);
    let cell = |lights: Vec<&LightYield>| {
        let (emitted, stored) = lights
            .iter()
            .fold((0, 0), |(e, s), l| (e + l.emitted, s + l.stored));
        if lights.is_empty() {
            return "-".to_string();
        }
        format!(
            "{:.1}% ({stored} of {emitted}; {} light{})",
            100.0 * stored as f64 / emitted.max(1) as f64,
            lights.len(),
            if lights.len() == 1 { "" } else { "s" }
        )
    };
    for r in rows {
        let lights = &r.eight.lights;
        let mut row = vec![r.photons.to_string(), cell(lights.iter().collect())];
        row.extend(
            kinds
                .iter()
                .map(|k| cell(lights.iter().filter(|l| l.kind == *k).collect())),
        );
        t.row(row);
    }
    format!("Photons stored per photon emitted:\n\n{}", t.render())
}

/// `cloudlight bench quality --technique photons`: the sweep over budgets on `scene`, with
/// the table, `quality.json`, the Pareto plot `quality.png` and each image (EXR, and a PNG
/// beside the reference with its error map: [`QualityView::write_image`]) written to `out`.
pub fn quality(
    raster: &Raster,
    scene_spec: &str,
    o: &QualityOptions,
    out: &Path,
) -> anyhow::Result<Vec<QualityRow>> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let scene = cloudlight_scenes::load(scene_spec)?;
    let view = QualityView::new(scene, &o.camera, o.width, o.height, o.spp)?;
    view.write_reference(out)?;
    if let Some(&first) = o.budgets.first() {
        view.warm_up(first, o);
    }
    let mut rows = Vec::new();
    for &budget in &o.budgets {
        let (row, image) = view.row(raster, budget, o)?;
        eprintln!(
            "{budget} photons: relMSE {:.4}, FLIP {:.3}, energy {:.3}, worst 1% of pixels {:.0}% of it",
            row.eight.errors.relmse,
            row.eight.errors.flip,
            row.eight.errors.energy_ratio,
            row.eight.errors.worst_share * 100.0
        );
        view.write_image(
            out,
            &format!("indirect_{budget}"),
            &image,
            &format!("{budget} photons, 8 B"),
        )?;
        rows.push(row);
    }
    println!("{}", quality_markdown(&rows, o.rate_hz));
    println!("{}", yield_markdown(&rows));
    // Each point's image written beside the reference, named `{name}_{photons}_{count}`.
    let written = |name: &str,
                   what: &str,
                   photons: u64,
                   points: Vec<(ProgressivePoint, Vec<Vec3>)>|
     -> anyhow::Result<Vec<ProgressivePoint>> {
        points
            .into_iter()
            .map(|(point, image)| {
                let label = format!("{photons} photons, {} {what}", point.passes);
                view.write_image(
                    out,
                    &format!("{name}_{photons}_{}", point.passes),
                    &image,
                    &label,
                )?;
                Ok(point)
            })
            .collect()
    };
    let progressive = match (o.passes > 1, o.budgets.first()) {
        (true, Some(&photons)) => {
            let points = view.progressive(raster, photons, o)?;
            let points = written("progressive", "passes", photons, points)?;
            println!("{}", progressive_markdown(&points, photons));
            points
        }
        _ => Vec::new(),
    };
    let window = match (o.window > 1, o.budgets.first()) {
        (true, Some(&photons)) => {
            let points = written(
                "window",
                "generations",
                photons,
                view.window(raster, photons, o)?,
            )?;
            println!("{}", window_markdown(&points, photons));
            points
        }
        _ => Vec::new(),
    };
    println!(
        "relMSE of the client's indirect radiance ({}x{}) against the path tracer's indirect image ({} spp) of the same \
         view and time, both divided by the reference's mean luminance over pixels that see geometry (ε = 0.01 of that \
         mean; the reference's own noise: {:.4}; the raster's sampling floor, what a client shading each pixel's \
         centre with exact light would show: {:.4}); Mbps if updated at {} Hz or as fast as the update allows. Paper's \
         operating point: 10k photons, {} Mbps, {} ms.",
        o.width,
        o.height,
        o.spp,
        view.reference_noise,
        view.sampling_floor,
        o.rate_hz,
        paper::PHOTON_OPERATING_POINT.0,
        paper::PHOTON_OPERATING_POINT.1
    );
    let report = serde_json::json!({ "technique": "photons", "scene": scene_spec, "options": o,
        "reference_seconds": view.reference_s, "reference_noise": view.reference_noise, "sampling_floor": view.sampling_floor, "rows": rows, "progressive": progressive, "window": window });
    let json = out.join("quality.json");
    std::fs::write(&json, serde_json::to_string_pretty(&report)?)
        .with_context(|| format!("writing {}", json.display()))?;
    let png = quality_plot(
        &out.join("quality.png"),
        scene_spec,
        &rows,
        view.sampling_floor,
    )?;
    println!("wrote {} and {}", json.display(), png.display());
    Ok(rows)
}

/// The Pareto plot of a knob sweep: each combination's 8-byte photons.
fn variants_plot(
    path: &Path,
    scene: &str,
    fronts: &[(String, Vec<QualityRow>)],
) -> anyhow::Result<std::path::PathBuf> {
    let sets: Vec<Front> = fronts
        .iter()
        .map(|(label, rows)| {
            (
                label.clone(),
                rows.iter().map(|r| (&r.eight).into()).collect(),
            )
        })
        .collect();
    fronts_plot(
        path,
        &format!("Photons, {scene}: error against bandwidth and update time (8-byte photons)"),
        &sets,
        None,
    )
}

/// The Pareto plot of one run: each packing's points, and the view's sampling floor.
fn quality_plot(
    path: &Path,
    scene: &str,
    rows: &[QualityRow],
    floor: f64,
) -> anyhow::Result<std::path::PathBuf> {
    type Pick = fn(&QualityRow) -> &QualityPoint;
    let pick: [(&str, Pick); 3] = [
        ("8-byte photons (Morton gaps)", |r| &r.eight),
        ("12-byte photons", |r| &r.twelve),
        ("20-byte photons", |r| &r.twenty),
    ];
    let sets: Vec<Front> = pick
        .iter()
        .map(|(label, f)| {
            (
                label.to_string(),
                rows.iter().map(|r| f(r).into()).collect(),
            )
        })
        .collect();
    fronts_plot(
        path,
        &format!("Photons, {scene}: error against bandwidth and update time"),
        &sets,
        Some(floor),
    )
}

/// What a Pareto plot shows of one point: where it lies (bandwidth, update time, error) and
/// its budget.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrontPoint {
    /// Photons emitted per update (the point's label in the plot).
    pub photons: u64,
    /// Server-to-client Mbit/s at the run's update rate.
    pub mbps: f64,
    /// Trace + pack time of one update, ms.
    pub update_ms: f64,
    /// Scale-invariant relMSE of the client's indirect light.
    pub relmse: f64,
}

impl From<&QualityPoint> for FrontPoint {
    fn from(p: &QualityPoint) -> Self {
        FrontPoint {
            photons: p.photons,
            mbps: p.mbps,
            update_ms: p.update_ms,
            relmse: p.errors.relmse,
        }
    }
}

/// A labelled set of points drawn as one series.
pub type Front = (String, Vec<FrontPoint>);

/// The fronts of photon `bench quality` runs (their `quality.json`, each with a label),
/// drawn together in one plot at `out`: before and after a change made anywhere — another
/// commit's build, other knobs, another seed. A run's front is its 8-byte photons (the
/// 12-byte ones for a run from before the 8-byte packing existed); a sweep gives one front
/// per combination, a run with a moving light's window another front of its first budget
/// as the client shows it with that window, and runs of one label one front (a run per
/// budget). Returns the fronts and the plot's path.
pub fn fronts(
    runs: &[(std::path::PathBuf, String)],
    out: &Path,
) -> anyhow::Result<(Vec<Front>, std::path::PathBuf)> {
    let mut sets = Vec::new();
    let mut scenes: Vec<String> = Vec::new();
    for (path, label) in runs {
        let text =
            std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let json: serde_json::Value = serde_json::from_str(&text)
            .with_context(|| format!("{} is not JSON", path.display()))?;
        let found = run_fronts(&json, label)
            .with_context(|| format!("{}: not a photon `bench quality` run", path.display()))?;
        if let Some(scene) = json.get("scene").and_then(|s| s.as_str())
            && !scenes.iter().any(|s| s == scene)
        {
            scenes.push(scene.to_string());
        }
        // Runs of one label make one front (e.g. a run per budget).
        for (label, points) in found {
            match sets.iter_mut().find(|(l, _): &&mut Front| *l == label) {
                Some((_, have)) => have.extend(points),
                None => sets.push((label, points)),
            }
        }
    }
    for (_, points) in &mut sets {
        points.sort_by_key(|p| p.photons);
    }
    let title = format!(
        "Photons, {}: error against bandwidth and update time",
        if scenes.is_empty() {
            "?".to_string()
        } else {
            scenes.join(" / ")
        }
    );
    let png = fronts_plot(out, &title, &sets, None)?;
    Ok((sets, png))
}

/// A point's `errors.relmse`, where it is a number >= 0.
fn relmse_of(point: &serde_json::Value) -> Option<f64> {
    point
        .get("errors")
        .and_then(|e| e.get("relmse"))
        .and_then(|v| v.as_f64())
        .filter(|v| v.is_finite() && *v >= 0.0)
}

/// The fronts of one photon `bench quality` report: its rows, or each variant's of a sweep.
fn run_fronts(json: &serde_json::Value, label: &str) -> anyhow::Result<Vec<Front>> {
    let technique = json.get("technique").and_then(|t| t.as_str());
    anyhow::ensure!(
        technique == Some("photons"),
        "its technique is {technique:?}, not \"photons\""
    );
    let points = |rows: &serde_json::Value| -> anyhow::Result<Vec<FrontPoint>> {
        let rows = rows.as_array().context("`rows` is not a list")?;
        rows.iter()
            .enumerate()
            .map(|(i, row)| {
                let p = row
                    .get("eight")
                    .or_else(|| row.get("twelve"))
                    .with_context(|| format!("row {i} has no 8- or 12-byte point"))?;
                let number = |key: &str| {
                    p.get(key)
                        .and_then(|v| v.as_f64())
                        .filter(|v| v.is_finite() && *v >= 0.0)
                        .with_context(|| format!("row {i}: `{key}` is not a number >= 0"))
                };
                let relmse = relmse_of(p)
                    .with_context(|| format!("row {i}: `errors.relmse` is not a number >= 0"))?;
                Ok(FrontPoint {
                    photons: number("photons")? as u64,
                    mbps: number("mbps")?,
                    update_ms: number("update_ms")?,
                    relmse,
                })
            })
            .collect()
    };
    if let Some(rows) = json.get("rows") {
        let points = points(rows)?;
        let mut fronts = vec![(label.to_string(), points.clone())];
        // A moving light's window (its first budget's generations drawn together): what
        // the client shows for the same bytes an update, as a point of its own front.
        let last = json
            .get("window")
            .and_then(|w| w.as_array())
            .and_then(|w| w.last());
        if let (Some(first), Some(last)) = (points.first(), last) {
            let generations = last.get("passes").and_then(|p| p.as_u64()).unwrap_or(1);
            let relmse =
                relmse_of(last).context("the window's last row has no `errors.relmse` >= 0")?;
            if generations > 1 {
                fronts.push((
                    format!("{label}, window of {generations}"),
                    vec![FrontPoint { relmse, ..*first }],
                ));
            }
        }
        return Ok(fronts);
    }
    let variants = json
        .get("variants")
        .and_then(|v| v.as_array())
        .context("it has neither `rows` nor `variants`")?;
    variants
        .iter()
        .map(|v| {
            let name = v.get("label").and_then(|l| l.as_str()).unwrap_or("?");
            let rows = v.get("rows").context("a variant has no `rows`")?;
            Ok((format!("{label}: {name}"), points(rows)?))
        })
        .collect()
}

/// relMSE against Mbps and against update time, a series per labelled set of points, with
/// the paper's operating point marked (and the view's sampling floor, where known).
fn fronts_plot(
    path: &Path,
    title: &str,
    sets: &[Front],
    floor: Option<f64>,
) -> anyhow::Result<std::path::PathBuf> {
    use crate::plot::{Floor, Marker, ParetoPanel, Series};
    let series = |x: fn(&FrontPoint) -> f64| -> Vec<Series> {
        sets.iter()
            .map(|(label, points)| Series {
                label: label.clone(),
                points: points
                    .iter()
                    .map(|p| (x(p), p.relmse, short(p.photons as f64)))
                    .collect(),
            })
            .collect()
    };
    let (mbps, ms) = paper::PHOTON_OPERATING_POINT;
    crate::plot::pareto(
        path,
        title,
        &[
            ParetoPanel {
                x_label: "server-to-client Mbps".into(),
                y_label: "relMSE (scale-invariant)".into(),
                series: series(|p| p.mbps),
                marker: Some(Marker {
                    x: mbps,
                    label: format!("paper: {mbps} Mbps (10k photons)"),
                }),
                floor: floor.map(Floor::sampling),
            },
            ParetoPanel {
                x_label: "update ms (trace + pack)".into(),
                y_label: "relMSE (scale-invariant)".into(),
                series: series(|p| p.update_ms),
                marker: Some(Marker {
                    x: ms,
                    label: format!("paper: {ms} ms per iteration"),
                }),
                floor: floor.map(Floor::sampling),
            },
        ],
    )
}
