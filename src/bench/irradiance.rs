//! The irradiance-map technique's benchmarks: its [`Technique`] descriptor (a gatherer and
//! one encoder shared on `cloud`, an `irradiance_reconstructor` per client on `home`), the
//! paper's Table 2 block (with "n/a" and its reason where a scene cannot be parametrised),
//! the client's frame, and the speed/accuracy sweep over bases, rays per basis and QP.

use std::path::Path;
use std::time::Instant;

use anyhow::Context;
use cloudlight_actors::basis_gatherer::{GathererParams, GathererReport};
use cloudlight_actors::client::{ClientParams, ClientReport, Params};
use cloudlight_actors::irradiance_reconstructor::{IrradianceClientParams, IrradianceClientReport};
use cloudlight_actors::video_encoder::{EncoderParams, EncoderReport};
use cloudlight_render::HdrMap;
use cloudlight_render::lightmap::{
    BasisFit, GatherMode, Gatherer, Lightmap, LightmapPass, NotParametrizable,
};
use cloudlight_render::metrics::{ImageErrors, compare};
use cloudlight_render::raster::{OneFrame, Raster, ShadowSettings};
use cloudlight_render::video::{Decoder, Encoder, EncoderSettings, RateControl, hdr};
use cloudlight_scenes::Scene;
use cloudlight_scenes::glam::Vec3;
use serde::{Deserialize, Serialize};

use super::client::{ClientBench, ClientBenchOptions};
use super::table::{Markdown, bytes, count};
use super::{
    Bench, CLIENT, ClusterOptions, ClusterRun, Placement, QualityCommon, QualityView, Row,
    ScalingRow, ServerCost, Side, StageGraph, Sweep, Technique, beside_paper, paper,
};

/// The irradiance-map technique.
pub struct Irradiance;

/// The irradiance benchmarks' knobs: the gatherer's, the encoder's QP and key-frame
/// interval, the clients' temporal filter.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct IrradianceOptions {
    /// `bases` or `texels` (the paper's naive server).
    pub mode: GatherMode,
    /// Rays per basis.
    pub rays_per_basis: u32,
    /// What a basis carries: `constant`, `linear` or `quadratic`.
    pub fit: BasisFit,
    /// Rays per texel in `texels` mode.
    pub rays_per_texel: u32,
    /// Valid texels per basis (the basis budget).
    pub texels_per_basis: f32,
    /// Map side (0: from the surface area).
    pub resolution: u32,
    /// Largest map side.
    pub max_resolution: u32,
    /// Unwrap time limit, seconds (0: only the scene's own light-map UVs).
    pub unwrap_limit_s: f64,
    /// Update period, ms.
    pub interval_ms: f64,
    /// The encoder's fixed QP.
    pub qp: u8,
    /// Seconds between key frames.
    pub keyframe_s: f64,
    /// The clients' temporal filter (weight of a new map).
    pub blend: f32,
}

impl Default for IrradianceOptions {
    fn default() -> Self {
        let g = GathererParams::default();
        IrradianceOptions {
            mode: g.mode,
            rays_per_basis: g.rays_per_basis,
            fit: g.fit,
            rays_per_texel: g.rays_per_texel,
            texels_per_basis: g.texels_per_basis,
            resolution: g.resolution,
            max_resolution: g.max_resolution,
            unwrap_limit_s: g.unwrap_limit_s,
            interval_ms: g.interval_ms,
            qp: 16,
            keyframe_s: 1.0,
            blend: IrradianceClientParams::default().blend,
        }
    }
}

impl IrradianceOptions {
    /// The gatherer's parameters.
    pub fn gatherer(&self) -> GathererParams {
        GathererParams {
            mode: self.mode,
            rays_per_basis: self.rays_per_basis,
            fit: self.fit,
            rays_per_texel: self.rays_per_texel,
            texels_per_basis: self.texels_per_basis,
            resolution: self.resolution,
            max_resolution: self.max_resolution,
            unwrap_limit_s: self.unwrap_limit_s,
            interval_ms: self.interval_ms,
            ..GathererParams::default()
        }
    }

    /// A client's own parameters (the gatherer's atlas settings).
    pub fn client(&self) -> IrradianceClientParams {
        let g = self.gatherer();
        IrradianceClientParams {
            blend: self.blend,
            texels_per_m2: g.texels_per_m2,
            resolution: g.resolution,
            max_resolution: g.max_resolution,
            max_texel_m: g.max_texel_m,
            unwrap_limit_s: g.unwrap_limit_s,
        }
    }

    /// Why `scene` has no light map at these settings, if it has none.
    pub fn not_parametrizable(&self, scene: &Scene) -> Option<NotParametrizable> {
        Lightmap::cached(scene, &self.gatherer().lightmap_settings()).err()
    }
}

impl Technique for Irradiance {
    const NAME: &'static str = "irradiance";
    type Options = IrradianceOptions;
    type Column = IrradianceColumn;

    fn graph(o: &IrradianceOptions) -> anyhow::Result<StageGraph> {
        let encode = EncoderParams {
            qp: Some(o.qp),
            keyframe_s: o.keyframe_s,
            fps: 1000.0 / o.interval_ms.max(1.0),
            ..EncoderParams::default()
        };
        let client = Params {
            client: ClientParams {
                render: false,
                fps: 20.0,
                ..ClientParams::default()
            },
            technique: o.client(),
        };
        Ok(StageGraph::new(&[Self::NAME, "video"])
            .stage(
                "gather",
                "basis_gatherer",
                Placement::Shared,
                toml::Table::try_from(o.gatherer())?,
            )
            .stage(
                "encode",
                "video_encoder",
                Placement::Shared,
                toml::Table::try_from(encode)?,
            )
            .stage(
                CLIENT,
                "irradiance_reconstructor",
                Placement::PerClient(Side::Home),
                client.to_table()?,
            )
            .edge("gather", "encode")
            .edge("encode", CLIENT))
    }

    fn scaling_row(run: &ClusterRun, clients: usize) -> anyhow::Result<ScalingRow> {
        let g: GathererReport = run.report("gather")?;
        let shown: Vec<ClientReport<IrradianceClientReport>> = run.per_client(CLIENT)?;
        let cost = ServerCost {
            update_ms: g.update_ms_mean,
            kernel_ms: g.update_ms_mean,
            updates: g.updates,
            per_client_ms: None,
        };
        Ok(ScalingRow::of(run, clients, cost, &shown))
    }

    fn scaling_figure() -> (&'static str, &'static str) {
        paper::IRRADIANCE_SCALING_FIGURE
    }

    fn table2_column(
        bench: &Bench,
        o: &IrradianceOptions,
        cluster: &ClusterOptions,
        size: (u32, u32),
    ) -> anyhow::Result<IrradianceColumn> {
        let scene = cloudlight_scenes::load(&cluster.scene)?;
        let mut column = IrradianceColumn {
            scene: cluster.scene.clone(),
            triangles: scene.triangle_count(),
            paper_scene: paper::SCENES[paper::nearest_scene(scene.triangle_count() as u64)].name,
            ..IrradianceColumn::default()
        };
        if let Some(why) = o.not_parametrizable(&scene) {
            eprintln!("{}: n/a: {why}", cluster.scene);
            column.na = Some(why.to_string());
            return Ok(column);
        }
        eprintln!(
            "{}: the gatherer, one encoder and a client for {} s...",
            cluster.scene, cluster.seconds
        );
        let run = super::run_cluster::<Irradiance>(bench.runtime, o, cluster, 1)?;
        let g: GathererReport = run.report("gather")?;
        let e: EncoderReport = run.report("encode")?;
        let c: ClientReport<IrradianceClientReport> = run.report(CLIENT)?;
        let frame = Self::client_frame(
            bench.raster,
            &scene,
            o,
            ClientBenchOptions {
                width: size.0,
                height: size.1,
                frames: 5,
                ..Default::default()
            },
        )?;
        Ok(IrradianceColumn {
            bases: g.bases,
            rays_per_update: g.rays_per_update,
            update_ms_p50: g.update_ms_p50,
            update_ms_mean: g.update_ms_mean,
            updates: g.updates,
            converged_updates: g.converged_updates,
            resolution: g.resolution,
            valid_texels: g.valid_texels,
            encode_ms_p50: e.encode_ms_p50,
            server_to_client_mbps: run.wire_mbps(),
            payload_mbps: run.payload_mbps(),
            client_bytes: c.technique.map_bytes,
            client_decode_ms_p50: c.technique.decode_ms_p50,
            client_indirect_ms: frame
                .passes
                .iter()
                .find(|p| p.pass == "indirect")
                .map_or(0.0, |p| p.p50_ms),
            client_resolution: format!("{}x{}", size.0, size.1),
            age_ms_p50: c.age_ms_p50,
            age_ms_p99: c.age_ms_p99,
            maps_blended: c.technique.maps_blended,
            ..column
        })
    }

    fn table2_markdown(columns: &[IrradianceColumn]) -> String {
        table2_markdown(columns)
    }

    fn table2_note(o: &IrradianceOptions, (width, height): (u32, u32), adapter: &str) -> String {
        format!(
            "An update every {} ms (one bounce over the last map; a static scene stops gathering once converged and re-sends \
             its map every second), H.264 at QP {} with key frames every {} s, 1 client over loopback; client indirect \
             (light-map lookup) at {width}x{height} on {adapter}. Local device indirect light size: ours is the map at f16 RGBA \
             (8 B a texel), the paper's 48 B a texel. Paper: GeForce Titan cloud (OptiX), GeForce 670 client.",
            o.interval_ms, o.qp, o.keyframe_s
        )
    }

    fn client_frame(
        raster: &Raster,
        scene: &Scene,
        o: &IrradianceOptions,
        frame: ClientBenchOptions,
    ) -> anyhow::Result<ClientBench> {
        let (lm, map, _) = converged_map(scene, o, 1, 8)?;
        let mut pass = LightmapPass::new(raster)?;
        pass.set_map(raster, &map)?;
        let mut bench = super::client::measure(raster, &lm.scene, &mut pass, frame)?;
        bench.indirect = format!(
            "a {}×{} light map ({} bases)",
            map.width(),
            map.height(),
            lm.bases.bases.len()
        );
        Ok(bench)
    }

    fn default_sweep() -> Sweep {
        let ints = |v: &[i64]| v.iter().map(|&x| toml::Value::Integer(x)).collect();
        vec![
            ("texels_per_basis".into(), ints(&[90, 180, 360])),
            ("rays_per_basis".into(), ints(&[128, 512, 2048])),
            (
                "fit".into(),
                vec!["constant".into(), "linear".into(), "quadratic".into()],
            ),
            ("qp".into(), ints(&[12, 20, 28])),
        ]
    }

    fn quality(
        raster: &Raster,
        scene: &str,
        common: &QualityCommon,
        options: &IrradianceOptions,
        sweep: &Sweep,
        out: &Path,
    ) -> anyhow::Result<serde_json::Value> {
        quality(raster, scene, common, options, sweep, out)
    }
}

/// The scene's light map at `o` and its map after `updates` updates at time 0 (or once
/// converged, at most `max` updates), with the mean update time of those that gathered.
fn converged_map(
    scene: &Scene,
    o: &IrradianceOptions,
    seed: u64,
    max: usize,
) -> anyhow::Result<(std::sync::Arc<Lightmap>, HdrMap, UpdateCost)> {
    let g = o.gatherer();
    let lm = Lightmap::cached(scene, &g.lightmap_settings())
        .map_err(|e| anyhow::anyhow!("{} has no irradiance map (n/a): {e}", scene.name))?;
    let mut gatherer = Gatherer::new(lm.clone(), g.gather_settings(seed));
    let mut cost = UpdateCost::default();
    for _ in 0..max {
        let u = gatherer.update(0.0);
        if u.converged {
            break;
        }
        cost.updates += 1;
        cost.seconds += u.seconds;
        cost.rays = u.rays;
    }
    Ok((lm, HdrMap::clone(gatherer.map()), cost))
}

/// What the updates of [`converged_map`] cost.
#[derive(Clone, Copy, Debug, Default)]
struct UpdateCost {
    updates: u32,
    seconds: f64,
    rays: u64,
}

/// One scene's column of the irradiance block of Table 2.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct IrradianceColumn {
    /// Scene.
    pub scene: String,
    /// Triangles.
    pub triangles: usize,
    /// The paper's scene it is compared with.
    pub paper_scene: &'static str,
    /// Why the scene has no light map (the paper's "n/a"); every figure is 0 then.
    pub na: Option<String>,
    /// Bases.
    pub bases: usize,
    /// Gather rays per update.
    pub rays_per_update: u64,
    /// Update time, p50 / mean, ms (updates that gathered).
    pub update_ms_p50: f64,
    /// Mean, ms.
    pub update_ms_mean: f64,
    /// Updates done.
    pub updates: u64,
    /// Of which converged (nothing gathered).
    pub converged_updates: u64,
    /// Map side, texels.
    pub resolution: u32,
    /// Valid texels.
    pub valid_texels: usize,
    /// Pack + encode per map, p50, ms.
    pub encode_ms_p50: f64,
    /// Server-to-client wire bandwidth, Mbps.
    pub server_to_client_mbps: f64,
    /// Payload bandwidth, Mbps.
    pub payload_mbps: f64,
    /// The map on the client's GPU, bytes.
    pub client_bytes: u64,
    /// The client's decode per map, p50, ms.
    pub client_decode_ms_p50: f64,
    /// The client's indirect pass (the light-map lookup), p50, ms.
    pub client_indirect_ms: f64,
    /// Its frame size.
    pub client_resolution: String,
    /// Age of the light shown, p50 / p99, ms.
    pub age_ms_p50: f64,
    /// p99, ms.
    pub age_ms_p99: f64,
    /// Maps the client blended.
    pub maps_blended: u64,
}

/// The irradiance block of Table 2: our columns beside the paper's; a scene without a light
/// map reads "n/a" in every row, its reason under the table.
pub fn table2_markdown(columns: &[IrradianceColumn]) -> String {
    fn or_na(c: &IrradianceColumn, f: impl Fn(&IrradianceColumn) -> String) -> String {
        if c.na.is_some() { "n/a".into() } else { f(c) }
    }
    let rows: [Row<IrradianceColumn>; 9] = [
        Row {
            label: "Triangles",
            paper: None,
            cell: |c| c.triangles.to_string(),
        },
        Row {
            label: "Number of basis functions",
            paper: Some(0),
            cell: |c| or_na(c, |c| count(c.bases as f64)),
        },
        Row {
            label: "Rays per update",
            paper: Some(1),
            cell: |c| or_na(c, |c| count(c.rays_per_update as f64)),
        },
        Row {
            label: "Cloud update time (p50)",
            paper: Some(2),
            cell: |c| {
                or_na(c, |c| {
                    format!(
                        "{:.1} ms ({} of {} updates converged)",
                        c.update_ms_p50, c.converged_updates, c.updates
                    )
                })
            },
        },
        Row {
            label: "Irradiance map texels",
            paper: Some(3),
            cell: |c| {
                or_na(c, |c| {
                    format!("{}² ({} valid)", c.resolution, count(c.valid_texels as f64))
                })
            },
        },
        Row {
            label: "H.264 encode (pack + encode, p50)",
            paper: Some(4),
            cell: |c| or_na(c, |c| format!("{:.2} ms", c.encode_ms_p50)),
        },
        Row {
            label: "Server-to-client bandwidth (mean, wire)",
            paper: Some(5),
            cell: |c| or_na(c, |c| format!("{:.2} Mbps", c.server_to_client_mbps)),
        },
        Row {
            label: "Local device indirect light size",
            paper: Some(6),
            cell: |c| or_na(c, |c| bytes(c.client_bytes as f64)),
        },
        Row {
            label: "Client: decode + lookup (p50)",
            paper: None,
            cell: |c| {
                or_na(c, |c| {
                    format!(
                        "{:.2} ms + {:.1} ms at {}",
                        c.client_decode_ms_p50, c.client_indirect_ms, c.client_resolution
                    )
                })
            },
        },
    ];
    let mut text = beside_paper(
        "Irradiance maps",
        columns,
        |c| (&c.scene, c.paper_scene),
        &rows[..8],
        &paper::IRRADIANCE,
    );
    // The client's own times have no paper row: a row of ours alone.
    let mut t = Markdown::new(&["scene", "client: decode per map + lookup per frame (p50)"]);
    for c in columns {
        t.row(vec![c.scene.clone(), (rows[8].cell)(c)]);
    }
    text += &t.render();
    for c in columns.iter().filter(|c| c.na.is_some()) {
        text += &format!(
            "\n{}: n/a: {}\n",
            c.scene,
            c.na.as_deref().unwrap_or_default()
        );
    }
    text
}

/// One point of the irradiance trade: a (basis budget, rays) setting, raw and through H.264
/// at one QP.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct IrradiancePoint {
    /// `bases` or `texels`.
    pub mode: String,
    /// What a basis carries (`constant`, `linear`, `quadratic`; `-` per texel).
    pub fit: String,
    /// The basis budget.
    pub texels_per_basis: f32,
    /// Bases baked.
    pub bases: usize,
    /// Rays per gather point (basis or texel).
    pub rays_per_point: u32,
    /// Rays per update.
    pub rays_per_update: u64,
    /// Updates gathered until the static map converged.
    pub updates: u32,
    /// Mean time of an update, ms.
    pub update_ms: f64,
    /// The QP.
    pub qp: u8,
    /// A key frame of the map, kB.
    pub key_kbytes: f64,
    /// Mbps if every update at the update rate were a key frame (an upper bound: a changing
    /// map's P frames cost less, a static map's almost nothing).
    pub mbps: f64,
    /// Errors of the client's indirect light with the raw f16 map.
    pub raw: ImageErrors,
    /// With the map through H.264 at `qp`.
    pub h264: ImageErrors,
}

/// The irradiance sweep: every (`texels_per_basis`, `rays_per_basis`) of `sweep` gathers a
/// converged map of `scene` at time 0; every `qp` codes it; each is shown by the client's
/// pass and compared with the reference's indirect image. One per-texel point (the paper's
/// naive server) beside them. Prints the table, writes `quality.json`, `quality.png` and the
/// images to `out` (EXR, and a PNG beside the reference with its error map).
pub fn quality(
    raster: &Raster,
    scene_spec: &str,
    common: &QualityCommon,
    options: &IrradianceOptions,
    sweep: &Sweep,
    out: &Path,
) -> anyhow::Result<serde_json::Value> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let mut qps = Vec::new();
    let mut texel_rays = Vec::new();
    let mut gather_sweep = Sweep::new();
    // Whole numbers of `values` in `range`, or an error naming `what`.
    let whole = |values: &[toml::Value], range: std::ops::RangeInclusive<i64>, what: &str| {
        values
            .iter()
            .map(|v| {
                v.as_integer()
                    .filter(|x| range.contains(x))
                    .with_context(|| {
                        format!(
                            "{what} `{v}` is not a whole number {} to {}",
                            range.start(),
                            range.end()
                        )
                    })
            })
            .collect::<anyhow::Result<Vec<i64>>>()
    };
    for (key, values) in sweep {
        match key.as_str() {
            "qp" => qps.extend(whole(values, 0..=51, "QP")?.into_iter().map(|q| q as u8)),
            "rays_per_texel" => texel_rays.extend(
                whole(values, 1..=100_000, "rays per texel")?
                    .into_iter()
                    .map(|r| r as u32),
            ),
            "texels_per_basis" | "rays_per_basis" | "fit" => {
                gather_sweep.push((key.clone(), values.clone()))
            }
            other => anyhow::bail!(
                "the irradiance quality sweep varies `texels_per_basis`, `rays_per_basis`, `fit`, `rays_per_texel` and `qp`, not `{other}`"
            ),
        }
    }
    if qps.is_empty() {
        qps.push(options.qp);
    }
    let knobs = toml::Table::try_from(options)?;
    let mut settings = super::expand::<Irradiance>(&knobs, &gather_sweep)?;
    let scene = cloudlight_scenes::load(scene_spec)?;
    if let Some(why) = options.not_parametrizable(&scene) {
        anyhow::bail!("{} has no irradiance map (n/a): {why}", scene.name);
    }
    if texel_rays.is_empty() {
        // Per texel with 5× the rays of the options' bases (the target's comparison), and
        // at the options' rays per texel.
        let lm = Lightmap::cached(&scene, &options.gatherer().lightmap_settings())
            .map_err(|e| anyhow::anyhow!("{} has no irradiance map (n/a): {e}", scene.name))?;
        let basis_rays = lm.bases.bases.len() as u64 * u64::from(options.rays_per_basis);
        let valid = lm.texels.valid_count().max(1) as u64;
        texel_rays.push((5 * basis_rays).div_ceil(valid).max(1) as u32);
        texel_rays.push(options.rays_per_texel);
        texel_rays.sort_unstable();
        texel_rays.dedup();
    }
    settings.extend(texel_rays.iter().map(|&rays_per_texel| IrradianceOptions {
        mode: GatherMode::Texels,
        rays_per_texel,
        ..options.clone()
    }));
    let view = QualityView::of(scene, common)?;
    let (w, h) = (common.width, common.height);
    view.write_reference(out)?;
    let shadows = ShadowSettings {
        size: 16,
        ..Default::default()
    };
    let mut points = Vec::new();
    for o in &settings {
        let start = Instant::now();
        let (lm, raw, cost) = converged_map(&view.scene, o, common.seed, 48)?;
        let tris = lm.scene.triangles_at(0.0);
        let show = |map: &HdrMap| -> anyhow::Result<(ImageErrors, Vec<Vec3>)> {
            let mut pass = LightmapPass::new(raster)?;
            pass.set_map(raster, map)?;
            let frame = OneFrame::new(&lm.scene, &tris, &[], &view.camera, (w, h), shadows)
                .with_samples(common.still_frames);
            let f = raster.read_frame(&frame, &mut pass)?;
            let mask: Vec<bool> = f.coverage.iter().map(|&c| c > 0.0).collect();
            Ok((
                compare(&f.indirect, &view.reference, &mask, w, h),
                f.indirect,
            ))
        };
        let (raw_errors, raw_image) = show(&raw)?;
        let (mode, per_point) = match o.mode {
            GatherMode::Bases => ("bases", o.rays_per_basis),
            GatherMode::Texels => ("texels", o.rays_per_texel),
        };
        let tag = match o.mode {
            GatherMode::Bases => format!(
                "bases_tpb{}_r{per_point}_{}",
                o.texels_per_basis,
                fit_name(o.fit)
            ),
            GatherMode::Texels => format!("texels_r{per_point}"),
        };
        view.write_image(
            out,
            &format!("indirect_{tag}_raw"),
            &raw_image,
            &format!("{tag}, raw"),
        )?;
        let update_ms = cost.seconds * 1000.0 / f64::from(cost.updates.max(1));
        let rate = common.rate_hz.min(1000.0 / update_ms.max(1e-3));
        let qp_list: &[u8] = if o.mode == GatherMode::Texels {
            &qps[..1]
        } else {
            &qps
        };
        for &qp in qp_list {
            let (coded, key_bytes) = through_h264(&raw, qp)?;
            let (h264, image) = show(&coded)?;
            view.write_image(
                out,
                &format!("indirect_{tag}_qp{qp}"),
                &image,
                &format!("{tag}, H.264 QP {qp}"),
            )?;
            points.push(IrradiancePoint {
                mode: mode.into(),
                fit: match o.mode {
                    GatherMode::Bases => fit_name(o.fit).into(),
                    GatherMode::Texels => "-".into(),
                },
                texels_per_basis: o.texels_per_basis,
                bases: lm.bases.bases.len(),
                rays_per_point: per_point,
                rays_per_update: cost.rays,
                updates: cost.updates,
                update_ms,
                qp,
                key_kbytes: key_bytes as f64 / 1e3,
                mbps: key_bytes as f64 * 8.0 * rate / 1e6,
                raw: raw_errors,
                h264,
            });
        }
        eprintln!(
            "{tag}: {} bases, {} rays/update, {update_ms:.1} ms/update, relMSE raw {:.4} ({:.1} s)",
            lm.bases.bases.len(),
            cost.rays,
            raw_errors.relmse,
            start.elapsed().as_secs_f64()
        );
    }
    println!("{}", quality_markdown(&points));
    if let Some(line) = per_basis_against_per_texel(&points, options) {
        println!("{line}");
    }
    println!(
        "relMSE of the client's indirect radiance ({w}x{h}, the light-map lookup) against the path tracer's indirect image \
         ({} spp) of the same view and time, both divided by the reference's mean luminance over pixels that see geometry; \
         each map converged (a static scene at time 0). \"raw\" is the f16 map as the raw cut shows it; the H.264 columns add \
         the codec's error. Mbps: every update a key frame at {} Hz or as fast as the update allows (an upper bound). \
         Paper's Cornell box: 50 bases, 26k rays, 7.5 ms, 0.16 Mbps.",
        common.spp, common.rate_hz
    );
    let report = serde_json::json!({ "technique": Irradiance::NAME, "scene": scene_spec, "common": common,
        "options": options, "reference_seconds": view.reference_s, "reference_noise": view.reference_noise, "sampling_floor": view.sampling_floor, "points": points });
    let json = out.join("quality.json");
    std::fs::write(&json, serde_json::to_string_pretty(&report)?)
        .with_context(|| format!("writing {}", json.display()))?;
    let png = quality_plot(
        &out.join("quality.png"),
        scene_spec,
        &points,
        &qps,
        view.sampling_floor,
    )?;
    println!("wrote {} and {}", json.display(), png.display());
    Ok(report)
}

/// `map` packed, coded as a key frame at `qp` and decoded; the map and the key frame's bytes.
pub(super) fn through_h264(map: &HdrMap, qp: u8) -> anyhow::Result<(HdrMap, usize)> {
    through_h264_at(map, RateControl::FixedQp(qp), 1, 30.0)
}

/// `map` as `frames` frames of a still H.264 stream at `fps` under `rate` (packed by
/// [`hdr::pack`]): the last picture decoded, and the mean bytes per frame (the key frame
/// and the frames refining it).
pub(super) fn through_h264_at(
    map: &HdrMap,
    rate: RateControl,
    frames: u32,
    fps: f64,
) -> anyhow::Result<(HdrMap, usize)> {
    let packed = hdr::pack(map)?;
    let mut enc = Encoder::new(EncoderSettings {
        width: map.width(),
        height: map.height(),
        rate,
        fps: fps as f32,
        ..Default::default()
    })?;
    let mut decoder = Decoder::new()?;
    let (mut bytes, mut last) = (0, None);
    for f in 0..frames.max(1) {
        let unit = enc
            .encode(&packed.yuv, f64::from(f) / fps)?
            .context("the encoder skipped the map")?;
        bytes += unit.data.len();
        if let Some(picture) = decoder.decode(&unit.data)? {
            last = Some(picture);
        }
    }
    let picture = last.context("the decoder showed no map")?;
    let texels = hdr::unpack(&picture, packed.range);
    Ok((
        HdrMap::new(map.width(), map.height(), &texels, &[])?,
        bytes / frames.max(1) as usize,
    ))
}

/// The quality table.
pub fn quality_markdown(points: &[IrradiancePoint]) -> String {
    let mut t = Markdown::new(&[
        "mode",
        "fit",
        "texels/basis",
        "bases",
        "rays/point",
        "rays/update",
        "update ms",
        "QP",
        "key kB",
        "Mbps (≤)",
        "relMSE raw",
        "relMSE H.264",
        "H.264 adds",
        "HDR-FLIP (H.264)",
        "energy ours / reference",
    ]);
    for p in points {
        t.row(vec![
            p.mode.clone(),
            p.fit.clone(),
            format!("{}", p.texels_per_basis),
            p.bases.to_string(),
            p.rays_per_point.to_string(),
            count(p.rays_per_update as f64),
            format!("{:.1}", p.update_ms),
            p.qp.to_string(),
            format!("{:.2}", p.key_kbytes),
            format!("{:.3}", p.mbps),
            format!("{:.4}", p.raw.relmse),
            format!("{:.4}", p.h264.relmse),
            format!("{:+.4}", p.h264.relmse - p.raw.relmse),
            format!("{:.3}", p.h264.flip),
            format!("{:.3}", p.h264.energy_ratio),
        ]);
    }
    t.render()
}

/// A fit's knob value.
fn fit_name(fit: BasisFit) -> &'static str {
    match fit {
        BasisFit::Constant => "constant",
        BasisFit::Linear => "linear",
        BasisFit::Quadratic => "quadratic",
    }
}

/// Per-basis gathering at the options' basis budget, rays and fit (or the nearest point)
/// against per-texel gathering with at least 5× its rays (the fewest such; else the most
/// rays there are), as a sentence: the target is within 20% of its error.
fn per_basis_against_per_texel(
    points: &[IrradiancePoint],
    o: &IrradianceOptions,
) -> Option<String> {
    let texels: Vec<&IrradiancePoint> = points.iter().filter(|p| p.mode == "texels").collect();
    let qp = texels.first()?.qp;
    let basis = points
        .iter()
        .filter(|p| p.mode == "bases" && p.qp == qp)
        .min_by_key(|p| {
            (
                p.fit != fit_name(o.fit),
                (p.texels_per_basis - o.texels_per_basis).abs() as i64,
                (i64::from(p.rays_per_point) - i64::from(o.rays_per_basis)).abs(),
            )
        })?;
    let enough = |p: &&&IrradiancePoint| p.rays_per_update >= 5 * basis.rays_per_update;
    let texel = texels
        .iter()
        .filter(enough)
        .min_by_key(|p| p.rays_per_update)
        .or_else(|| texels.iter().max_by_key(|p| p.rays_per_update))?;
    Some(format!(
        "per basis ({} bases, {} fit, × {} rays = {} rays) against per texel ({} rays per texel = {} rays): relMSE {:.4} against {:.4} \
         ({:+.0}%) with {:.1}× fewer rays (target: within 20% with at least 5× fewer)",
        basis.bases,
        basis.fit,
        basis.rays_per_point,
        count(basis.rays_per_update as f64),
        texel.rays_per_point,
        count(texel.rays_per_update as f64),
        basis.raw.relmse,
        texel.raw.relmse,
        (basis.raw.relmse / texel.raw.relmse.max(1e-12) - 1.0) * 100.0,
        texel.rays_per_update as f64 / basis.rays_per_update.max(1) as f64
    ))
}

/// The Pareto plot: relMSE (through H.264) against Mbps and against update time, one
/// series per QP and one for per-texel gathering.
fn quality_plot(
    path: &Path,
    scene: &str,
    points: &[IrradiancePoint],
    qps: &[u8],
    floor: f64,
) -> anyhow::Result<std::path::PathBuf> {
    use crate::plot::{Floor, Marker, ParetoPanel, Series};
    // One series per fit, at the middle QP of the sweep (QP moves the error by far less
    // than the fit does; the table has every QP).
    let qp = qps.get(qps.len() / 2).copied().unwrap_or_default();
    let mut fits: Vec<&str> = points
        .iter()
        .filter(|p| p.mode == "bases")
        .map(|p| p.fit.as_str())
        .collect();
    fits.dedup();
    fits.sort_unstable();
    fits.dedup();
    let series = |x: fn(&IrradiancePoint) -> f64| -> Vec<Series> {
        let mut s: Vec<Series> = fits
            .iter()
            .map(|&fit| Series {
                label: format!("per basis, {fit} fit, H.264 QP {qp}"),
                points: points
                    .iter()
                    .filter(|p| p.mode == "bases" && p.qp == qp && p.fit == fit)
                    .map(|p| {
                        (
                            x(p),
                            p.h264.relmse,
                            format!("{}b×{}", p.bases, p.rays_per_point),
                        )
                    })
                    .collect(),
            })
            .collect();
        s.push(Series {
            label: "per texel".into(),
            points: points
                .iter()
                .filter(|p| p.mode == "texels")
                .map(|p| (x(p), p.h264.relmse, format!("{}/texel", p.rays_per_point)))
                .collect(),
        });
        s
    };
    crate::plot::pareto(
        path,
        &format!("Irradiance maps, {scene}: error against bandwidth and update time"),
        &[
            ParetoPanel {
                x_label: "server-to-client Mbps (every update a key frame)".into(),
                y_label: "relMSE (scale-invariant)".into(),
                series: series(|p| p.mbps),
                marker: Some(Marker {
                    x: 0.16,
                    label: "paper: 0.16 Mbps (Cornell box)".into(),
                }),
                floor: Some(Floor::sampling(floor)),
            },
            ParetoPanel {
                x_label: "update ms (gather)".into(),
                y_label: "relMSE (scale-invariant)".into(),
                series: series(|p| p.update_ms),
                marker: Some(Marker {
                    x: 7.5,
                    label: "paper: 7.5 ms per update".into(),
                }),
                floor: Some(Floor::sampling(floor)),
            },
        ],
    )
}
