//! The voxel technique in running clusters: the GI stages on a cloud node stream Haar
//! deltas over an emulated lossy link to frame renderers on another node; none and fifty
//! of them.

mod common;

use cloudlight::runtime::RunOptions;
use common::{f, plan_text, report, run_plan};

/// The GI stages (depth 4, updates every 100 ms) on `cloud` over a 10 ms, 1%-loss link to
/// `clients` measuring frame renderers on `home` (none: the GI stages alone).
fn topology(clients: u32) -> String {
    let renderers = if clients == 0 {
        String::new()
    } else {
        format!(
            r#"[[stage]]
name = "render"
kind = "frame_renderer"
node = "home"
replicas = {clients}
params = {{ max_depth = 4, width = 64, height = 48, fps = 10.0, render = false }}
[[edge]]
from = "cones.out"
to = "render.in"
"#
        )
    };
    format!(
        r#"techniques = ["voxels"]
scene = "cornell-animated"
seed = 5
duration_s = 2.5
cluster = "voxel-tests"
secret = "s"
[[node]]
name = "cloud"
address = "127.0.0.1:0"
[[node]]
name = "home"
address = "127.0.0.1:0"
[[link]]
between = ["cloud", "home"]
latency_ms = 10.0
loss = 0.01
[[stage]]
name = "inject"
kind = "light_injector"
node = "cloud"
params = {{ max_depth = 4, interval_ms = 100.0 }}
[[stage]]
name = "filter"
kind = "octree_filter"
node = "cloud"
[[stage]]
name = "cones"
kind = "cone_tracer"
node = "cloud"
params = {{ key_every = 5 }}
[[edge]]
from = "inject.out"
to = "filter.in"
[[edge]]
from = "filter.out"
to = "cones.in"
[[edge]]
from = "cones.bounce"
to = "inject.bounce"
{renderers}"#
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn zero_and_fifty_frame_renderers_follow_one_gi_node() {
    let registry = cloudlight::actors::registry();
    let alone = run_plan(
        &plan_text(&topology(0), &registry),
        &registry,
        RunOptions::default(),
    )
    .await
    .unwrap();
    let cones = report(&alone.metrics, "cones");
    assert!(f(cones, "updates") >= 3.0, "{cones}");
    assert!(f(report(&alone.metrics, "inject"), "bounces_applied") >= 1.0);
    // Fifty: one gather serves them all; every renderer applies every update it got whole,
    // refusing nothing (the deltas cross a lossy link, reliably).
    let run = run_plan(
        &plan_text(&topology(50), &registry),
        &registry,
        RunOptions::default(),
    )
    .await
    .unwrap();
    let cones = report(&run.metrics, "cones");
    assert!(f(cones, "updates_sent") >= 2.0, "{cones}");
    for i in 0..50 {
        let r = report(&run.metrics, &format!("render[{i}]"));
        assert!(f(r, "updates_complete") >= 1.0, "render[{i}]: {r}");
        for refused in [
            "deltas_rejected",
            "deltas_foreign",
            "deltas_out_of_sequence",
        ] {
            assert_eq!(f(r, refused), 0.0, "render[{i}]: {r}");
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_thin_client_in_an_outage_keeps_its_last_frame_reports_the_gap_and_recovers_at_a_key_frame()
 {
    // voxels-cloud in small: the GI stages and one client's frame renderer and encoder on
    // `cloud` (10 frames a second, a key frame every second = 10 units), a thin
    // `video_client` on `home`. A gate drops units 8 to 37 (three seconds): there is no
    // fallback light, so the client shows its last frame, counts the gap, and shows
    // pictures again from the next key frame.
    let thin = r#"[[stage]]
name = "render"
kind = "frame_renderer"
node = "cloud"
params = { max_depth = 4, width = 64, height = 48, fps = 10.0 }
[[stage]]
name = "encode"
kind = "video_encoder"
node = "cloud"
params = { qp = 24, keyframe_s = 1.0, fps = 10.0 }
[[stage]]
name = "gate"
kind = "unit_gate"
node = "cloud"
params = { drop_from = 8, drop_until = 38 }
[[stage]]
name = "viewer"
kind = "video_client"
node = "home"
params = { width = 64, height = 48, fps = 10.0 }
[[edge]]
from = "cones.out"
to = "render.in"
[[edge]]
from = "render.frames"
to = "encode.in"
[[edge]]
from = "encode.out"
to = "gate.in"
[[edge]]
from = "gate.out"
to = "viewer.in"
policy = "block"
capacity = 16
"#;
    let text = topology(0)
        .replace(
            "techniques = [\"voxels\"]",
            "techniques = [\"voxels\", \"video\", \"test\"]",
        )
        .replace("duration_s = 2.5", "duration_s = 7.0")
        + thin;
    let run = common::run_gated(&text).await;
    let encode = report(&run.metrics, "encode");
    println!("encode: {encode}");
    let viewer = report(&run.metrics, "viewer");
    println!("viewer: {viewer}");
    let decoder = &viewer["decoder"];
    // It showed frames before the outage, through it (the last one stayed: the light's age
    // climbed past the three seconds without data), and after it.
    assert_eq!(viewer["indirect_shown"], true, "{viewer}");
    assert!(f(viewer, "age_ms_max") >= 2500.0, "{viewer}");
    // The gap is reported: one break of thirty units.
    assert_eq!(f(viewer, "gaps"), 1.0, "{viewer}");
    assert_eq!(f(viewer, "units_missed"), 30.0, "{viewer}");
    // After it the decoder waited for the next key frame (at most a second of units) and
    // then showed every picture, none broken.
    let waiting = decoder["waiting_for_key"].as_f64().unwrap();
    assert!(waiting < 10.0, "{viewer}");
    assert_eq!(decoder["errors"], 0, "{viewer}");
    let (units, pictures) = (
        decoder["units"].as_f64().unwrap(),
        decoder["pictures"].as_f64().unwrap(),
    );
    assert!(
        units >= 8.0 + 10.0,
        "units before and after the outage arrived: {viewer}"
    );
    assert_eq!(pictures, units - waiting, "{viewer}");
    assert!(pictures > 8.0, "pictures after the outage: {viewer}");
}
