//! Bad input as a careless operator or an attacker writes it: topology files with random and
//! extreme values, numeric flags of every command, and mutated glTF files. Nothing may
//! panic, hang or grow without bound; each gets a clear error or a valid result.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use cloudlight::runtime::{Plan, StageRegistry};
use proptest::prelude::*;

// ---------------------------------------------------------------------------------------
// Topologies

/// A photon topology with every numeric key the parser knows, each a `@key@` placeholder.
const TEMPLATE: &str = r#"techniques = ["photons", "probe"]
scene = "cornell"
secret = "s"
seed = @seed@
duration_s = @duration_s@
scene_start_s = @scene_start_s@
time_scale = @time_scale@
[transport]
max_packet_bytes = @max_packet_bytes@
window_packets = @window_packets@
pacing_mbps = @pacing_mbps@
peer_timeout_ms = @peer_timeout_ms@
heartbeat_ms = @heartbeat_ms@
connect_timeout_s = @connect_timeout_s@
stall_timeout_s = @stall_timeout_s@
rejoin_timeout_s = @rejoin_timeout_s@
[defaults]
capacity = @default_capacity@
[[node]]
name = @node_name@
address = @address@
[[node]]
name = "client"
address = "127.0.0.1:0"
[[stage]]
name = "batcher"
kind = "photon_batcher"
node = @node_ref@
params = { photons = @photons@, batch_size = @batch_size@, bounces = @bounces@, photons_per_disk = @photons_per_disk@, radius_m = @radius_m@, interval_ms = @interval_ms@, resend_s = @resend_s@, passes = @passes@, format = @format@, receive = @receive@, guide_share = @guide_share@, guide_reach = @guide_reach@, relax = @relax@, merge = @merge@ }
[[stage]]
name = "viewer"
kind = "photon_reconstructor"
node = "client"
replicas = @replicas@
params = { width = @width@, height = @height@, fps = @fps@, camera = @camera@, write_every = @write_every@, light_samples = @light_samples@, shadow_size = @shadow_size@, downsample = @downsample@, levels = @levels@, min_texels = @min_texels@, compute = @compute@, splat_merge = @splat_merge@ }
[[stage]]
name = "probe"
kind = "probe_source"
node = "client"
params = { rate_hz = @rate_hz@, payload_bytes = @payload_bytes@ }
[[stage]]
name = "sink"
kind = "probe_sink"
node = "client"
params = { work_ms = @work_ms@ }
[[edge]]
from = "batcher"
to = "viewer"
capacity = @edge_capacity@
[[edge]]
from = "probe"
to = "sink"
[[link]]
between = [@node_ref@, "client"]
latency_ms = @latency_ms@
jitter_ms = @jitter_ms@
bandwidth_mbps = @bandwidth_mbps@
loss = @loss@
duplicate = @duplicate@
reorder = @reorder@
"#;

/// Each placeholder and a valid value for it.
const KEYS: &[(&str, &str)] = &[
    ("seed", "1"),
    ("duration_s", "2.0"),
    ("scene_start_s", "0.0"),
    ("time_scale", "1.0"),
    ("max_packet_bytes", "1200"),
    ("window_packets", "1024"),
    ("pacing_mbps", "1000.0"),
    ("peer_timeout_ms", "3000.0"),
    ("heartbeat_ms", "250.0"),
    ("connect_timeout_s", "10.0"),
    ("stall_timeout_s", "30.0"),
    ("rejoin_timeout_s", "30.0"),
    ("default_capacity", "8"),
    ("node_name", "\"cloud\""),
    ("address", "\"127.0.0.1:0\""),
    ("node_ref", "\"cloud\""),
    ("photons", "1000"),
    ("batch_size", "1000"),
    ("bounces", "3"),
    ("photons_per_disk", "20.0"),
    ("radius_m", "0.1"),
    ("interval_ms", "33.0"),
    ("resend_s", "1.0"),
    ("passes", "4"),
    ("format", "\"compact8\""),
    ("receive", "\"normal\""),
    ("guide_share", "0.5"),
    ("guide_reach", "0.05"),
    ("relax", "2"),
    ("merge", "0.5"),
    ("replicas", "2"),
    ("width", "64"),
    ("height", "48"),
    ("fps", "10.0"),
    ("camera", "0"),
    ("write_every", "1"),
    ("light_samples", "2"),
    ("shadow_size", "256"),
    ("downsample", "2"),
    ("levels", "4"),
    ("min_texels", "2.0"),
    ("compute", "true"),
    ("splat_merge", "0.5"),
    ("rate_hz", "10.0"),
    ("payload_bytes", "100"),
    ("work_ms", "1.0"),
    ("edge_capacity", "4"),
    ("latency_ms", "5.0"),
    ("jitter_ms", "1.0"),
    ("bandwidth_mbps", "100.0"),
    ("loss", "0.01"),
    ("duplicate", "0.0"),
    ("reorder", "0.0"),
];

/// Values as TOML text: the extremes every parser meets, and random numbers.
fn value() -> impl Strategy<Value = String> {
    let extremes = [
        "nan",
        "+inf",
        "-inf",
        "0",
        "0.0",
        "-0.0",
        "1e-300",
        "-1e-300",
        "1e300",
        "-1e300",
        "-1",
        "9223372036854775807",
        "-9223372036854775808",
        "18446744073709551616",
        "4294967296",
        "true",
        "[]",
        "{}",
        "\"\"",
        "\"127.0.0.1:7\"",
    ];
    prop_oneof![
        proptest::sample::select(extremes.to_vec()).prop_map(String::from),
        any::<i64>().prop_map(|v| v.to_string()),
        any::<f64>().prop_map(|v| format!("{v:e}")),
        (0u32..20_000).prop_map(|v| v.to_string()),
        (0usize..3).prop_map(|n| format!("\"{}\"", "x".repeat([300, 70_000, 1][n]))),
    ]
}

fn topology(mutations: &[(usize, String)]) -> String {
    let mut text = TEMPLATE.to_string();
    for (k, (key, good)) in KEYS.iter().enumerate() {
        let v = mutations
            .iter()
            .rev()
            .find(|(i, _)| i % KEYS.len() == k)
            .map_or(*good, |(_, v)| v.as_str());
        text = text.replace(&format!("@{key}@"), v);
    }
    text
}

/// What a valid plan promises the run: durations convertible, sizes within their bounds.
fn check_promises(plan: &Plan) {
    let t = &plan.topology;
    let seconds = [
        t.duration_s.unwrap_or(1.0),
        t.transport.peer_timeout_ms / 1000.0,
        t.transport.heartbeat_ms / 1000.0,
        t.transport.connect_timeout_s,
        t.transport.stall_timeout_s,
        t.transport.rejoin_timeout_s,
    ];
    for s in seconds {
        let d = Duration::try_from_secs_f64(s).expect("a valid plan's durations convert");
        assert!(
            Instant::now().checked_add(d).is_some(),
            "{s} s as a deadline"
        );
    }
    for l in &t.links {
        for ms in [l.profile.latency_ms, l.profile.jitter_ms] {
            Duration::try_from_secs_f64(ms / 1000.0).expect("link delays convert");
        }
    }
    for e in &plan.edges {
        assert!((1..=1_000_000).contains(&e.settings.capacity));
    }
    assert!(plan.instances.len() <= 100_000);
}

fn registry() -> StageRegistry {
    cloudlight::actors::registry()
}

#[test]
fn the_template_topology_is_valid() {
    let plan = Plan::from_str("t.toml", &topology(&[]), &registry()).unwrap();
    check_promises(&plan);
    let scene = cloudlight::scenes::load("cornell").unwrap();
    plan.check_scene(&registry(), &scene).unwrap();
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 3000, failure_persistence: None, ..ProptestConfig::default() })]

    /// Random and extreme values at up to four keys: an error naming each, or a valid plan
    /// that keeps every promise; never a panic.
    #[test]
    fn random_and_extreme_values_give_errors_or_valid_plans(
        mutations in proptest::collection::vec((0usize..KEYS.len(), value()), 1..5)
    ) {
        let text = topology(&mutations);
        match Plan::from_str("fuzz.toml", &text, &registry()) {
            Ok(plan) => {
                check_promises(&plan);
                let scene = cloudlight::scenes::load("cornell").unwrap();
                let _ = plan.check_scene(&registry(), &scene);
            }
            Err(e) => {
                prop_assert!(!e.0.is_empty());
                for d in &e.0 {
                    prop_assert!(!d.message.is_empty() && d.line > 0, "{d}");
                }
            }
        }
    }
}

#[test]
fn a_photon_budget_a_scene_cannot_hold_is_refused_against_the_scene() {
    let text = topology(&[]).replace("photons = 1000,", "photons_per_watt = 1e9,");
    let plan = Plan::from_str("t.toml", &text, &registry()).unwrap();
    let scene = cloudlight::scenes::load("cornell").unwrap();
    let e = plan
        .check_scene(&registry(), &scene)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("stage[0].params") && e.contains("photons per iteration"),
        "{e}"
    );
    // A camera the scene does not have.
    let text = topology(&[]).replace("camera = 0,", "camera = 7,");
    let plan = Plan::from_str("t.toml", &text, &registry()).unwrap();
    let e = plan
        .check_scene(&registry(), &scene)
        .unwrap_err()
        .to_string();
    assert!(e.contains("`camera` = 7"), "{e}");
}

// ---------------------------------------------------------------------------------------
// Command-line flags

fn binary() -> PathBuf {
    PathBuf::from(env!("CARGO_BIN_EXE_cloudlight"))
}

/// Most memory any refused input may make the binary hold, bytes (its peak resident set as
/// last seen before it exits).
const MEMORY_LIMIT_BYTES: u64 = 1 << 30;

/// The peak resident set of a running process, bytes (Linux `VmHWM`).
fn peak_rss_bytes(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// Runs the binary with a deadline; its exit code (None: killed at the deadline) and stderr.
/// Fails when its memory grows past [`MEMORY_LIMIT_BYTES`].
fn run_bounded(args: &[String], limit: Duration) -> (Option<i32>, String) {
    let dir = tempfile::tempdir().unwrap();
    let mut child = Command::new(binary())
        .args(args)
        .current_dir(dir.path())
        .env("WGPU_BACKEND", "gl")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let start = Instant::now();
    loop {
        let rss = peak_rss_bytes(child.id()).unwrap_or(0);
        if rss > MEMORY_LIMIT_BYTES {
            let _ = child.kill();
            let _ = child.wait();
            panic!("{args:?} grew to {} MiB", rss >> 20);
        }
        if let Some(status) = child.try_wait().unwrap() {
            let mut err = String::new();
            use std::io::Read;
            child
                .stderr
                .take()
                .unwrap()
                .read_to_string(&mut err)
                .unwrap();
            return (status.code(), err);
        }
        if start.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            return (None, String::new());
        }
        std::thread::sleep(Duration::from_millis(10));
    }
}

fn example(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("examples/topologies")
        .join(name)
        .display()
        .to_string()
}

/// Every numeric flag of every command, with the other arguments the command needs.
fn numeric_flags() -> Vec<(Vec<String>, &'static str)> {
    let s = |v: &[&str]| v.iter().map(|x| x.to_string()).collect::<Vec<_>>();
    let run = vec!["run".to_string(), example("probe-local.toml")];
    let reference = s(&["reference", "cornell", "--out", "out"]);
    let mut flags = Vec::new();
    for f in ["--duration", "--connect-timeout", "--metrics-interval"] {
        flags.push((run.clone(), f));
    }
    for f in ["--time", "--spp", "--width", "--height", "--seed"] {
        flags.push((reference.clone(), f));
    }
    for f in [
        "--size",
        "--count",
        "--loss",
        "--latency-ms",
        "--jitter-ms",
        "--bandwidth-mbps",
        "--duplicate",
        "--reorder",
        "--packet-bytes",
        "--capacity",
        "--window",
        "--rtt-rounds",
        "--seed",
        "--time-limit-s",
    ] {
        flags.push((s(&["bench", "transport"]), f));
    }
    for f in [
        "--width",
        "--height",
        "--frames",
        "--fps",
        "--photons",
        "--light-samples",
        "--shadow-size",
        "--downsample",
    ] {
        flags.push((s(&["bench", "client"]), f));
    }
    for f in [
        "--photons",
        "--batch-size",
        "--interval-ms",
        "--seconds",
        "--width",
        "--height",
    ] {
        flags.push((s(&["bench", "table2"]), f));
    }
    for f in [
        "--clients",
        "--photons",
        "--batch-size",
        "--interval-ms",
        "--seconds",
    ] {
        flags.push((s(&["bench", "scaling"]), f));
    }
    for f in [
        "--budgets",
        "--batch-size",
        "--spp",
        "--width",
        "--height",
        "--rate-hz",
    ] {
        flags.push((s(&["bench", "quality"]), f));
    }
    flags.push((s(&["bench", "raster"]), "--rounds"));
    for f in ["--threads", "--passes"] {
        flags.push((s(&["bench", "rays"]), f));
    }
    flags
}

#[test]
fn numeric_flags_refuse_values_no_command_can_use() {
    // None of these is valid for any numeric flag, so no command runs: each must exit 2,
    // naming its flag, within a few seconds.
    let huge = "9".repeat(10_000);
    let values = [
        "nan",
        "inf",
        "-inf",
        "1e300",
        "-1e300",
        "18446744073709551616",
        "-18446744073709551617",
        "",
        "x",
        "0x10",
        "1e",
        huge.as_str(),
    ];
    for (base, flag) in numeric_flags() {
        for v in values {
            let mut args = base.clone();
            args.push(format!("{flag}={v}"));
            let (code, err) = run_bounded(&args, Duration::from_secs(20));
            let shown = &v[..v.len().min(20)];
            assert_eq!(code, Some(2), "{base:?} {flag}={shown}: {err}");
            assert!(
                err.contains(flag) && !err.contains("panicked"),
                "{base:?} {flag}={shown}: {err}"
            );
        }
    }
}

#[test]
fn numeric_flags_at_their_edges_run_or_refuse_cleanly() {
    // Edge values that some flags accept: cheap commands run them (bounded), none panics.
    let cheap = |base: &[String]| {
        base[0] == "run" || base[0] == "reference" || (base[0] == "bench" && base[1] == "transport")
    };
    for (base, flag) in numeric_flags().into_iter().filter(|(b, _)| cheap(b)) {
        for v in ["0", "1e-300", "-1", "1"] {
            let mut args = base.clone();
            // Keep the runs that accept the value short.
            match base[0].as_str() {
                "run" if flag != "--duration" => args.push("--duration=0.5".into()),
                "reference" => {
                    for (f, small) in [("--spp", "1"), ("--width", "8"), ("--height", "8")] {
                        if f != flag {
                            args.push(format!("{f}={small}"));
                        }
                    }
                }
                "bench" => {
                    for (f, small) in [
                        ("--count", "2"),
                        ("--rtt-rounds", "1"),
                        ("--time-limit-s", "10"),
                    ] {
                        if f != flag {
                            args.push(format!("{f}={small}"));
                        }
                    }
                    args.push("--no-baseline".into());
                }
                _ => {}
            }
            args.push(format!("{flag}={v}"));
            let (code, err) = run_bounded(&args, Duration::from_secs(60));
            assert!(
                matches!(code, Some(0 | 2 | 4)),
                "{args:?}: exit {code:?}: {err}"
            );
            assert!(!err.contains("panicked"), "{args:?}: {err}");
        }
    }
}

// ---------------------------------------------------------------------------------------
// glTF files

fn assets() -> PathBuf {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("assets");
    assert!(
        dir.join("gltf2/.complete").exists(),
        "test assets missing: run scenes/fetch-assets.sh first"
    );
    dir
}

/// The project's random stream, with a bounded draw for choosing mutations.
struct Rng(cloudlight::render::sampling::Rng);

impl Rng {
    fn seeded(seed: u64) -> Self {
        Rng(cloudlight::render::sampling::Rng::new(seed, 0))
    }
    fn next(&mut self) -> u64 {
        self.0.next_u64()
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// One mutation of a glTF's JSON text: a number replaced by an extreme, a byte changed,
/// a span deleted or duplicated, or the text cut short.
fn mutate_json(text: &[u8], rng: &mut Rng) -> Vec<u8> {
    let mut t = text.to_vec();
    match rng.below(5) {
        0 | 1 => {
            // Replace the digits of one number with an extreme value.
            let starts: Vec<usize> = (1..t.len())
                .filter(|&i| t[i].is_ascii_digit() && !t[i - 1].is_ascii_alphanumeric())
                .collect();
            if let Some(&at) = starts.get(rng.below(starts.len())) {
                let end = (at..t.len())
                    .find(|&i| !(t[i].is_ascii_digit() || b".eE+-".contains(&t[i])))
                    .unwrap_or(t.len());
                let extremes = [
                    "1e39",
                    "-1e39",
                    "1e20",
                    "4294967295",
                    "2147483648",
                    "18446744073709551615",
                    "0",
                    "-1",
                    "3.4e38",
                    "1e-45",
                    "65535",
                    "7",
                ];
                let v = extremes[rng.below(extremes.len())];
                t.splice(at..end, v.bytes());
            }
        }
        2 => {
            let i = rng.below(t.len());
            t[i] = (rng.next() & 0xff) as u8;
        }
        3 => {
            let a = rng.below(t.len());
            let b = (a + 1 + rng.below(64)).min(t.len());
            if rng.below(2) == 0 {
                t.drain(a..b);
            } else {
                let piece = t[a..b].to_vec();
                t.splice(a..a, piece);
            }
        }
        _ => t.truncate(rng.below(t.len())),
    }
    t
}

/// One mutation of a binary buffer: bytes flipped (floats become NaN, huge or tiny), or the
/// buffer cut short.
fn mutate_bin(bin: &[u8], rng: &mut Rng) -> Vec<u8> {
    let mut b = bin.to_vec();
    if b.is_empty() {
        return b;
    }
    if rng.below(8) == 0 {
        b.truncate(rng.below(b.len()));
        return b;
    }
    for _ in 0..1 + rng.below(8) {
        let i = rng.below(b.len()) & !3;
        let word: [u8; 4] = match rng.below(4) {
            0 => f32::NAN.to_le_bytes(),
            1 => 1e30f32.to_le_bytes(),
            2 => u32::MAX.to_le_bytes(),
            _ => (rng.next() as u32).to_le_bytes(),
        };
        for (k, w) in word.iter().enumerate() {
            if let Some(x) = b.get_mut(i + k) {
                *x = *w;
            }
        }
    }
    b
}

/// Loads a mutated file as a run would (check included), then plans it and builds its BVH;
/// whether it loaded.
fn load_and_plan(path: &Path) -> bool {
    let spec = path.display().to_string();
    let Ok(scene) = cloudlight::scenes::load(&spec) else {
        return false;
    };
    // A coarse octree: the voxel walk's cost grows 4× per level, and the levels are not what
    // is under test.
    let settings = cloudlight::render::plan::PlanSettings {
        octree_levels: 4,
        ..Default::default()
    };
    let _ = cloudlight::render::plan::plan(&scene, &settings);
    if scene.triangle_count() > 0 {
        let _ = cloudlight::render::SceneBvh::at(&scene, 0.0, Default::default());
    }
    true
}

/// Name of the thread that fuzzes the glTF reader: panics the importer catches there (the
/// `gltf` crate unwraps some fields itself) are not printed, so that thousands of them do
/// not each cost a backtrace. Panics anywhere else print as usual.
const QUIET_THREAD: &str = "gltf-fuzz";

fn quiet_caught_panics() {
    let default = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        if std::thread::current().name() != Some(QUIET_THREAD) {
            default(info);
        }
    }));
}

#[test]
fn mutated_gltf_files_load_or_fail_cleanly_in_bounded_time() {
    quiet_caught_panics();
    let fuzz = std::thread::Builder::new()
        .name(QUIET_THREAD.into())
        .spawn(fuzz_gltf)
        .unwrap();
    let (tried, loaded) = match fuzz.join() {
        Ok(counts) => counts,
        Err(_) => panic!("a mutated glTF file panicked past the importer (run alone to see it)"),
    };
    assert!(tried >= 1000, "only {tried} mutations tried");
    assert!(
        loaded > 0,
        "no mutation loaded: the mutations are too coarse to test loading"
    );
    eprintln!("{tried} mutated glTF files, {loaded} loaded");
}

/// Mutates the test models, loads and plans each mutation; (tried, loaded).
fn fuzz_gltf() -> (usize, usize) {
    let dir = tempfile::tempdir().unwrap();
    let models = [
        "BoxTextured-glTF/BoxTextured.gltf",
        "BoxTexcoords-glTF/boxTexcoords.gltf",
        "cameras/Cameras.gltf",
        "simple_skin/simple_skin.gltf",
    ];
    let deadline = Instant::now() + Duration::from_secs(120);
    let mut rng = Rng::seeded(0x5eed);
    let mut tried = 0;
    let mut loaded = 0;
    for model in models {
        let src = assets().join("gltf2").join(model);
        let Ok(json) = std::fs::read(&src) else {
            continue;
        };
        // Copy the model's folder (its buffers and images) beside the mutated file.
        let here = dir.path().join(model.replace('/', "_"));
        std::fs::create_dir_all(&here).unwrap();
        let mut bins = Vec::new();
        for entry in std::fs::read_dir(src.parent().unwrap()).unwrap() {
            let p = entry.unwrap().path();
            if p.is_file() {
                std::fs::copy(&p, here.join(p.file_name().unwrap())).unwrap();
                if p.extension().is_some_and(|e| e == "bin") {
                    bins.push((
                        here.join(p.file_name().unwrap()),
                        std::fs::read(&p).unwrap(),
                    ));
                }
            }
        }
        let target = here.join("fuzz.gltf");
        for i in 0..1500 {
            if Instant::now() > deadline {
                break;
            }
            let mutated_bin = i % 4 == 3 && !bins.is_empty();
            if mutated_bin {
                std::fs::write(&target, &json).unwrap();
                let (p, b) = &bins[rng.below(bins.len())];
                std::fs::write(p, mutate_bin(b, &mut rng)).unwrap();
            } else {
                std::fs::write(&target, mutate_json(&json, &mut rng)).unwrap();
            }
            let started = Instant::now();
            loaded += load_and_plan(&target) as usize;
            let took = started.elapsed();
            assert!(
                took < Duration::from_secs(10),
                "{model} mutation {i} took {took:?}"
            );
            if mutated_bin {
                for (p, b) in &bins {
                    std::fs::write(p, b).unwrap();
                }
            }
            tried += 1;
        }
    }
    (tried, loaded)
}

#[test]
fn scenes_with_far_or_non_finite_geometry_are_refused_by_validate() {
    let dir = tempfile::tempdir().unwrap();
    let write = |name: &str, points: &[[f32; 3]]| -> PathBuf {
        let bin: Vec<u8> = points
            .iter()
            .flatten()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        std::fs::write(dir.path().join(format!("{name}.bin")), &bin).unwrap();
        let gltf = serde_json::json!({
            "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
            "nodes": [{"mesh": 0}],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
            "accessors": [{"bufferView": 0, "componentType": 5126, "count": points.len(), "type": "VEC3",
                           "min": [0, 0, 0], "max": [1, 1, 1]}],
            "bufferViews": [{"buffer": 0, "byteLength": bin.len()}],
            "buffers": [{"byteLength": bin.len(), "uri": format!("{name}.bin")}],
        });
        let path = dir.path().join(format!("{name}.gltf"));
        std::fs::write(&path, gltf.to_string()).unwrap();
        path
    };
    let far = write(
        "far",
        &[
            [0.0; 3],
            [1e20, 0.0, 0.0],
            [0.0, 1e20, 0.0],
            [0.0; 3],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
        ],
    );
    let nan = write("nan", &[[0.0; 3], [f32::NAN, 0.0, 0.0], [0.0, 1.0, 0.0]]);
    let random = dir.path().join("random.glb");
    std::fs::write(
        &random,
        (0..4096u32)
            .map(|i| (i.wrapping_mul(2654435761) >> 13) as u8)
            .collect::<Vec<_>>(),
    )
    .unwrap();
    for (scene, words) in [
        (&far, "beyond 100000 m"),
        (&nan, "non-finite"),
        (&random, "random.glb"),
    ] {
        // `plan` used to run for ever on coordinates near 1e20 m.
        let (code, err) = run_bounded(
            &["plan".into(), scene.display().to_string()],
            Duration::from_secs(30),
        );
        assert_eq!(code, Some(2), "plan {}: {err}", scene.display());
        assert!(err.contains(words), "plan {}: {err}", scene.display());
        let topo = dir.path().join("t.toml");
        std::fs::write(
            &topo,
            format!(
                "techniques = [\"probe\"]\nscene = \"{}\"\n[[node]]\nname = \"n\"\naddress = \"127.0.0.1:0\"\n",
                scene.display()
            ),
        )
        .unwrap();
        let (code, err) = run_bounded(
            &["validate".into(), topo.display().to_string()],
            Duration::from_secs(30),
        );
        assert_eq!(code, Some(2), "validate {}: {err}", scene.display());
        assert!(err.contains("`scene`") && err.contains(words), "{err}");
    }
}
