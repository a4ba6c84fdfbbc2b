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
