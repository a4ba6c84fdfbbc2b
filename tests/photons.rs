//! The photon technique end to end in one process: a batcher on a cloud node streams packed
//! batches over emulated links (real UDP sockets on loopback) to reconstructors on client
//! nodes.

mod common;

use std::time::Duration;

use cloudlight::actors::photon_batcher;
use cloudlight::actors::wire::PhotonMsg;
use cloudlight::render::photon::{Manifest, PackFormat, PackedBatch, pack::BatchHeader};
use cloudlight::runtime::{NextTick, RunOptions, Stage, StageCtx, StageKind, StageRegistry};
use common::{f, plan_text, report, run_plan};

/// A topology of a `cloud` and a `home` node on loopback (free ports) followed by `body`.
fn cloud_and_home(scene: &str, duration_s: f64, body: &str) -> String {
    format!(
        r#"techniques = ["photons"]
scene = "{scene}"
seed = 4
duration_s = {duration_s}
cluster = "photon-tests"
secret = "s"
[[node]]
name = "cloud"
address = "127.0.0.1:0"
[[node]]
name = "home"
address = "127.0.0.1:0"
{body}"#
    )
}

/// Runs a topology text with the project's stages, its output in a new folder (kept while
/// the returned guard lives).
async fn run_with_output(text: &str) -> (cloudlight::runtime::RunReport, tempfile::TempDir) {
    let registry = cloudlight::actors::registry();
    let plan = plan_text(text, &registry);
    let out = tempfile::tempdir().unwrap();
    let run = run_plan(
        &plan,
        &registry,
        RunOptions {
            out_dir: Some(out.path().to_path_buf()),
            ..RunOptions::default()
        },
    )
    .await
    .unwrap_or_else(|e| panic!("{e}"));
    (run, out)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clients_behind_a_slow_lossy_link_show_current_indirect_light() {
    // 50 ms each way and 2% loss between the cloud and each client. The Cornell box's light
    // moves all the time, so every iteration re-traces its batch: clients must show indirect
    // light soon after start, replace stale batches as new ones arrive, and the age of what
    // they show must stay bounded (about one iteration + the link's latency + queueing).
    let text = cloud_and_home(
        "cornell-animated",
        4.0,
        r#"
[[stage]]
name = "batcher"
kind = "photon_batcher"
node = "cloud"
params = { photons = 5000, batch_size = 2500, interval_ms = 100.0 }
[[stage]]
name = "viewer"
kind = "photon_reconstructor"
node = "home"
params = { width = 48, height = 36, fps = 4.0, light_samples = 1, shadow_size = 128 }
[[stage]]
name = "counter"
kind = "photon_reconstructor"
node = "home"
params = { render = false, fps = 20.0 }
[[edge]]
from = "batcher.out"
to = "viewer.in"
[[edge]]
from = "batcher.out"
to = "counter.in"
[[link]]
between = ["cloud", "home"]
latency_ms = 50.0
jitter_ms = 5.0
loss = 0.02
"#,
    );
    let (run, _out) = run_with_output(&text).await;
    let m = &run.metrics;
    let batcher = report(m, "batcher");
    assert!(f(batcher, "iterations") >= 10.0, "{batcher}");
    assert_eq!(f(batcher, "batches"), 2.0, "{batcher}");
    for client in ["viewer", "counter"] {
        let r = report(m, client);
        eprintln!("{client}: {r}");
        assert_eq!(r["indirect_shown"], true, "{client}: {r}");
        assert!(f(r, "first_indirect_s") < 1.5, "{client}: {r}");
        assert!(f(r, "batches_replaced") >= 10.0, "{client}: {r}");
        assert_eq!(f(r, "batches_rejected"), 0.0);
        assert!(f(r, "photons_stored") > 1000.0, "{client}: {r}");
        assert!(f(r, "age_ms_max") < 1000.0, "{client}: {r}");
        assert!(f(r, "age_ms_p50") < 500.0, "{client}: {r}");
    }
    assert!(f(report(m, "viewer"), "frames") >= 3.0);
    // Each cut edge crossed the lossy link and recovered its losses.
    let cut: Vec<_> = m.edges.iter().filter_map(|e| e.wire.as_ref()).collect();
    assert!(!cut.is_empty());
    assert!(
        cut.iter().map(|w| w.retransmissions).sum::<u64>() > 0,
        "{cut:?}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn zero_and_fifty_clients_run_cleanly() {
    for clients in [0usize, 50] {
        let mut text = cloud_and_home(
            "cornell-animated",
            2.0,
            r#"
[[stage]]
name = "batcher"
kind = "photon_batcher"
node = "cloud"
params = { photons = 2000, batch_size = 1000, interval_ms = 100.0 }
"#,
        );
        if clients > 0 {
            text += &format!(
                r#"
[[stage]]
name = "client"
kind = "photon_reconstructor"
node = "home"
replicas = {clients}
params = {{ render = false, fps = 10.0 }}
[[edge]]
from = "batcher.out"
to = "client.in"
"#
            );
        }
        let registry = cloudlight::actors::registry();
        let plan = plan_text(&text, &registry);
        let run = run_plan(&plan, &registry, RunOptions::default())
            .await
            .unwrap_or_else(|e| panic!("{clients} clients: {e}"));
        let batcher = report(&run.metrics, "batcher");
        assert!(f(batcher, "iterations") >= 5.0, "{batcher}");
        for i in 0..clients {
            let r = report(&run.metrics, &format!("client[{i}]"));
            assert_eq!(r["indirect_shown"], true, "client[{i}]: {r}");
            assert!(f(r, "age_ms_max").is_finite());
        }
    }
}

/// Sends batches whose bytes are garbage, then a manifest.
struct GarbageBatcher {
    sent: u32,
}

#[async_trait::async_trait]
impl Stage for GarbageBatcher {
    async fn on_tick(&mut self, ctx: &mut StageCtx) -> anyhow::Result<NextTick> {
        if self.sent == 20 {
            let m = Manifest {
                iteration: 1,
                scene_time_s: 0.0,
                lights: Vec::new(),
            };
            ctx.send(photon_batcher::OUT, 0.0, PhotonMsg::Manifest(m))
                .await?;
            return Ok(NextTick::Never);
        }
        let photons = vec![
            cloudlight::render::photon::Photon {
                position: cloudlight::scenes::glam::Vec3::ONE,
                direction: cloudlight::scenes::glam::Vec3::NEG_Y,
                power: cloudlight::scenes::glam::Vec3::ONE,
                radius: 0.1,
                receive: Default::default(),
            };
            8
        ];
        let header = BatchHeader {
            light: 0,
            slot: 0,
            slots: 1,
            generation: self.sent as u64,
            pass: 0,
            scene_time_s: 0.0,
            emitted: 8,
            receive: Default::default(),
        };
        let mut b = PackedBatch::pack(header, &photons, PackFormat::Compact12);
        for (i, x) in b.data.iter_mut().enumerate() {
            *x = ((i as u32).wrapping_mul(2_654_435_761) ^ self.sent) as u8;
        }
        self.sent += 1;
        ctx.send(photon_batcher::OUT, 0.0, PhotonMsg::Batch(b))
            .await?;
        Ok(NextTick::After(Duration::from_millis(5)))
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn garbage_batches_are_rejected_and_counted() {
    let mut registry: StageRegistry = cloudlight::actors::registry();
    registry.register(
        StageKind::new("garbage", "photons", "sends corrupt photon batches", |_| {
            Ok(Box::new(GarbageBatcher { sent: 0 }))
        })
        .output(photon_batcher::OUT),
    );
    let text = cloud_and_home(
        "cornell",
        1.0,
        r#"
[[stage]]
name = "garbage"
kind = "garbage"
node = "cloud"
[[stage]]
name = "client"
kind = "photon_reconstructor"
node = "home"
params = { render = false }
[[edge]]
from = "garbage.out"
to = "client.in"
"#,
    );
    let plan = plan_text(&text, &registry);
    let run = run_plan(&plan, &registry, RunOptions::default())
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    let r = report(&run.metrics, "client");
    assert_eq!(f(r, "batches_rejected"), 20.0, "{r}");
    assert_eq!(f(r, "photons_stored"), 0.0, "{r}");
    assert_eq!(f(r, "manifests"), 1.0, "{r}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn only_lights_that_change_are_retraced() {
    // The city's sun moves over the day; its street lamps do not. Each light's budget is its
    // share of the watts: against the sun's ~10⁸ W the lamps' 245 W round to no photon at
    // this budget, so they get no batch; the sun's batches are traced again each iteration
    // (the stream test `a_stream_traces_again_only_the_lights_that_changed` checks that a
    // static light with photons is not).
    let text = r#"
techniques = ["photons"]
scene = "city:2000"
duration_s = 1.5
[[node]]
name = "cloud"
address = "127.0.0.1:0"
[[stage]]
name = "batcher"
kind = "photon_batcher"
node = "cloud"
params = { photons = 4000, batch_size = 500, interval_ms = 100.0 }
"#;
    let registry = cloudlight::actors::registry();
    let plan = plan_text(text, &registry);
    let run = run_plan(&plan, &registry, RunOptions::default())
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    let b = report(&run.metrics, "batcher");
    let generations = b["generations"].as_object().unwrap();
    let iterations = f(b, "iterations") as u64;
    assert!(iterations >= 5, "{b}");
    let sun = generations["sun"].as_u64().unwrap();
    assert!(sun >= iterations - 1, "the sun moves: {b}");
    for (light, generation) in generations {
        if light != "sun" {
            assert_eq!(generation.as_u64(), Some(1), "{light} is static: {b}");
        }
    }
    // The budget went to the sun: 4000 photons an iteration, not 4000 plus a batch per lamp.
    let emitted = f(b, "photons_emitted") / sun as f64;
    assert!(
        (emitted / 4000.0 - 1.0).abs() < 0.01,
        "{emitted} photons an iteration: {b}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clients_send_their_views_upstream_and_the_batcher_guides_by_them() {
    // A client at home sends its camera each frame over the cut edge `client.view ->
    // batcher.views` (a cycle with `batcher.out -> client.in`, both `latest`); the
    // batcher guides the city's sun by it. A batcher without the edge is not warned about:
    // the input is optional.
    let edges = |views: bool| {
        format!(
            r#"
[[stage]]
name = "batcher"
kind = "photon_batcher"
node = "cloud"
params = {{ photons = 4000, batch_size = 2000, interval_ms = 100.0 }}
[[stage]]
name = "client"
kind = "photon_reconstructor"
node = "home"
params = {{ render = false, fps = 20.0 }}
[[edge]]
from = "batcher.out"
to = "client.in"
{}"#,
            if views {
                "[[edge]]\nfrom = \"client.view\"\nto = \"batcher.views\"\n"
            } else {
                ""
            }
        )
    };
    let registry = cloudlight::actors::registry();
    let unguided = plan_text(&cloud_and_home("city:2000", 1.5, &edges(false)), &registry);
    assert!(
        unguided
            .warnings
            .iter()
            .all(|w| !w.message.contains("views")),
        "{:?}",
        unguided.warnings
    );
    let plan = plan_text(&cloud_and_home("city:2000", 2.0, &edges(true)), &registry);
    let run = run_plan(&plan, &registry, RunOptions::default())
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    let b = report(&run.metrics, "batcher");
    assert!(f(b, "views_received") >= 10.0, "{b}");
    assert_eq!(f(b, "views_rejected"), 0.0, "{b}");
    assert_eq!(f(b, "views_in_use"), 1.0, "{b}");
    let c = report(&run.metrics, "client");
    assert_eq!(c["indirect_shown"], true, "{c}");
    let views = run
        .metrics
        .edges
        .iter()
        .find(|e| e.name.starts_with("client.view -> batcher.views") && e.wire.is_some())
        .expect("the views edge is cut");
    assert!(views.messages >= 10, "{views:?}");
}

/// Sends views whose numbers are out of range, then one good view.
struct BadViews {
    sent: usize,
}

impl BadViews {
    fn views() -> Vec<cloudlight::scenes::View> {
        use cloudlight::scenes::glam::Vec3;
        let good = cloudlight::scenes::View {
            camera: cloudlight::scenes::Camera {
                position: Vec3::new(0.0, 2.0, 0.0),
                target: Vec3::new(10.0, 2.0, 1.0),
                up: Vec3::Y,
                fov_y_rad: 1.0,
            },
            aspect: 1.5,
        };
        let mut v = Vec::new();
        for k in 0..6 {
            let mut bad = good;
            match k {
                0 => bad.camera.position.x = f32::NAN,
                1 => bad.camera.target = bad.camera.position,
                2 => bad.camera.fov_y_rad = 0.0,
                3 => bad.camera.fov_y_rad = f32::INFINITY,
                4 => bad.aspect = -1.0,
                _ => bad.camera.up.y = f32::NEG_INFINITY,
            }
            v.push(bad);
        }
        v.push(good);
        v
    }
}

#[async_trait::async_trait]
impl Stage for BadViews {
    async fn on_tick(&mut self, ctx: &mut StageCtx) -> anyhow::Result<NextTick> {
        let views = Self::views();
        let Some(v) = views.get(self.sent) else {
            return Ok(NextTick::Never);
        };
        self.sent += 1;
        ctx.send(cloudlight::actors::client::VIEW, 0.0, *v).await?;
        Ok(NextTick::After(Duration::from_millis(5)))
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn views_out_of_range_are_dropped_and_counted() {
    let mut registry: StageRegistry = cloudlight::actors::registry();
    registry.register(
        StageKind::new("bad_views", "photons", "sends views out of range", |_| {
            Ok(Box::new(BadViews { sent: 0 }))
        })
        .output(cloudlight::actors::client::VIEW),
    );
    let text = cloud_and_home(
        "city:2000",
        1.0,
        r#"
[[stage]]
name = "batcher"
kind = "photon_batcher"
node = "cloud"
params = { photons = 2000, batch_size = 2000, interval_ms = 100.0 }
[[stage]]
name = "views"
kind = "bad_views"
node = "home"
[[edge]]
from = "views.view"
to = "batcher.views"
capacity = 16
"#,
    );
    let plan = plan_text(&text, &registry);
    let run = run_plan(&plan, &registry, RunOptions::default())
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    let b = report(&run.metrics, "batcher");
    assert_eq!(f(b, "views_received"), 7.0, "{b}");
    assert_eq!(f(b, "views_rejected"), 6.0, "{b}");
    assert_eq!(f(b, "views_in_use"), 1.0, "{b}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_still_view_of_still_light_shows_the_mean_of_its_jittered_frames() {
    // The static Cornell box from its still camera: once the light has arrived, nothing a
    // client shows changes, and a client that accumulates (the default) blends each frame,
    // sampled at another point in its pixels, into the mean of those since (batches sent
    // again unchanged do not reset it): its last frame
    // matches the plain client's inside surfaces and differs along the edges, where a pixel
    // straddles two surfaces. A client that does not accumulate blends nothing.
    let text = cloud_and_home(
        "cornell",
        3.0,
        r#"
[[stage]]
name = "batcher"
kind = "photon_batcher"
node = "cloud"
params = { photons = 3000, batch_size = 3000, interval_ms = 100.0, resend_s = 0.5 }
[[stage]]
name = "still"
kind = "photon_reconstructor"
node = "home"
params = { width = 48, height = 36, fps = 8.0, shadow_size = 128, write_frames = true, exposure_stops = 0.0 }
[[stage]]
name = "plain"
kind = "photon_reconstructor"
node = "home"
params = { width = 48, height = 36, fps = 8.0, shadow_size = 128, write_frames = true, exposure_stops = 0.0, accumulate = false }
[[edge]]
from = "batcher.out"
to = "still.in"
[[edge]]
from = "batcher.out"
to = "plain.in"
"#,
    );
    let (run, out) = run_with_output(&text).await;
    let (still, plain) = (report(&run.metrics, "still"), report(&run.metrics, "plain"));
    eprintln!("still: {still}\nplain: {plain}");
    // Every frame after the light arrived but the one that started the mean: the batches
    // sent again every 0.5 s change nothing.
    assert!(f(still, "batches_replaced") >= 3.0, "{still}");
    assert!(
        f(still, "still_frames") >= f(still, "frames") - 5.0,
        "{still}"
    );
    assert_eq!(f(plain, "still_frames"), 0.0, "{plain}");
    // The last frame each wrote.
    let last = |client: &str| {
        let dir = out.path().join(client);
        let mut frames: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|e| e == "png"))
            .collect();
        frames.sort();
        image::open(frames.last().unwrap()).unwrap().to_rgb8()
    };
    let (a, b) = (last("still"), last("plain"));
    let differ: Vec<u8> = a
        .pixels()
        .zip(b.pixels())
        .map(|(p, q)| (0..3).map(|c| p[c].abs_diff(q[c])).max().unwrap())
        .collect();
    let changed = differ.iter().filter(|&&d| d > 8).count();
    let n = differ.len();
    eprintln!("{changed} of {n} pixels differ by more than 8/255");
    assert!(changed > 0, "the accumulated frame is the plain one");
    assert!(
        changed * 4 < n,
        "{changed} of {n} pixels differ: not only edges"
    );
}
