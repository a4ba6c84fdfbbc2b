//! The client's frame alone on the machine (`cloudlight bench client`): frame time p50/p99
//! whole, and split by pass (each pass submitted and waited for on its own), for any
//! technique's indirect pass, with the scene's lights moving as its animation says (shadow
//! maps are rendered again only on frames where a light moved), beside the raster anchor of
//! `TARGETS.md` measured on the same device in the same run ([`raster_anchor`]).

use std::time::{Duration, Instant};

use cloudlight_render::raster::{
    FrameInputs, FrameRenderer, IndirectPass, NoIndirect, PassTimes, Raster, Readback,
    ShadowSettings,
};
use cloudlight_scenes::Scene;
use serde::Serialize;

/// What to measure.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct ClientBenchOptions {
    /// Frame width, pixels.
    pub width: u32,
    /// Frame height, pixels.
    pub height: u32,
    /// Frames timed (each of the two runs: whole frames, then split by pass).
    pub frames: usize,
    /// Scene time advances 1/fps per frame.
    pub fps: f64,
    /// Emissive triangles become n² point emitters each.
    pub light_samples: u32,
    /// Shadow-map side, texels.
    pub shadow_size: u32,
    /// A still view (camera and lights as in the frame before) accumulates its jittered
    /// frames, as the client shell does (its `accumulate`).
    pub accumulate: bool,
}

impl Default for ClientBenchOptions {
    fn default() -> Self {
        ClientBenchOptions {
            width: 640,
            height: 360,
            frames: 30,
            fps: 30.0,
            light_samples: cloudlight_actors::client::DEFAULT_LIGHT_SAMPLES,
            shadow_size: 512,
            accumulate: true,
        }
    }
}

/// One pass's times.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PassStat {
    /// Pass name (a step of the technique's pass: `indirect: <step>`).
    pub pass: String,
    /// Median, ms.
    pub p50_ms: f64,
    /// 99th percentile, ms.
    pub p99_ms: f64,
    /// Mean, ms.
    pub mean_ms: f64,
}

/// The client benchmark's result.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ClientBench {
    /// Scene.
    pub scene: String,
    /// Triangles drawn.
    pub triangles: usize,
    /// Lights of the direct pass (emitter samples included).
    pub lights: usize,
    /// The adapter.
    pub adapter: String,
    /// What the technique's pass drew (e.g. `9,981 photons`), as the technique says it.
    pub indirect: String,
    /// Settings.
    pub options: ClientBenchOptions,
    /// Whole frames (one submit, nothing read back): median, ms.
    pub frame_p50_ms: f64,
    /// Whole frames: 99th percentile, ms.
    pub frame_p99_ms: f64,
    /// Split by pass (read-back of the composed frame included).
    pub passes: Vec<PassStat>,
    /// Frames (of the split run) that rendered shadow maps.
    pub frames_with_shadows: usize,
    /// The raster anchor measured in the same run, where it was ([`raster_anchor`]).
    pub anchor: Option<RasterAnchor>,
}

/// Triangles of the raster anchor's scene (`city:100000`).
pub const ANCHOR_TRIANGLES: usize = 100_000;
/// The raster anchor's frame size.
pub const ANCHOR_SIZE: (u32, u32) = (1280, 720);
/// What `TARGETS.md` gives for the anchor on this kind of machine (lavapipe, 2 cores): "draws
/// 100k triangles at 1280×720 in 20–25 ms", ms.
pub const ANCHOR_TARGETS_MS: (f64, f64) = (20.0, 25.0);

/// The raster anchor as measured in one run: how fast this device draws what `TARGETS.md`
/// timed, so that a frame time can be read against the speed the targets assume (a shared
/// machine's speed drifts by a third between runs).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RasterAnchor {
    /// Triangles drawn.
    pub triangles: usize,
    /// Frame width, pixels.
    pub width: u32,
    /// Frame height, pixels.
    pub height: u32,
    /// Frames timed.
    pub frames: usize,
    /// The G-buffer pass (each frame submitted and waited for on its own): median, ms.
    pub gbuffer_p50_ms: f64,
    /// The backend it ran on (`Vulkan`, `Gl`, ...).
    pub backend: String,
}

impl RasterAnchor {
    /// How much slower than the middle of `TARGETS.md`'s range this run's device drew the
    /// anchor (1: as fast; 1.4: a slow phase of a shared machine).
    pub fn slowdown(&self) -> f64 {
        let (lo, hi) = ANCHOR_TARGETS_MS;
        self.gbuffer_p50_ms / (0.5 * (lo + hi))
    }

    /// Whether it ran where `TARGETS.md` timed it: lavapipe is Vulkan. GL llvmpipe draws
    /// the anchor much faster than lavapipe (back to back: 29.0 against 54.1 ms; 18.7 on
    /// GL on a day lavapipe read 20–39) but the photon client's passes as fast, so its
    /// slowdown does not carry over to a frame.
    pub fn comparable(&self) -> bool {
        self.backend == "Vulkan"
    }
}

/// Times the raster anchor: the G-buffer pass of `city:100000` seen whole
/// ([`Scene::overview_camera`]: every chunk in view) at 1280×720 without lights or indirect
/// light, `frames` frames after two warm-up frames. What the process drew before moves it
/// (after Cornell frames it read 29–31 ms, after `city:250000` frames 21–28 ms, in
/// alternating runs; more warm-up frames changed nothing): a guide to the machine's speed,
/// not an exact correction.
pub fn raster_anchor(raster: &Raster, frames: usize) -> anyhow::Result<RasterAnchor> {
    let scene = cloudlight_scenes::city::city(ANCHOR_TRIANGLES);
    let triangles = scene.triangles_at(0.0);
    let (width, height) = ANCHOR_SIZE;
    let mut frame = FrameRenderer::new(raster, width, height, ShadowSettings::default())?;
    frame.set_geometry(raster, &scene, &triangles)?;
    let inputs = FrameInputs {
        camera: scene.overview_camera(),
        lights: &[],
        still: None,
    };
    let frames = frames.max(1);
    let mut times = Vec::with_capacity(frames);
    for i in 0..frames + 2 {
        let images = frame.render(raster, &inputs, &mut NoIndirect, Readback::Nothing, true)?;
        if i >= 2 {
            times.push(ms(images.times.gbuffer));
        }
    }
    Ok(RasterAnchor {
        triangles: triangles.len(),
        width,
        height,
        frames,
        gbuffer_p50_ms: stat("anchor", times).p50_ms,
        backend: format!("{:?}", raster.adapter().backend),
    })
}

fn stat(pass: impl Into<String>, mut ms: Vec<f64>) -> PassStat {
    ms.sort_by(f64::total_cmp);
    let q = |p: f64| {
        ms.get(((ms.len() as f64 - 1.0) * p).round() as usize)
            .copied()
            .unwrap_or(0.0)
    };
    PassStat {
        pass: pass.into(),
        p50_ms: q(0.5),
        p99_ms: q(0.99),
        mean_ms: ms.iter().sum::<f64>() / ms.len().max(1) as f64,
    }
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1000.0
}

/// Renders `options.frames` frames of `scene`'s first camera with `indirect` as the
/// technique's pass, twice (whole frames, then split by pass), after two warm-up frames.
pub fn measure(
    raster: &Raster,
    scene: &Scene,
    indirect: &mut dyn IndirectPass,
    options: ClientBenchOptions,
) -> anyhow::Result<ClientBench> {
    let mut frame = FrameRenderer::new(
        raster,
        options.width,
        options.height,
        ShadowSettings {
            size: options.shadow_size,
            ..Default::default()
        },
    )?;
    let moving = scene.has_moving_geometry();
    let mut triangles = scene.triangles_at(0.0);
    frame.set_geometry(raster, scene, &triangles)?;
    let static_samples = (!moving).then(|| scene.surface_light_samples(0.0, options.light_samples));
    let camera_path = scene
        .cameras
        .first()
        .ok_or_else(|| anyhow::anyhow!("scene `{}` has no camera", scene.name))?;
    let mut lights_count = 0;
    let mut whole = Vec::new();
    let mut split: Vec<PassTimes> = Vec::new();
    // A still view's frame number, as the client shell counts it (the technique's light does
    // not change here).
    let mut last_view = None;
    let mut still: Option<u32> = None;
    let total = 2 + 2 * options.frames.max(1);
    for i in 0..total {
        let t = i as f64 / options.fps.max(1e-3);
        if moving {
            triangles = scene.triangles_at(t);
            frame.set_geometry(raster, scene, &triangles)?;
        }
        let lights = match &static_samples {
            Some(s) => scene.direct_lights(t, s),
            None => scene.direct_lights(t, &scene.surface_light_samples(t, options.light_samples)),
        };
        lights_count = lights.len();
        let camera = camera_path.at(t);
        let view = Some((camera, lights.clone()));
        still = (options.accumulate && !moving && view == last_view)
            .then(|| still.map_or(0, |k| k + 1));
        last_view = view;
        let inputs = FrameInputs {
            camera,
            lights: &lights,
            still,
        };
        let timed = i >= 2 + options.frames;
        let readback = if timed {
            Readback::Composed
        } else {
            Readback::Nothing
        };
        let start = Instant::now();
        let images = frame.render(raster, &inputs, indirect, readback, timed)?;
        if i < 2 {
            continue;
        }
        if timed {
            split.push(images.times);
        } else {
            whole.push(ms(start.elapsed()));
        }
    }
    let pick = |f: fn(&PassTimes) -> Duration| split.iter().map(|p| ms(f(p))).collect::<Vec<_>>();
    let whole_stat = stat("frame", whole);
    // The technique's steps, in the order its pass ran them.
    let mut step_names: Vec<&'static str> = Vec::new();
    for (name, _) in split.iter().flat_map(|p| &p.indirect_steps) {
        if !step_names.contains(name) {
            step_names.push(name);
        }
    }
    let steps = step_names.into_iter().map(|name| {
        let times = split
            .iter()
            .map(|p| {
                let d = p
                    .indirect_steps
                    .iter()
                    .filter(|(n, _)| *n == name)
                    .map(|(_, d)| *d);
                ms(d.sum())
            })
            .collect();
        stat(format!("indirect: {name}"), times)
    });
    Ok(ClientBench {
        scene: scene.name.clone(),
        triangles: triangles.len(),
        lights: lights_count,
        adapter: raster.describe(),
        indirect: String::new(),
        options,
        frame_p50_ms: whole_stat.p50_ms,
        frame_p99_ms: whole_stat.p99_ms,
        passes: vec![
            stat("gbuffer", pick(|p| p.gbuffer)),
            stat("shadows", pick(|p| p.shadows)),
            stat("direct", pick(|p| p.direct)),
            stat("indirect", pick(|p| p.indirect)),
        ]
        .into_iter()
        .chain(steps)
        .chain([
            stat("compose", pick(|p| p.compose)),
            stat("accumulate", pick(|p| p.accumulate)),
            stat("readback", pick(|p| p.readback)),
            stat("total (split)", pick(|p| p.total)),
        ])
        .collect(),
        frames_with_shadows: split.iter().filter(|p| p.shadows_rendered).count(),
        anchor: None,
    })
}

impl ClientBench {
    /// The per-pass table.
    pub fn table(&self) -> String {
        let mut t = super::table::Markdown::new(&["pass", "p50 ms", "p99 ms", "mean ms"]);
        t.row(vec![
            "whole frame (one submit, no read-back)".into(),
            format!("{:.1}", self.frame_p50_ms),
            format!("{:.1}", self.frame_p99_ms),
            String::new(),
        ]);
        for p in &self.passes {
            t.row(vec![
                p.pass.to_string(),
                format!("{:.2}", p.p50_ms),
                format!("{:.2}", p.p99_ms),
                format!("{:.2}", p.mean_ms),
            ]);
        }
        t.render()
    }

    /// The anchor's line: its time in this run against `TARGETS.md`'s, and the whole frame
    /// at the speed the targets assume where the anchor ran on their backend (None without
    /// an anchor).
    pub fn anchor_line(&self) -> Option<String> {
        let a = self.anchor.as_ref()?;
        let (lo, hi) = ANCHOR_TARGETS_MS;
        let slowdown = a.slowdown();
        let head = format!(
            "raster anchor (TARGETS.md: {}k triangles at {}x{} in {lo:.0}–{hi:.0} ms on lavapipe, \
             Vulkan): {} triangles in {:.1} ms p50 in this run ({}), {slowdown:.2}× the targets' \
             time",
            ANCHOR_TRIANGLES / 1000,
            a.width,
            a.height,
            a.triangles,
            a.gbuffer_p50_ms,
            a.backend,
        );
        Some(if a.comparable() {
            format!(
                "{head}; the whole frame at their speed: {:.1} / {slowdown:.2} = {:.1} ms p50",
                self.frame_p50_ms,
                self.frame_p50_ms / slowdown.max(1e-9),
            )
        } else {
            format!("{head}; not their backend, so the frame is not scaled by it")
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_anchor_reads_a_frame_at_the_speed_the_targets_assume() {
        let anchor = RasterAnchor {
            triangles: 100_034,
            width: 1280,
            height: 720,
            frames: 10,
            gbuffer_p50_ms: 45.0,
            backend: "Vulkan".into(),
        };
        // Twice the middle of 20–25 ms: the machine ran at half the targets' speed.
        assert!((anchor.slowdown() - 2.0).abs() < 1e-12);
        let bench = ClientBench {
            scene: "cornell".into(),
            triangles: 32,
            lights: 2,
            adapter: "test".into(),
            indirect: String::new(),
            options: ClientBenchOptions::default(),
            frame_p50_ms: 50.0,
            frame_p99_ms: 60.0,
            passes: Vec::new(),
            frames_with_shadows: 0,
            anchor: None,
        };
        assert_eq!(bench.anchor_line(), None);
        let line = ClientBench {
            anchor: Some(anchor.clone()),
            ..bench.clone()
        }
        .anchor_line()
        .unwrap();
        assert!(
            line.contains("in 45.0 ms p50 in this run (Vulkan), 2.00×"),
            "{line}"
        );
        assert!(line.contains("50.0 / 2.00 = 25.0 ms p50"), "{line}");
        // On GL the anchor is no yardstick for the targets' backend: no scaled frame.
        let gl = ClientBench {
            anchor: Some(RasterAnchor {
                backend: "Gl".into(),
                ..anchor
            }),
            ..bench
        }
        .anchor_line()
        .unwrap();
        assert!(
            gl.contains("in 45.0 ms p50 in this run (Gl), 2.00×"),
            "{gl}"
        );
        assert!(gl.contains("not scaled") && !gl.contains("= 25.0"), "{gl}");
    }
}
