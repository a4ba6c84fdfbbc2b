//! The client's frame alone on the machine (`cloudlight bench client`): frame time p50/p99
//! whole, and split by pass (each pass submitted and waited for on its own), for any
//! technique's indirect pass, with the scene's lights moving as its animation says (shadow
//! maps are rendered again only on frames where a light moved).

use std::time::{Duration, Instant};

use cloudlight_render::raster::{
    FrameInputs, FrameRenderer, IndirectPass, PassTimes, Raster, Readback, ShadowSettings,
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
        let inputs = FrameInputs {
            camera: camera_path.at(t),
            lights: &lights,
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
            stat("readback", pick(|p| p.readback)),
            stat("total (split)", pick(|p| p.total)),
        ])
        .collect(),
        frames_with_shadows: split.iter().filter(|p| p.shadows_rendered).count(),
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
}
