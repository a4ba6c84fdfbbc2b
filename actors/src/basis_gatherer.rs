//! `basis_gatherer`: the cloud side of the irradiance-map technique (CloudLight §4.2).
//!
//! At start it bakes the scene's light map (atlas, texel G-buffer, bases; cached per scene
//! in the process) — a scene that cannot be parametrised fails validation with the reason,
//! the paper's "n/a". Every `interval_ms` it runs one update of the kernel
//! ([`Gatherer::update`]: texture-space direct light, one gathered bounce over the previous
//! map, per-texel reconstruction) at the current scene time and sends the map as
//! [`FrameMsg::Hdr`] (E_indirect in W·m⁻², valid texels marked), stamped with the scene time
//! it is valid for. One gatherer feeds every client (through one `video_encoder`, or raw).
//! A static scene that has converged is not gathered again; its map is re-sent every
//! `resend_s` so late clients get it, marked `steady` (valid until superseded, so a client
//! holding it reports its light as current rather than as old as the last re-send).
//!
//! Ports: [`OUT`] (FrameMsg::Hdr). What `latest` drops on `out`: older maps (each map is
//! complete; the newest supersedes them).

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use cloudlight_render::lightmap::{
    AtlasSettings, BasisFit, BasisSettings, GatherMode, GatherSettings, Gatherer, Lightmap,
    LightmapSettings,
};
use cloudlight_runtime::{
    Cadence, CheckParams, Latency, NextTick, Port, Stage, StageCtx, StageKind, StageSetup, lock,
};
use serde::{Deserialize, Serialize};

use crate::wire::FrameMsg;

/// Technique name of the irradiance-map stages.
pub const TECHNIQUE: &str = "irradiance";

/// The maps, one per update (and re-sends).
pub const OUT: Port<FrameMsg> = Port::new("out");

/// Parameters of `basis_gatherer`.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GathererParams {
    /// `bases` (default: gather once per basis) or `texels` (the paper's naive server).
    pub mode: GatherMode,
    /// Rays per basis.
    pub rays_per_basis: u32,
    /// What a basis carries: `constant` (the paper's bases: one value, every ray from its
    /// centre), `linear` or `quadratic` (default; a fit to rays from all its texels).
    pub fit: BasisFit,
    /// Rays per texel in `texels` mode.
    pub rays_per_texel: u32,
    /// Light samples per texel for texture-space direct light.
    pub direct_samples: u32,
    /// Re-compute only what changed (default), or everything each update.
    pub partial: bool,
    /// Valid texels per basis (sets the basis budget).
    pub texels_per_basis: f32,
    /// Map side in texels (0: from the surface area at `texels_per_m2`).
    pub resolution: u32,
    /// Texels per m² the atlas aims for.
    pub texels_per_m2: f64,
    /// Largest map side the texel budget allows.
    pub max_resolution: u32,
    /// Largest texel edge allowed, meters.
    pub max_texel_m: f32,
    /// Time the unwrap may take, seconds (0: only the scene's own light-map UVs).
    pub unwrap_limit_s: f64,
    /// Period of updates, milliseconds (an update that takes longer is followed at once).
    pub interval_ms: f64,
    /// Re-send the map when none went out for this long, seconds (0: never).
    pub resend_s: f64,
}

impl Default for GathererParams {
    fn default() -> Self {
        let (a, b, g) = (
            AtlasSettings::default(),
            BasisSettings::default(),
            GatherSettings::default(),
        );
        GathererParams {
            mode: g.mode,
            rays_per_basis: g.rays_per_basis,
            fit: g.fit,
            rays_per_texel: g.rays_per_texel,
            direct_samples: g.direct_samples,
            partial: g.partial,
            texels_per_basis: b.texels_per_basis,
            resolution: a.resolution,
            texels_per_m2: a.texels_per_m2,
            max_resolution: a.max_resolution,
            max_texel_m: a.max_texel_m,
            unwrap_limit_s: a.unwrap_limit_s,
            interval_ms: 100.0,
            resend_s: 1.0,
        }
    }
}

/// Largest map side (texels): the largest square picture H.264 level 5.2 holds (its short
/// side is at most 2160), so that every map the gatherer makes can be encoded.
pub const MAX_RESOLUTION: u32 = 2160;

/// Checks the atlas knobs (`texels_per_m2`, `resolution`, `max_resolution`, `max_texel_m`,
/// `unwrap_limit_s`) a gatherer and its clients share.
pub fn check_atlas(a: &AtlasSettings) -> Result<(), String> {
    use cloudlight_runtime::check_range;
    check_range("texels_per_m2", a.texels_per_m2, 1e-6, 1e9, "texels per m²")?;
    check_map_side("resolution", a.resolution, true)?;
    check_range(
        "max_resolution",
        a.max_resolution as f64,
        16.0,
        MAX_RESOLUTION as f64,
        "texels",
    )?;
    check_map_side("max_resolution", a.max_resolution, false)?;
    check_range("max_texel_m", a.max_texel_m as f64, 1e-6, 1e4, "m")?;
    check_range("unwrap_limit_s", a.unwrap_limit_s, 0.0, 86_400.0, "s")
}

/// Checks a map side `value` of knob `key` against what the video encoder takes (even, at
/// most [`MAX_RESOLUTION`]); `allow_zero` for "from the surface area".
pub fn check_map_side(key: &str, value: u32, allow_zero: bool) -> Result<(), String> {
    if allow_zero && value == 0 {
        return Ok(());
    }
    cloudlight_render::video::yuv::check_size(value, value).map_err(|_| {
        format!(
            "`{key}` = {value}: a light map's side must be even and 2 to {MAX_RESOLUTION} texels (what H.264 encodes){}",
            if allow_zero { ", or 0 (from the surface area)" } else { "" }
        )
    })
}

impl GathererParams {
    /// The kernel's offline settings.
    pub fn lightmap_settings(&self) -> LightmapSettings {
        LightmapSettings {
            atlas: AtlasSettings {
                texels_per_m2: self.texels_per_m2,
                resolution: self.resolution,
                max_resolution: self.max_resolution,
                max_texel_m: self.max_texel_m,
                unwrap_limit_s: self.unwrap_limit_s,
                ..Default::default()
            },
            bases: BasisSettings {
                texels_per_basis: self.texels_per_basis,
                ..Default::default()
            },
        }
    }

    /// The kernel's per-update settings.
    pub fn gather_settings(&self, seed: u64) -> GatherSettings {
        GatherSettings {
            mode: self.mode,
            rays_per_basis: self.rays_per_basis,
            fit: self.fit,
            rays_per_texel: self.rays_per_texel,
            direct_samples: self.direct_samples,
            partial: self.partial,
            seed,
        }
    }
}

impl CheckParams for GathererParams {
    fn check(&self) -> Result<(), String> {
        use cloudlight_runtime::check_range;
        check_range(
            "rays_per_basis",
            self.rays_per_basis as f64,
            1.0,
            1e6,
            "rays",
        )?;
        check_range(
            "rays_per_texel",
            self.rays_per_texel as f64,
            1.0,
            1e5,
            "rays",
        )?;
        check_range(
            "direct_samples",
            self.direct_samples as f64,
            1.0,
            1e4,
            "samples",
        )?;
        check_range(
            "texels_per_basis",
            self.texels_per_basis as f64,
            1.0,
            1e7,
            "texels",
        )?;
        check_atlas(&self.lightmap_settings().atlas)?;
        check_range("interval_ms", self.interval_ms, 0.0, 3.6e6, "ms")?;
        check_range("resend_s", self.resend_s, 0.0, 86_400.0, "s")
    }
}

/// What `basis_gatherer` reports (its stage report, as JSON).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GathererReport {
    /// One line for people.
    pub summary: String,
    /// Updates done (converged ones included).
    pub updates: u64,
    /// Updates that gathered nothing (a static scene that had converged).
    pub converged_updates: u64,
    /// Map side, texels.
    pub resolution: u32,
    /// Valid texels.
    pub valid_texels: usize,
    /// Charts of the atlas (0: the scene's own UVs).
    pub charts: u32,
    /// Fraction of the map covered by charts.
    pub utilization: f32,
    /// Unwrap time, seconds.
    pub unwrap_s: f64,
    /// Bases.
    pub bases: usize,
    /// Gather rays of the last update that gathered.
    pub rays_per_update: u64,
    /// Mean fraction of the points (bases or texels) gathered again per update that
    /// gathered: below 1 when only part of the scene changed (`partial`).
    pub regathered_fraction: f64,
    /// Mean fraction of the valid texels whose direct light an update computed.
    pub direct_fraction: f64,
    /// Update time, p50 / p99 / mean, ms (updates that gathered).
    pub update_ms_p50: f64,
    /// p99, ms.
    pub update_ms_p99: f64,
    /// Mean, ms.
    pub update_ms_mean: f64,
    /// Updates that ended after the next one was due.
    pub overruns: u64,
    /// Maps handed downstream.
    pub maps_sent: u64,
    /// Bytes of the maps handed downstream (f16 texels + coverage bits).
    pub bytes_sent: u64,
    /// Bytes a client holds for one map at f16 RGBA.
    pub client_bytes: u64,
}

/// The basis gatherer stage.
pub struct BasisGatherer {
    params: GathererParams,
    gatherer: Arc<Mutex<Gatherer>>,
    cadence: Cadence,
    last_sent: Option<Instant>,
    /// Whether the newest map sent was marked steady.
    sent_steady: bool,
    report: GathererReport,
    update: Latency,
}

impl BasisGatherer {
    fn new(setup: &StageSetup) -> anyhow::Result<Self> {
        let params: GathererParams = setup.params()?;
        params
            .check()
            .map_err(|e| anyhow::anyhow!("{}: params: {e}", setup.info.name))?;
        let scene = cloudlight_scenes::load(&setup.scene)?;
        let lightmap = Lightmap::cached(&scene, &params.lightmap_settings()).map_err(|e| {
            anyhow::anyhow!(
                "{}: {} has no irradiance map (n/a): {e}",
                setup.info.name,
                scene.name
            )
        })?;
        let report = GathererReport {
            resolution: lightmap.texels.width,
            valid_texels: lightmap.texels.valid_count(),
            charts: lightmap.atlas.charts,
            utilization: lightmap.atlas.utilization,
            unwrap_s: lightmap.atlas.unwrap_s,
            bases: lightmap.bases.bases.len(),
            client_bytes: lightmap.client_bytes(),
            ..Default::default()
        };
        let gatherer = Gatherer::new(lightmap, params.gather_settings(setup.seed));
        let cadence = Cadence::every_ms(params.interval_ms);
        Ok(BasisGatherer {
            gatherer: Arc::new(Mutex::new(gatherer)),
            cadence,
            last_sent: None,
            sent_steady: false,
            report,
            update: Latency::new(),
            params,
        })
    }

    fn publish(&mut self, ctx: &StageCtx) {
        let r = &mut self.report;
        r.update_ms_p50 = self.update.p50_ms();
        r.update_ms_p99 = self.update.p99_ms();
        r.update_ms_mean = self.update.mean_ms();
        r.overruns = self.cadence.overruns();
        r.summary = format!(
            "{} updates (p50 {:.1} ms, {} rays, {} converged; {:.0}% of points gathered and {:.0}% of direct light computed per update), {}² map, {} bases, {} maps sent",
            r.updates,
            r.update_ms_p50,
            r.rays_per_update,
            r.converged_updates,
            r.regathered_fraction * 100.0,
            r.direct_fraction * 100.0,
            r.resolution,
            r.bases,
            r.maps_sent
        );
        ctx.report(serde_json::to_value(&self.report).unwrap_or_default());
    }

    /// One update on a blocking thread; sends the map unless the scene converged and it
    /// went out less than `resend_s` ago.
    async fn update(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        let t = ctx.scene_time_s();
        let g = self.gatherer.clone();
        let u = tokio::task::spawn_blocking(move || lock(&g).update(t)).await?;
        self.report.updates += 1;
        if u.converged {
            self.report.converged_updates += 1;
            let resend = Duration::from_secs_f64(self.params.resend_s);
            let recent = self.last_sent.is_some_and(|s| s.elapsed() < resend);
            // The first converged map goes out at once, marked steady: clients then know
            // their light is current. Later ones only as re-sends.
            if self.sent_steady && (recent || self.params.resend_s == 0.0) {
                return Ok(());
            }
            self.sent_steady = true;
        } else {
            self.sent_steady = false;
            self.update.record_s(u.seconds);
            self.report.rays_per_update = u.rays;
            let n = (self.report.updates - self.report.converged_updates) as f64;
            let mean = |old: f64, x: f64| old + (x - old) / n.max(1.0);
            self.report.regathered_fraction = mean(
                self.report.regathered_fraction,
                u.regathered as f64 / u.gather_points.max(1) as f64,
            );
            self.report.direct_fraction = mean(
                self.report.direct_fraction,
                u.direct_texels as f64 / self.report.valid_texels.max(1) as f64,
            );
        }
        let bytes = u.map.data_bytes() as u64;
        // A converged static map is valid until superseded: clients show it as current.
        let msg = FrameMsg::Hdr {
            map: (*u.map).clone(),
            steady: u.converged,
        };
        ctx.send(OUT, u.time_s, msg).await?;
        self.last_sent = Some(Instant::now());
        self.report.maps_sent += 1;
        self.report.bytes_sent += bytes;
        Ok(())
    }
}

#[async_trait::async_trait]
impl Stage for BasisGatherer {
    async fn on_start(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        self.publish(ctx);
        Ok(())
    }

    async fn on_tick(&mut self, ctx: &mut StageCtx) -> anyhow::Result<NextTick> {
        if ctx.is_stopping() {
            return Ok(NextTick::Never);
        }
        self.cadence.begin();
        self.update(ctx).await?;
        let next = self.cadence.end_tick();
        self.publish(ctx);
        Ok(next)
    }

    async fn on_stop(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        self.publish(ctx);
        Ok(())
    }
}

/// Registers `basis_gatherer`.
pub fn register(registry: &mut cloudlight_runtime::StageRegistry) {
    registry.register(
        StageKind::new(
            "basis_gatherer",
            TECHNIQUE,
            "gathers one bounce per update at light-map bases and streams the irradiance map",
            |s| Ok(Box::new(BasisGatherer::new(s)?)),
        )
        .output(OUT)
        .checked_params::<GathererParams>()
        .scene_check(|table, scene| {
            let params: GathererParams = cloudlight_runtime::parse_params(table)?;
            let scene = crate::the_scene(scene)?;
            Lightmap::cached(scene, &params.lightmap_settings())
                .map(|_| ())
                .map_err(|e| format!("{} has no irradiance map (n/a): {e}", scene.name))
        }),
    );
}
