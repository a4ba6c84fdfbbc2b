//! The irradiance-map technique in running clusters: a `basis_gatherer` on a cloud node
//! streams its maps through one `video_encoder` (or raw) over an emulated lossy link to
//! irradiance clients, which decode, blend and show them; 0 and 50 clients; an outage and a
//! late join; scenes that cannot be parametrised are refused at validation with the reason
//! (the paper's "n/a").

mod common;

use cloudlight::runtime::{Plan, RunOptions};
use common::{f, plan_text, report, run_plan};

/// A gatherer and an encoder on `cloud` over a 10 ms, 1%-loss link to `home`, followed by
/// `rest` (the clients, edges to them).
fn cluster(scene: &str, gatherer: &str, duration_s: f64, rest: &str) -> String {
    let test = if rest.contains("unit_gate") {
        ", \"test\""
    } else {
        ""
    };
    format!(
        r#"techniques = ["irradiance", "video"{test}]
scene = "{scene}"
seed = 3
duration_s = {duration_s}
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
[[edge]]
from = "gather.out"
to = "encode.in"
capacity = 2
policy = "latest"
{rest}"#
    )
}

/// `clients` H.264 irradiance clients on `home` (measuring, not rendering).
fn viewers(clients: u32) -> String {
    format!(
        r#"[[stage]]
name = "viewer"
kind = "irradiance_reconstructor"
node = "home"
replicas = {clients}
params = {{ width = 128, height = 128, fps = 10.0, render = false }}
[[edge]]
from = "encode.out"
to = "viewer.in"
policy = "block"
capacity = 16
"#
    )
}

/// A raw-map client `raw` on `home` (64×48, with `params`) fed by the gatherer.
fn raw_client(params: &str) -> String {
    format!(
        r#"[[stage]]
name = "raw"
kind = "irradiance_raw_reconstructor"
node = "home"
params = {{ width = 64, height = 48, {params} }}
[[edge]]
from = "gather.out"
to = "raw.in"
"#
    )
}

fn topology(scene: &str, gatherer: &str, clients: u32) -> String {
    cluster(scene, gatherer, 2.5, &viewers(clients))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_gatherer_streams_maps_to_every_client_through_h264_and_raw_over_a_lossy_link() {
    // Two H.264 clients and one raw client (the f16 map across the cut), rendering frames.
    let raw = raw_client("fps = 5.0");
    let text = cluster(
        "cornell-animated",
        "interval_ms = 100.0",
        2.5,
        &(viewers(2) + &raw),
    );
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
    for name in ["viewer[0]", "viewer[1]", "raw"] {
        let v = report(&run.metrics, name);
        println!("{name}: {v}");
        // Every map that arrives over the 1%-loss link decodes and is blended in.
        assert!(f(v, "maps_blended") >= 4.0, "{name}: {v}");
        assert_eq!(f(v, "maps_blended"), f(v, "maps_decoded"), "{name}: {v}");
        assert_eq!(f(v, "decode_errors"), 0.0, "{name}: {v}");
        assert_eq!(f(v, "maps_mismatched"), 0.0, "{name}: {v}");
        assert_eq!((f(v, "map_width"), f(v, "map_height")), (128.0, 128.0));
        assert_eq!(v["indirect_shown"], true, "{name}: {v}");
        // The light shown is recent: 0.1 s updates blended at 0.5 lag about 0.1 s more.
        let age = f(v, "age_ms_p50");
        assert!((20.0..800.0).contains(&age), "{name}: age {age} ms");
    }
    let raw = report(&run.metrics, "raw");
    assert!(f(raw, "frames") >= 3.0, "the raw client renders: {raw}");
    assert!(
        f(raw, "bytes_received") > 20.0 * f(report(&run.metrics, "viewer[0]"), "bytes_received")
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_converged_static_map_is_current_light_between_its_re_sends() {
    // The static box converges within about a second of 50 ms updates; from then on the
    // gatherer re-sends its map once a second, marked steady: the light a client holds is
    // current (age 0), not as old as the last re-send.
    let raw = raw_client("fps = 10.0, render = false");
    let text = cluster("cornell", "interval_ms = 50.0, resend_s = 1.0", 4.0, &raw);
    let registry = cloudlight::actors::registry();
    let run = run_plan(
        &plan_text(&text, &registry),
        &registry,
        RunOptions::default(),
    )
    .await
    .unwrap();
    let g = report(&run.metrics, "gather");
    let v = report(&run.metrics, "raw");
    println!("gather: {g}\nraw: {v}");
    assert!(f(g, "converged_updates") > 0.0, "{g}");
    assert_eq!(v["indirect_shown"], true, "{v}");
    // Most frames show the steady map: the median age is 0 and none climbs towards the 1 s
    // between re-sends.
    assert!(f(v, "age_ms_p50") < 1.0, "{v}");
    assert!(f(v, "age_ms_max") < 700.0, "{v}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn zero_and_fifty_irradiance_clients_run_cleanly() {
    let registry = cloudlight::actors::registry();
    // None: the gatherer and encoder run alone.
    let alone = cluster("cornell-animated", "interval_ms = 100.0", 1.5, "");
    let run = run_plan(
        &plan_text(&alone, &registry),
        &registry,
        RunOptions::default(),
    )
    .await
    .unwrap();
    let g = report(&run.metrics, "gather");
    assert!(f(g, "maps_sent") >= 2.0, "{g}");
    // Fifty: every one decodes and blends every map it gets.
    let text = topology("cornell-animated", "interval_ms = 100.0", 50);
    let run = run_plan(
        &plan_text(&text, &registry),
        &registry,
        RunOptions::default(),
    )
    .await
    .unwrap();
    let g = report(&run.metrics, "gather");
    for i in 0..50 {
        let v = report(&run.metrics, &format!("viewer[{i}]"));
        assert!(f(v, "maps_blended") >= 3.0, "viewer[{i}]: {v}");
        assert_eq!(f(v, "decode_errors"), 0.0, "viewer[{i}]: {v}");
        assert_eq!(
            f(v, "maps_blended"),
            f(v, "maps_decoded"),
            "viewer[{i}]: {v}"
        );
    }
    assert!(f(g, "maps_sent") >= 3.0, "{g}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_keeps_its_map_through_an_outage_and_a_late_one_shows_light_within_a_key_frame() {
    // Maps at 10 per second, key frames every second (10 units). `out` loses units 10 to 59
    // (5 s without data); `late` joins at unit 15, between two key frames.
    let gated = |name: &str, from: u64, until: u64| {
        format!(
            r#"[[stage]]
name = "gate-{name}"
kind = "unit_gate"
node = "cloud"
params = {{ drop_from = {from}, drop_until = {until} }}
[[stage]]
name = "{name}"
kind = "irradiance_reconstructor"
node = "home"
params = {{ width = 64, height = 48, fps = 10.0, render = false, blend = 1.0 }}
[[edge]]
from = "encode.out"
to = "gate-{name}.in"
[[edge]]
from = "gate-{name}.out"
to = "{name}.in"
policy = "block"
capacity = 16
"#
        )
    };
    let text = cluster(
        "cornell-animated",
        "interval_ms = 100.0",
        10.0,
        &(gated("out", 10, 60) + &gated("late", 0, 15)),
    );
    let run = common::run_gated(&text).await;
    let out = report(&run.metrics, "out");
    println!("out: {out}");
    // It showed light before, through and after the outage: its age climbed past the 5 s
    // without data (the last map stayed), and maps blended in again after it.
    assert_eq!(out["indirect_shown"], true, "{out}");
    assert!(f(out, "age_ms_max") >= 4500.0, "{out}");
    assert!(
        f(out, "maps_blended") >= 11.0,
        "maps before and after the outage: {out}"
    );
    // After the gap it waits for the next key frame (at most 10 units on) rather than decode
    // a broken stream (the unit test of `H264Maps` shows the wait itself).
    assert!(f(out, "waiting_for_key") < 10.0, "{out}");
    assert_eq!(f(out, "decode_errors"), 0.0, "{out}");
    assert_eq!(f(out, "maps_blended"), f(out, "maps_decoded"), "{out}");
    let late = report(&run.metrics, "late");
    println!("late: {late}");
    // Joining at unit 15, it showed light from the next key frame: key frames come at least
    // every 10 units (1 s of stream time, at most 10 updates), so it dropped fewer than 10.
    assert_eq!(late["indirect_shown"], true, "{late}");
    assert!(f(late, "waiting_for_key") < 10.0, "{late}");
    assert!(f(late, "maps_blended") >= 1.0, "{late}");
    assert_eq!(f(late, "maps_blended"), f(late, "maps_decoded"), "{late}");
    assert_eq!(f(late, "decode_errors"), 0.0, "{late}");
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
    // A client of a scene without a light map is refused at validation too.
    let client = topology("cornell", "", 1)
        .replace("render = false }", "render = false, unwrap_limit_s = 0.0 }");
    let err = scene_error(&client, "cornell");
    assert!(err.contains("n/a") && err.contains("TEXCOORD_1"), "{err}");
    let registry = cloudlight::actors::registry();
    let text = topology("cornell", "rays_per_basis = 0", 1);
    let err = Plan::from_str("t.toml", &text, &registry)
        .unwrap_err()
        .to_string();
    assert!(err.contains("rays_per_basis"), "{err}");
    // Map sides the H.264 encoder cannot take are refused before anything runs.
    for (params, key) in [
        ("resolution = 129", "resolution"),
        ("resolution = 4096", "resolution"),
        ("max_resolution = 2159", "max_resolution"),
        ("max_resolution = 2162", "max_resolution"),
    ] {
        let err = Plan::from_str("t.toml", &topology("cornell", params, 1), &registry)
            .unwrap_err()
            .to_string();
        assert!(err.contains(key), "{params}: {err}");
        assert!(
            params.ends_with("2162") || err.contains("even"),
            "{params}: {err}"
        );
    }
}
