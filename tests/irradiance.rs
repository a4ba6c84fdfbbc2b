//! The irradiance-map server in running clusters: a `basis_gatherer` on a cloud node streams
//! its maps through one `video_encoder` over an emulated link to clients; scenes that cannot
//! be parametrised are refused at validation with the reason (the paper's "n/a").

mod common;

use cloudlight::runtime::{Plan, RunOptions};
use common::{f, plan_text, report, run_plan};

fn topology(scene: &str, gatherer: &str, clients: u32) -> String {
    format!(
        r#"techniques = ["irradiance", "video"]
scene = "{scene}"
seed = 3
duration_s = 2.5
cluster = "irradiance-tests"
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
name = "gather"
kind = "basis_gatherer"
node = "cloud"
params = {{ {gatherer} }}
[[stage]]
name = "encode"
kind = "video_encoder"
node = "cloud"
params = {{ qp = 16, keyframe_s = 1.0, fps = 10.0 }}
[[stage]]
name = "viewer"
kind = "video_client"
node = "home"
replicas = {clients}
params = {{ width = 128, height = 128, fps = 10.0 }}
[[edge]]
from = "gather.out"
to = "encode.in"
capacity = 2
policy = "latest"
[[edge]]
from = "encode.out"
to = "viewer.in"
policy = "block"
capacity = 16
"#
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_gatherer_streams_h264_light_maps_to_every_client() {
    let text = topology("cornell-animated", "interval_ms = 100.0", 2);
    let registry = cloudlight::actors::registry();
    let plan = plan_text(&text, &registry);
    let run = run_plan(&plan, &registry, RunOptions::default())
        .await
        .unwrap();
    let g = report(&run.metrics, "gather");
    println!("gatherer: {g}");
    assert!(f(g, "updates") >= 5.0, "{g}");
    assert!(f(g, "maps_sent") >= 5.0, "{g}");
    assert!((30.0..=80.0).contains(&f(g, "bases")), "{g}");
    assert_eq!(f(g, "resolution"), 128.0);
    assert_eq!(f(g, "converged_updates"), 0.0, "the light moves: {g}");
    assert!(f(g, "rays_per_update") > 10_000.0, "{g}");
    for i in 0..2 {
        let v = report(&run.metrics, &format!("viewer[{i}]"));
        println!("viewer[{i}]: {v}");
        // The decode-only client cannot show light maps: it counts them (the irradiance
        // client reconstructs them).
        assert!(f(v, "hdr_units_ignored") >= 4.0, "viewer[{i}]: {v}");
    }
}

/// The error `check_scene` gives `text` against its scene.
fn scene_error(text: &str, scene: &str) -> String {
    let registry = cloudlight::actors::registry();
    let plan = Plan::from_str("t.toml", text, &registry).unwrap_or_else(|e| panic!("{e}"));
    let scene = cloudlight::scenes::load(scene).unwrap();
    plan.check_scene(&registry, &scene)
        .expect_err("the scene check refuses it")
        .to_string()
}

#[test]
fn scenes_that_cannot_be_parametrised_are_refused_with_the_reason() {
    let err = scene_error(&topology("cornell", "unwrap_limit_s = 0.0", 1), "cornell");
    assert!(
        err.contains("n/a") && err.contains("TEXCOORD_1") && err.contains("stage[0]"),
        "{err}"
    );
    let err = scene_error(
        &topology("city:2000", "max_resolution = 32", 1),
        "city:2000",
    );
    assert!(err.contains("n/a") && err.contains("charts"), "{err}");
    let registry = cloudlight::actors::registry();
    let text = topology("cornell", "rays_per_basis = 0", 1);
    let err = Plan::from_str("t.toml", &text, &registry)
        .unwrap_err()
        .to_string();
    assert!(err.contains("rays_per_basis"), "{err}");
}
