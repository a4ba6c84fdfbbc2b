//! `video_encoder` in running clusters: pictures from a test source, H.264 units decoded by a
//! test sink, in one process and across a cut edge over loopback; SDR frames keep their
//! order, times and quality, HDR maps their luminance, a late decoder starts at a key frame.

mod common;

use std::sync::{Arc, Mutex};

use cloudlight::actors::wire::{FrameMsg, HdrMap, VideoMsg};
use cloudlight::render::video::{Decoder, Yuv420, hdr, psnr};
use cloudlight::runtime::{
    EdgeSettings, EndReason, Input, NextTick, Policy, Port, RunOptions, Stage, StageCtx, StageKind,
    StageRegistry,
};
use cloudlight::scenes::glam::Vec3;
use common::{plan_text, run_plan};
use serde::Deserialize;

const PICTURES: Port<FrameMsg> = Port::new("out");
const UNITS_IN: Port<VideoMsg> = Port::new("in");

const W: u32 = 96;
const H: u32 = 64;

/// Picture `i` of the test stream: gradients and a square that moves.
fn picture(i: u64) -> Vec<u8> {
    let mut rgb = Vec::with_capacity((W * H * 3) as usize);
    for y in 0..H {
        for x in 0..W {
            let inside = (x + 3 * i as u32) % W < 20 && (20..44).contains(&y);
            rgb.extend(if inside {
                [240, 230, 40]
            } else {
                [(x * 255 / W) as u8, (y * 255 / H) as u8, 120]
            });
        }
    }
    rgb
}

/// HDR map `i`: 10 stops across, tinted, brighter with `i`.
fn map(i: u64) -> Vec<Vec3> {
    (0..W * H)
        .map(|k| {
            let (x, y) = (k % W, k / W);
            let l = (x as f32 / W as f32 * 10.0 - 4.0 + i as f32 * 0.01).exp2();
            Vec3::new(l, l * (0.5 + y as f32 / H as f32 * 0.5), l * 0.7)
        })
        .collect()
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SourceParams {
    count: u64,
    #[serde(default)]
    hdr: bool,
    /// Live: one picture per 1/30 s of wall time, stamped with the cluster's scene time and
    /// showing light this many seconds older (a renderer in the cloud); otherwise pictures as
    /// fast as the edge takes them, 1/30 s of scene time apart.
    #[serde(default)]
    live_light_lag_s: Option<f64>,
}

struct Source {
    p: SourceParams,
    next: u64,
}

#[async_trait::async_trait]
impl Stage for Source {
    async fn on_tick(&mut self, ctx: &mut StageCtx) -> anyhow::Result<NextTick> {
        if self.next >= self.p.count {
            return Ok(NextTick::Never);
        }
        let frame = if self.p.hdr {
            FrameMsg::Hdr {
                map: HdrMap::new(W, H, &map(self.next), &[])?,
                steady: false,
            }
        } else {
            FrameMsg::Sdr {
                width: W,
                height: H,
                rgb: picture(self.next),
                light_s: None,
            }
        };
        self.next += 1;
        if let Some(lag) = self.p.live_light_lag_s {
            let t = ctx.scene_time_s();
            let frame = match frame {
                FrameMsg::Sdr {
                    width, height, rgb, ..
                } => FrameMsg::Sdr {
                    width,
                    height,
                    rgb,
                    light_s: Some(t - lag),
                },
                hdr => hdr,
            };
            ctx.send(PICTURES, t, frame).await?;
            return Ok(NextTick::After(std::time::Duration::from_secs_f64(
                1.0 / 30.0,
            )));
        }
        // Scene time 1/30 s per picture, whatever the wall clock does.
        ctx.send(PICTURES, (self.next - 1) as f64 / 30.0, frame)
            .await?;
        Ok(NextTick::After(std::time::Duration::from_millis(5)))
    }
}

/// What a sink decoded: (index, key, scene time, luma PSNR or HDR mean error).
type Decoded = Vec<(u64, bool, f64, f64)>;

#[derive(Default)]
struct Seen {
    by_sink: Mutex<std::collections::HashMap<String, (Decoded, u64)>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SinkParams {
    /// Ignore units before this index (a client joining late).
    #[serde(default)]
    join_at: u64,
}

struct Sink {
    p: SinkParams,
    decoder: Decoder,
    seen: Arc<Seen>,
    name: String,
}

#[async_trait::async_trait]
impl Stage for Sink {
    async fn on_input(&mut self, _ctx: &mut StageCtx, input: Input) -> anyhow::Result<()> {
        let msg = input.on(UNITS_IN)?;
        let v = &msg.body;
        if v.index < self.p.join_at {
            return Ok(());
        }
        let picture_out = self.decoder.decode(&v.data)?;
        let mut seen = self.seen.by_sink.lock().unwrap();
        let entry = seen.entry(self.name.clone()).or_default();
        entry.1 += 1;
        let Some(yuv) = picture_out else {
            return Ok(());
        };
        let quality = match v.hdr {
            Some(range) => {
                let original = HdrMap::new(W, H, &map(v.index), &[])?;
                hdr::error(&original, &hdr::unpack(&yuv, range), range).luminance_mean
            }
            None => psnr(&Yuv420::from_rgb8(W, H, &picture(v.index))?.y, &yuv.y),
        };
        entry.0.push((v.index, v.key, msg.scene_time_s, quality));
        Ok(())
    }
}

fn registry(seen: &Arc<Seen>) -> StageRegistry {
    let mut r = cloudlight::actors::registry();
    let edge = EdgeSettings {
        capacity: 16,
        policy: Policy::Block,
    };
    r.register(
        StageKind::new("frame_source", "test", "test pictures", |s| {
            Ok(Box::new(Source {
                p: s.params()?,
                next: 0,
            }))
        })
        .output(PICTURES)
        .params::<SourceParams>(),
    );
    common::register_unit_gate(&mut r);
    let seen = seen.clone();
    r.register(
        StageKind::new("video_sink", "test", "decodes and scores", move |s| {
            Ok(Box::new(Sink {
                p: s.params()?,
                decoder: Decoder::new()?,
                seen: seen.clone(),
                name: s.info.name.to_string(),
            }))
        })
        .input(UNITS_IN, edge)
        .params::<SinkParams>(),
    );
    r
}

fn topology(encoder_node: &str, source: &str, encoder: &str, sinks: &str) -> String {
    format!(
        r#"techniques = ["video", "test"]
cluster = "video-tests"
secret = "not very secret"
[[node]]
name = "cloud"
address = "127.0.0.1:0"
[[node]]
name = "home"
address = "127.0.0.1:0"
[[link]]
between = ["cloud", "home"]
latency_ms = 2.0
loss = 0.01
[[stage]]
name = "src"
kind = "frame_source"
node = "cloud"
params = {{ {source} }}
[[stage]]
name = "enc"
kind = "video_encoder"
node = "{encoder_node}"
params = {{ {encoder} }}
[[stage]]
name = "view"
kind = "video_sink"
node = "home"
{sinks}
[[edge]]
from = "src"
to = "enc"
policy = "block"
capacity = 4
[[edge]]
from = "enc"
to = "view"
"#
    )
}

async fn run(text: &str, seen: &Arc<Seen>) {
    let reg = registry(seen);
    let plan = plan_text(text, &reg);
    let report = run_plan(&plan, &reg, RunOptions::default()).await.unwrap();
    assert_eq!(report.end, EndReason::Finished);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sdr_pictures_cross_a_cut_edge_in_order_with_their_times_and_quality() {
    let seen = Arc::new(Seen::default());
    // The encoder on the cloud, the decoder at home: the access units cross the network.
    run(
        &topology("cloud", "count = 60", "qp = 22, keyframe_s = 1.0", ""),
        &seen,
    )
    .await;
    let by_sink = seen.by_sink.lock().unwrap();
    let (decoded, units) = &by_sink["view"];
    assert_eq!(*units, 60, "every unit arrives (a block edge)");
    assert_eq!(decoded.len(), 60);
    for (k, (index, key, t, db)) in decoded.iter().enumerate() {
        assert_eq!(*index, k as u64);
        assert_eq!(
            *key,
            k % 30 == 0,
            "picture {k}: a key frame each second of scene time"
        );
        assert!(
            (t - k as f64 / 30.0).abs() < 1e-9,
            "picture {k} keeps its scene time"
        );
        assert!(*db > 38.0, "picture {k}: {db:.1} dB at QP 22");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hdr_maps_keep_their_luminance_and_a_late_client_starts_at_a_key_frame() {
    let seen = Arc::new(Seen::default());
    // One encoder (at home, beside its clients) feeding two: one from the start, one that
    // joins at picture 10 and must wait for the key frame at 15 (keyframe_s = 0.5).
    let late = "[[stage]]\nname = \"late\"\nkind = \"video_sink\"\nnode = \"home\"\nparams = { join_at = 10 }\n[[edge]]\nfrom = \"enc\"\nto = \"late\"\n";
    let text = topology(
        "home",
        "count = 40, hdr = true",
        "qp = 16, keyframe_s = 0.5",
        "",
    ) + late;
    run(&text, &seen).await;
    let by_sink = seen.by_sink.lock().unwrap();
    let (decoded, _) = &by_sink["view"];
    assert_eq!(decoded.len(), 40);
    for (index, _, _, err) in decoded {
        assert!(
            *err < 0.03,
            "map {index}: mean relative luminance error {err:.4} at QP 16"
        );
    }
    let (late_decoded, late_units) = &by_sink["late"];
    assert_eq!(*late_units, 30, "units 10 to 39 reach the late client");
    let first = late_decoded
        .first()
        .expect("the late client shows pictures");
    assert_eq!(
        (first.0, first.1),
        (15, true),
        "its first picture is the key frame at 15"
    );
    assert_eq!(late_decoded.len(), 25);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_video_client_joining_late_shows_pictures_within_one_key_frame_interval() {
    // A live stream at 30 fps with key frames every 0.5 s (15 pictures); the real
    // `video_client`, across the cut edge, receives it from picture 10 on.
    let seen = Arc::new(Seen::default());
    let client = "kind = \"video_client\"\nnode = \"home\"\n\
        params = { width = 96, height = 64, fps = 30.0 }\n\
        [[stage]]\nname = \"gate\"\nkind = \"unit_gate\"\nnode = \"cloud\"\n\
        params = { drop_until = 10 }\n";
    let text = topology(
        "cloud",
        "count = 45, live_light_lag_s = 0.25",
        "qp = 24, keyframe_s = 0.5, fps = 30.0",
        "",
    )
    .replace("kind = \"video_sink\"\nnode = \"home\"\n", client)
    .replace(
        "from = \"enc\"\nto = \"view\"",
        "from = \"enc\"\nto = \"gate\"\n[[edge]]\nfrom = \"gate\"\nto = \"view\"",
    );
    let text = format!("duration_s = 2.5\n{text}");
    let reg = registry(&seen);
    let plan = plan_text(&text, &reg);
    let report = run_plan(&plan, &reg, RunOptions::default()).await.unwrap();
    assert_eq!(report.end, EndReason::Duration, "{text}");
    let view = report
        .metrics
        .stages
        .iter()
        .find(|s| s.name == "view")
        .and_then(|s| s.report.clone())
        .expect("the client reports");
    let decoder = &view["decoder"];
    let (units, pictures, waiting) = (
        decoder["units"].as_u64().unwrap(),
        decoder["pictures"].as_u64().unwrap(),
        decoder["waiting_for_key"].as_u64().unwrap(),
    );
    assert_eq!(decoder["errors"], 0, "{view}");
    assert_eq!(units, 35, "units 10 to 44 reach the client: {view}");
    assert!(
        (1..15).contains(&waiting),
        "it joined between key frames and waited less than one interval (15 pictures): {view}"
    );
    assert_eq!(
        pictures,
        units - waiting,
        "then it shows every picture: {view}"
    );
    assert_eq!(view["indirect_shown"], true, "{view}");
    // The age it reports is the light's (rendered 0.25 s before the picture), not the
    // picture's.
    let age = view["age_ms_p50"].as_f64().unwrap();
    assert!((250.0..1000.0).contains(&age), "age p50 {age} ms: {view}");
}
