//! `cloudlight bench video`: H.264 encode and decode time per frame, Mbps at 30 Hz and
//! quality, for SDR frames of a client (the raster's direct light, tone-mapped to sRGB) at
//! 640×360 and 1280×720, and for an HDR light map through the log-luminance packing — each
//! beside the paper's figures (a hardware encoder: 4.2 ms per 720p frame, 3–6 Mbps per
//! client, about 1 ms decode).

use cloudlight_render::metrics::tonemap;
use cloudlight_render::raster::{Raster, ShadowSettings};
use cloudlight_render::video::RateControl;
use cloudlight_render::video::measure::{self, HdrCodecFigures, SdrCodecFigures};
use serde::Serialize;

/// The paper's video figures (Table 2 and section 5).
pub const PAPER_ENCODE_MS_720P: f64 = 4.2;
/// Mbps per client the paper streams.
pub const PAPER_MBPS: (f64, f64) = (3.0, 6.0);
/// Decode time the paper reports per frame, ms.
pub const PAPER_DECODE_MS: f64 = 1.0;

/// What to measure.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct VideoBenchOptions {
    /// Scene the frames show (its lights move when it is animated).
    pub scene: String,
    /// Frame sizes, pixels.
    pub sizes: Vec<(u32, u32)>,
    /// Frames per size.
    pub frames: usize,
    /// SDR rate settings.
    pub sdr_rates: Vec<RateControl>,
    /// HDR light-map side, texels, and reference samples per texel.
    pub hdr_size: u32,
    /// Samples per texel of the HDR map.
    pub hdr_spp: u32,
    /// HDR rate settings.
    pub hdr_rates: Vec<RateControl>,
}

impl Default for VideoBenchOptions {
    fn default() -> Self {
        VideoBenchOptions {
            scene: "cornell-animated".into(),
            sizes: vec![(640, 360), (1280, 720)],
            frames: 30,
            sdr_rates: vec![
                RateControl::Bitrate(1_500_000),
                RateControl::Bitrate(3_000_000),
                RateControl::Bitrate(6_000_000),
                RateControl::FixedQp(24),
            ],
            hdr_size: 128,
            hdr_spp: 256,
            hdr_rates: [12, 20, 28, 36].map(RateControl::FixedQp).to_vec(),
        }
    }
}

/// The benchmark's result.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct VideoBench {
    /// Scene.
    pub scene: String,
    /// The adapter the frames were rendered on.
    pub adapter: String,
    /// SDR rows.
    pub sdr: Vec<SdrCodecFigures>,
    /// HDR rows (one map of `hdr_size`²).
    pub hdr: Vec<HdrCodecFigures>,
    /// HDR map side.
    pub hdr_size: u32,
}

/// Renders the SDR frames of one size: the scene's first camera turning about its target,
/// scene time 1/30 s apart.
fn client_frames(
    raster: &Raster,
    scene: &cloudlight_scenes::Scene,
    (width, height): (u32, u32),
    frames: usize,
) -> anyhow::Result<Vec<Vec<u8>>> {
    let mut out = Vec::with_capacity(frames);
    let mut exposure = None;
    for i in 0..frames {
        let t = i as f64 / 30.0;
        let tris = scene.triangles_at(t);
        let mut lights: Vec<_> = scene.lights.iter().map(|l| l.at(t)).collect();
        lights.extend(scene.surface_light_samples(t, 2));
        // The view turns about its target, 20° per second, as a moving client's would: a
        // still camera leaves P frames nearly empty and flatters the encoder.
        let mut camera = scene
            .cameras
            .first()
            .map_or_else(|| scene.overview_camera(), |c| c.at(t));
        let turn = cloudlight_scenes::glam::Quat::from_rotation_y((20.0 * t as f32).to_radians());
        camera.position = camera.target + turn * (camera.position - camera.target);
        let (_, direct) = raster.direct(
            scene,
            &tris,
            &lights,
            &camera,
            width,
            height,
            ShadowSettings::default(),
        )?;
        let stops =
            *exposure.get_or_insert_with(|| cloudlight_render::image_io::auto_exposure(&direct));
        out.push(tonemap(&direct, stops));
    }
    Ok(out)
}

/// Runs the benchmark, printing progress to stderr.
pub fn run(raster: &Raster, opts: &VideoBenchOptions) -> anyhow::Result<VideoBench> {
    let scene = cloudlight_scenes::load(&opts.scene)?;
    let mut sdr = Vec::new();
    for &size in &opts.sizes {
        eprintln!(
            "rendering {} frames at {}x{} on {}...",
            opts.frames,
            size.0,
            size.1,
            raster.describe()
        );
        let frames = client_frames(raster, &scene, size, opts.frames)?;
        for &rate in &opts.sdr_rates {
            eprintln!("encoding {}x{} at {rate:?}...", size.0, size.1);
            sdr.push(measure::sdr_codec(size.0, size.1, &frames, rate)?);
        }
    }
    eprintln!(
        "tracing a {0}x{0} HDR map at {1} spp...",
        opts.hdr_size, opts.hdr_spp
    );
    let map = measure::reference_map(&scene, opts.hdr_size, opts.hdr_spp);
    let hdr = opts
        .hdr_rates
        .iter()
        .map(|&r| measure::hdr_codec(&map, r))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(VideoBench {
        scene: scene.name.clone(),
        adapter: raster.describe(),
        sdr,
        hdr,
        hdr_size: opts.hdr_size,
    })
}

fn rate_name(r: RateControl) -> String {
    match r {
        RateControl::Bitrate(bps) => format!("{:.1} Mbit/s", bps as f64 / 1e6),
        RateControl::FixedQp(q) => format!("QP {q}"),
    }
}

/// The result as Markdown tables, the paper's figures beside ours.
pub fn markdown(b: &VideoBench) -> String {
    let mut s = format!(
        "SDR frames of `{}` (raster direct light on {}; the view turns 20°/s about its target), openh264 on one core, 30 Hz\n\n\
         | size | rate | encode ms p50 | paper encode ms (720p, HW) | ratio paper/ours | decode ms p50 | paper decode ms | Mbps | paper Mbps | PSNR-Y dB |\n\
         |---|---|---|---|---|---|---|---|---|---|\n",
        b.scene, b.adapter
    );
    for r in &b.sdr {
        let paper_enc = PAPER_ENCODE_MS_720P * (r.width * r.height) as f64 / (1280.0 * 720.0);
        s += &format!(
            "| {}x{} | {} | {:.2} | {:.2} | {:.2} | {:.2} | {:.1} | {:.2} | {}–{} | {:.1} |\n",
            r.width,
            r.height,
            rate_name(r.rate),
            r.encode_ms_p50,
            paper_enc,
            paper_enc / r.encode_ms_p50.max(1e-9),
            r.decode_ms_p50,
            PAPER_DECODE_MS,
            r.mbps_at_30hz,
            PAPER_MBPS.0,
            PAPER_MBPS.1,
            r.psnr_y_db
        );
    }
    s += &format!(
        "\nHDR light map ({0}x{0} texels of the reference tracer's indirect light), log2-luminance packing\n\n\
         | rate | packing alone: rel. lum. error mean / max | coded: mean / p99 | chroma error mean | key frame bytes | next frame bytes | Mbps at 30 Hz (key + 29 P) |\n\
         |---|---|---|---|---|---|---|\n",
        b.hdr_size
    );
    for r in &b.hdr {
        let mbps = (r.key_bytes + 29 * r.next_bytes) as f64 * 8.0 / 1e6;
        s += &format!(
            "| {} | {:.2}% / {:.2}% | {:.2}% / {:.2}% | {:.4} | {} | {} | {:.3} |\n",
            rate_name(r.rate),
            100.0 * r.packing.luminance_mean,
            100.0 * r.packing.luminance_max,
            100.0 * r.key.luminance_mean,
            100.0 * r.key.luminance_p99,
            r.key.chroma_mean,
            r.key_bytes,
            r.next_bytes,
            mbps
        );
    }
    s
}
