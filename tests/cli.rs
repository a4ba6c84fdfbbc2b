//! The command line as a user meets it: validate, run (default and file), node, kinds.

use assert_cmd::Command;

fn cloudlight() -> Command {
    let mut c = Command::cargo_bin("cloudlight").unwrap();
    c.env("RUST_LOG", "warn");
    c
}

/// Asserts that a command succeeded, showing its stderr otherwise.
fn ok(out: &std::process::Output) {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A JSON file written by a command.
fn read_json(path: impl AsRef<std::path::Path>) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

fn example(name: &str) -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("examples/topologies")
        .join(name)
}

#[test]
fn validate_prints_the_placement_and_cut_edges() {
    let out = cloudlight()
        .arg("validate")
        .arg(example("probe-cluster.toml"))
        .output()
        .unwrap();
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("node cloud @ 127.0.0.1:7200: source (probe_source)"),
        "{text}"
    );
    assert!(text.contains("CUT cloud -> edge"), "{text}");
    assert!(text.contains("3 cut"), "{text}");
}

#[test]
fn validate_reports_errors_with_file_line_and_key() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.toml");
    std::fs::write(
        &bad,
        "techniques = [\"probe\"]\nbogus = 1\n[[node]]\nname = \"a\"\naddress = \"x\"\n",
    )
    .unwrap();
    let out = cloudlight().arg("validate").arg(&bad).output().unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("bad.toml:2:1: `bogus`: unknown key"), "{err}");
    assert!(err.contains("bad.toml:5:11: `node[0].address`"), "{err}");
    assert!(err.contains("2 problems found"), "{err}");
}

#[test]
fn run_without_topology_runs_the_default_and_writes_metrics() {
    // The default: photons on the Cornell box, traced on a cloud node and streamed to two
    // clients that write their frames.
    let dir = tempfile::tempdir().unwrap();
    // As on a machine without a desktop session (where the graphics stack used to print
    // "error: XDG_RUNTIME_DIR is invalid ..." twice).
    let out = cloudlight()
        .args(["run", "--duration", "2", "--out"])
        .arg(dir.path())
        .env_remove("XDG_RUNTIME_DIR")
        .env_remove("WAYLAND_DISPLAY")
        .output()
        .unwrap();
    ok(&out);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("built-in default"));
    // A run that succeeds prints no line that reads as an error.
    for line in err.lines() {
        let lower = line.to_lowercase();
        assert!(
            !lower.trim_start().starts_with("error") && !lower.contains(" error "),
            "a successful run printed: {line}"
        );
    }
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("batcher.out -> client[0].in"), "{text}");
    assert!(text.contains("frames of client[1]: "), "{text}");
    let json = read_json(dir.path().join("metrics.json"));
    assert_eq!(json["status"], "finished");
    for client in ["client[0]", "client[1]"] {
        let stage = json["stages"]
            .as_array()
            .unwrap()
            .iter()
            .find(|s| s["name"] == client)
            .unwrap();
        let r = &stage["report"];
        assert!(r["photons_stored"].as_u64().unwrap() > 1000, "{stage}");
        assert_eq!(r["batches_rejected"], 0);
        let frames = std::path::Path::new(r["frames_dir"].as_str().unwrap());
        assert!(frames.starts_with(dir.path()), "{frames:?}");
        assert!(frames.join("frame_00000.png").is_file(), "{frames:?}");
    }
}

#[test]
fn a_failing_stage_exits_non_zero_and_names_the_stage() {
    let dir = tempfile::tempdir().unwrap();
    let topo = dir.path().join("fail.toml");
    std::fs::write(
        &topo,
        r#"techniques = ["probe"]
[[node]]
name = "a"
address = "127.0.0.1:0"
[[stage]]
name = "src"
kind = "probe_source"
node = "a"
params = { rate_hz = 500.0 }
[[stage]]
name = "flaky"
kind = "probe_relay"
node = "a"
params = { fail_after = 3 }
[[stage]]
name = "sink"
kind = "probe_sink"
node = "a"
[[edge]]
from = "src"
to = "flaky"
[[edge]]
from = "flaky"
to = "sink"
"#,
    )
    .unwrap();
    let out = cloudlight()
        .arg("run")
        .arg(&topo)
        .args(["--duration", "10", "--out"])
        .arg(dir.path().join("out"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(3));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("stage `flaky` failed"), "{err}");
    assert!(err.contains("injected failure after 3 messages"), "{err}");
}

#[test]
fn node_runs_only_its_stages_and_names_the_peers_it_waits_for() {
    let home = |extra: &[&str]| {
        cloudlight()
            .args(["node"])
            .arg(example("probe-cluster.toml"))
            .args([
                "--node",
                "home",
                "--duration",
                "1",
                "--connect-timeout",
                "0.5",
            ])
            .args(extra)
            .env("CLOUDLIGHT_TEST_SECRET", "a1b2c3d4e5f60718")
            .output()
            .unwrap()
    };
    // The example carries no secret: a node on its own refuses to start without one.
    let out = home(&[]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("node `home` is started on its own"), "{err}");
    assert!(err.contains("secret_env"), "{err}");
    let out = home(&["--secret-env", "CLOUDLIGHT_TEST_SECRET"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("peers not reachable"), "{err}");
    assert!(!err.contains("no secret"), "{err}");
    assert!(err.contains("home -> edge @ 127.0.0.1:7201"), "{err}");

    let dir = tempfile::tempdir().unwrap();
    let out = cloudlight()
        .args(["node"])
        .arg(example("probe-local.toml"))
        .args(["--node", "local", "--duration", "0.5", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    ok(&out);
    assert!(dir.path().join("metrics.json").exists());

    let out = cloudlight()
        .args(["node"])
        .arg(example("probe-local.toml"))
        .args(["--node", "elsewhere"])
        .output()
        .unwrap();
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("node `elsewhere` is not in the topology")
    );
}

#[test]
fn kinds_lists_ports_and_types() {
    let out = cloudlight().arg("kinds").output().unwrap();
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("probe_relay (technique probe)"), "{text}");
    assert!(
        text.contains("in  in           cloudlight_actors::wire::ProbeMsg [default block 8]"),
        "{text}"
    );
}

#[test]
fn every_command_documents_its_options() {
    for cmd in ["validate", "run", "node", "kinds"] {
        let out = cloudlight().args([cmd, "--help"]).output().unwrap();
        assert!(out.status.success());
        assert!(String::from_utf8_lossy(&out.stdout).contains("Usage"));
    }
}

#[test]
fn bench_transport_judges_nothing_it_did_not_receive() {
    // Everything lost: exit 4, and the report does not call nothing "byte-identical".
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("bench.json");
    let out = cloudlight()
        .args([
            "bench",
            "transport",
            "--loss",
            "1.0",
            "--count",
            "3",
            "--size",
            "100",
        ])
        .args([
            "--time-limit-s",
            "1",
            "--no-baseline",
            "--rtt-rounds",
            "1",
            "--json",
        ])
        .arg(&json)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(4));
    let r = read_json(&json);
    assert_eq!(r["delivered"], 0);
    assert!(
        r["byte_identical"].is_null() && r["in_order"].is_null(),
        "{r}"
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("none delivered"));
}

#[test]
fn bench_transport_fans_out_to_clients_and_answers_requests() {
    let dir = tempfile::tempdir().unwrap();
    for (pattern, count) in [("bulk", 200), ("request-response", 50)] {
        let json = dir.path().join(format!("{pattern}.json"));
        let out = cloudlight()
            .args(["bench", "transport", "--pattern", pattern, "--clients", "3"])
            .args([
                "--size",
                "700",
                "--count",
                &count.to_string(),
                "--loss",
                "0.05",
            ])
            .args(["--rtt-rounds", "5", "--no-baseline", "--json"])
            .arg(&json)
            .output()
            .unwrap();
        ok(&out);
        let r = read_json(&json);
        assert_eq!(r["delivered"], 3 * count, "{pattern}: {r}");
        assert_eq!(r["byte_identical"], true, "{pattern}: {r}");
        assert_eq!(r["in_order"], true, "{pattern}: {r}");
        let per_client = r["client_goodput_mb_s"].as_array().unwrap();
        assert_eq!(per_client.len(), 3, "{pattern}: {r}");
        assert!(per_client.iter().all(|g| g.as_f64().unwrap() > 0.0));
        assert!(
            r["completion_ms_p99"].as_f64().unwrap() >= r["completion_ms_p50"].as_f64().unwrap()
        );
    }
}

#[test]
fn bench_transport_reports_an_intact_transfer_through_a_lossy_link() {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("bench.json");
    let out = cloudlight()
        .args([
            "bench",
            "transport",
            "--size",
            "5000",
            "--count",
            "300",
            "--loss",
            "0.05",
            "--latency-ms",
            "1",
        ])
        .args(["--rtt-rounds", "20", "--json"])
        .arg(&json)
        .output()
        .unwrap();
    ok(&out);
    let table = String::from_utf8_lossy(&out.stdout);
    assert!(table.contains("byte-identical"), "{table}");
    let r = read_json(&json);
    assert_eq!(r["delivered"], 300);
    assert_eq!(r["byte_identical"], true);
    assert_eq!(r["in_order"], true);
    assert!(r["retransmissions"].as_u64().unwrap() > 0, "{r}");
    assert!(
        r["rtt_p50_us"].as_f64().unwrap() >= 2000.0,
        "two 1 ms hops each way: {r}"
    );
    assert!(r["udp_blast_mb_s"].as_f64().unwrap() > 0.0);

    let bad = cloudlight()
        .args(["bench", "transport", "--loss", "2"])
        .output()
        .unwrap();
    assert_eq!(bad.status.code(), Some(2));
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(
        err.contains("--loss") && err.contains("must be a number in [0, 1]"),
        "{err}"
    );
}

#[test]
fn reference_writes_three_float_images_and_pngs() {
    let dir = tempfile::tempdir().unwrap();
    // The Cornell box at 32 × 24 and 4 spp into `out`, with `extra` flags.
    let cornell = |out: &std::path::Path, extra: &[&str]| {
        cloudlight()
            .args([
                "reference",
                "cornell",
                "--spp",
                "4",
                "--width",
                "32",
                "--height",
                "24",
            ])
            .args(extra)
            .arg("--out")
            .arg(out)
            .output()
            .unwrap()
    };
    ok(&cornell(dir.path(), &[]));
    for name in ["full", "direct", "indirect"] {
        let (w, h, px) =
            cloudlight::render::image_io::read_exr(&dir.path().join(format!("{name}.exr")))
                .unwrap();
        assert_eq!((w, h), (32, 24));
        assert!(px.iter().all(|v| v.is_finite() && v.min_element() >= 0.0));
        assert!(px.iter().any(|v| v.max_element() > 0.0), "{name} is black");
        assert!(dir.path().join(format!("{name}.png")).exists());
    }
    let bad = cloudlight()
        .args(["reference", "cornell", "--camera", "7", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert_eq!(bad.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&bad.stderr).contains("has 1 camera paths"));
    let custom = cloudlight()
        .args([
            "reference",
            "city:1000",
            "--spp",
            "1",
            "--width",
            "8",
            "--height",
            "8",
            "--camera",
            "-4,2,-4:20,1,20:60",
            "--out",
        ])
        .arg(dir.path().join("city"))
        .output()
        .unwrap();
    assert!(
        custom.status.success(),
        "{}",
        String::from_utf8_lossy(&custom.stderr)
    );
    // Through each pixel's centre: the same light on the whole, another where pixels
    // straddle the box's edges; a sampling it does not know is refused.
    ok(&cornell(&dir.path().join("centre"), &["--pixel", "centre"]));
    let read = |d: &std::path::Path| {
        cloudlight::render::image_io::read_exr(&d.join("direct.exr"))
            .unwrap()
            .2
    };
    let (area, centre) = (read(dir.path()), read(&dir.path().join("centre")));
    assert_eq!(area.len(), centre.len());
    let mean = |img: &[cloudlight::scenes::glam::Vec3]| {
        img.iter().map(|v| v.element_sum() as f64).sum::<f64>() / img.len() as f64
    };
    let (ma, mc) = (mean(&area), mean(&centre));
    assert!((ma / mc - 1.0).abs() < 0.1, "area {ma}, centre {mc}");
    // Pixels whose centre sees another surface (or the dark) than most of their area.
    let straddle = area
        .iter()
        .zip(&centre)
        .filter(|(a, c)| {
            (a.element_sum() - c.element_sum()).abs() > 0.5 * a.element_sum().max(c.element_sum())
        })
        .count();
    assert!(
        straddle > 0 && straddle < area.len() / 4,
        "{straddle} of {} pixels straddle an edge",
        area.len()
    );
    let bad = cloudlight()
        .args(["reference", "cornell", "--pixel", "corner", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert_eq!(bad.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&bad.stderr).contains("area, centre"));
}

#[test]
fn plan_describes_the_scene_and_the_allocations() {
    let out = cloudlight().args(["plan", "cornell"]).output().unwrap();
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("32 triangles"), "{text}");
    assert!(text.contains("0.7290 / 0.5146 / 0.1715 W"), "{text}");
    assert!(text.contains("512³"), "{text}");
    assert!(text.contains("10000 an iteration"), "{text}");
    assert!(
        text.contains("128×128 atlas") && text.contains("45 bases"),
        "{text}"
    );
    let bad = cloudlight()
        .args(["plan", "nowhere.gltf"])
        .output()
        .unwrap();
    assert_eq!(bad.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&bad.stderr).contains("nowhere.gltf"));
}

#[test]
fn photon_table2_benchmark_prints_our_rows_beside_the_papers() {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("table2.json");
    let out = cloudlight()
        .args([
            "bench",
            "table2",
            "--technique",
            "photons",
            "--scene",
            "cornell",
            "--seconds",
            "1",
            "--width",
            "64",
            "--height",
            "48",
            "--json",
        ])
        .arg(&json)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    ok(&out);
    for row in [
        "Number of batches",
        "Photons per batch",
        "Memory footprint",
        "Iteration interval",
        "Photon trace",
        "Photon packing",
        "Send",
        "Server-to-client bandwidth",
        "Local device stored photons",
        "Client indirect",
    ] {
        assert!(text.contains(row), "{row} missing: {text}");
    }
    let report = read_json(&json);
    let col = &report["columns"][0];
    assert_eq!(col["batches"], 1.0);
    assert!(
        col["server_to_client_mbps"].as_f64().unwrap() > 0.0,
        "{col}"
    );
    assert!(
        col["client_stored_photons"].as_f64().unwrap() > 1000.0,
        "{col}"
    );
    assert!(text.contains("paper: Cornell Box"), "{text}");
}

#[test]
fn photon_scaling_benchmark_writes_its_table_json_and_plot() {
    let dir = tempfile::tempdir().unwrap();
    let scaling = dir.path().join("scaling");
    let out = cloudlight()
        .args([
            "bench",
            "scaling",
            "--technique",
            "photons",
            "--clients",
            "1,3",
            "--seconds",
            "1",
            "--out",
        ])
        .arg(&scaling)
        .output()
        .unwrap();
    ok(&out);
    let report = read_json(scaling.join("scaling.json"));
    let rows = report["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 2);
    assert_eq!(rows[1]["clients_showing_indirect"], 3);
    assert!(scaling.join("scaling.png").metadata().unwrap().len() > 1000);
}

#[test]
fn photon_quality_benchmark_writes_its_table_json_and_pareto_plot() {
    let dir = tempfile::tempdir().unwrap();
    let quality = dir.path().join("quality");
    let out = cloudlight()
        .args([
            "bench",
            "quality",
            "--technique",
            "photons",
            "--budgets",
            "1000,8000",
            "--spp",
            "64",
            "--width",
            "32",
            "--height",
            "32",
            "--set",
            "passes=3",
            "--set",
            "window=2",
            "--still-frames",
            "4",
            "--out",
        ])
        .arg(&quality)
        .output()
        .unwrap();
    ok(&out);
    let report = read_json(quality.join("quality.json"));
    // The client's image: the mean of 4 jittered frames of the still view.
    assert_eq!(report["options"]["still_frames"], 4);
    // Passes 1, 2 and 3 of the first budget while the scene stands still.
    let progressive = report["progressive"].as_array().unwrap();
    let passes: Vec<u64> = progressive
        .iter()
        .map(|p| p["passes"].as_u64().unwrap())
        .collect();
    assert_eq!(passes, vec![1, 2, 3]);
    for p in progressive {
        assert!(p["errors"]["relmse"].as_f64().unwrap().is_finite(), "{p}");
    }
    // A light that changes every iteration, drawn from its last 1 and 2 generations: twice
    // the photons for the same bytes an update.
    let window = report["window"].as_array().unwrap();
    assert_eq!(window.len(), 2, "{window:?}");
    assert!(window[1]["photons"].as_u64() > window[0]["photons"].as_u64());
    assert_eq!(window[0]["kbytes"], window[1]["kbytes"]);
    assert!(window[1]["errors"]["relmse"].as_f64().unwrap().is_finite());
    let photons: Vec<u64> = progressive
        .iter()
        .map(|p| p["photons"].as_u64().unwrap())
        .collect();
    assert!(
        photons[2] > photons[1] && photons[1] > photons[0],
        "{photons:?}"
    );
    for row in report["rows"].as_array().unwrap() {
        for packing in ["eight", "twelve", "twenty"] {
            let p = &row[packing];
            for value in [
                &p["errors"]["relmse"],
                &p["errors"]["flip"],
                &p["errors"]["energy_ratio"],
                &p["update_ms"],
                &p["mbps"],
            ] {
                assert!(value.as_f64().unwrap().is_finite(), "{packing}: {row}");
            }
            let worst = p["errors"]["worst_share"].as_f64().unwrap();
            assert!((0.0..=1.0).contains(&worst), "{packing}: {row}");
        }
        // The box's one light, an emissive surface: what it emitted and stored.
        let lights = row["eight"]["lights"].as_array().unwrap();
        assert_eq!(lights.len(), 1, "{row}");
        assert_eq!(lights[0]["kind"], "surface");
        assert_eq!(lights[0]["stored"], row["eight"]["stored"]);
        let emitted = lights[0]["emitted"].as_f64().unwrap();
        let budget = row["photons"].as_f64().unwrap();
        assert!((emitted / budget - 1.0).abs() < 0.01, "{row}");
    }
    let table = String::from_utf8_lossy(&out.stdout);
    assert!(
        table.contains("Photons stored per photon emitted") && table.contains("surface lights"),
        "{table}"
    );
    // The reference's own noise (64 spp: small, but not nothing), and each image beside it.
    let noise = report["reference_noise"].as_f64().unwrap();
    assert!(noise > 0.0 && noise < 0.5, "{noise}");
    // What a client shading pixel centres with exact light shows: the box's edges hold some.
    let floor = report["sampling_floor"].as_f64().unwrap();
    assert!(floor > 0.0 && floor < 1.0, "{floor}");
    for image in ["indirect_8000", "progressive_1000_3"] {
        assert!(quality.join(format!("{image}.exr")).is_file(), "{image}");
        assert!(
            quality
                .join(format!("{image}.png"))
                .metadata()
                .unwrap()
                .len()
                > 1000,
            "{image}"
        );
    }
    assert!(quality.join("quality.png").metadata().unwrap().len() > 1000);
}

#[test]
fn quality_benchmark_measures_the_view_it_is_given() {
    let dir = tempfile::tempdir().unwrap();
    let run = |camera: &str, out: &std::path::Path| {
        cloudlight()
            .args([
                "bench",
                "quality",
                "--budgets",
                "1000",
                "--spp",
                "16",
                "--width",
                "16",
                "--height",
                "16",
                "--camera",
                camera,
                "--out",
            ])
            .arg(out)
            .env("CLOUDLIGHT_REFERENCE_CACHE", "off")
            .output()
            .unwrap()
    };
    // The scene's own camera, and one inside the box looking into a corner.
    let (own, inside) = (dir.path().join("own"), dir.path().join("inside"));
    ok(&run("0", &own));
    let corner = "0.4,0.35,0.2:0.05,0.1,0.5:60";
    ok(&run(corner, &inside));
    assert_eq!(
        read_json(inside.join("quality.json"))["options"]["camera"],
        corner
    );
    let reference = |d: &std::path::Path| {
        cloudlight::render::image_io::read_exr(&d.join("reference_indirect.exr"))
            .unwrap()
            .2
    };
    assert_ne!(
        reference(&own),
        reference(&inside),
        "the view made no difference"
    );
    // Views that are none are refused before anything is rendered.
    for (camera, words) in [
        ("7", "has 1 camera paths"),
        ("0,1,3:0,1,3", "camera `0,1,3:0,1,3`"),
        ("1,2:3,4,5", "expected an index"),
    ] {
        let out = run(camera, &dir.path().join("bad"));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{camera}");
        assert!(err.contains(words), "{camera}: {err}");
        assert!(
            !err.contains("reference:"),
            "{camera}: rendered before refusing: {err}"
        );
    }
}

/// `bench quality --technique photons` at a tiny size (8², 4 spp, no reference cache) with
/// `args`, into `out`.
fn photon_quality(args: &[&str], out: &std::path::Path) -> std::process::Output {
    cloudlight()
        .args(["bench", "quality", "--technique", "photons"])
        .args(["--spp", "4", "--width", "8", "--height", "8"])
        .args(args)
        .arg("--out")
        .arg(out)
        .env("CLOUDLIGHT_REFERENCE_CACHE", "off")
        .output()
        .unwrap()
}

#[test]
fn photon_quality_sweeps_a_knob_and_draws_each_combination_s_front() {
    let dir = tempfile::tempdir().unwrap();
    let run = |sweep: &str, out: &std::path::Path| {
        photon_quality(&["--sweep", sweep, "--budgets", "300,600"], out)
    };
    let out = run("fit=0,3", dir.path());
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("quality.json")).unwrap()).unwrap();
    assert_eq!(report["swept"], serde_json::json!(["fit"]));
    let variants = report["variants"].as_array().unwrap();
    assert_eq!(variants.len(), 2);
    for (v, (label, fit)) in variants.iter().zip([("fit=0", 0), ("fit=3", 3)]) {
        assert_eq!(v["label"], label);
        assert_eq!(v["options"]["fit"], fit);
        let budgets: Vec<u64> = v["rows"]
            .as_array()
            .unwrap()
            .iter()
            .map(|r| r["photons"].as_u64().unwrap())
            .collect();
        assert_eq!(budgets, [300, 600]);
        // Each combination's own table, images and plot in its folder.
        for file in [
            "quality.json",
            "quality.png",
            "indirect_600.exr",
            "indirect_600.png",
        ] {
            assert!(
                dir.path().join(label).join(file).is_file(),
                "{label}/{file}"
            );
        }
    }
    assert!(dir.path().join("quality.png").is_file());
    // A combination a batcher would refuse stops the run before anything renders.
    let out = run("fit=3,9", &dir.path().join("bad"));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("`fit` = 9 is out of range"), "{err}");
    assert!(!dir.path().join("bad").join("fit=3").exists(), "{err}");
}

#[test]
fn photon_quality_refuses_knobs_a_batcher_or_client_would_refuse() {
    let dir = tempfile::tempdir().unwrap();
    for (knob, words) in [
        ("fit=9", "`fit` = 9 is out of range: must be in [0, 8]"),
        ("passes=5000", "`passes` = 5000 is out of range"),
        ("levels=0", "`levels` = 0 must be 1 to 4"),
        (
            "window=65",
            "`window` = 65 is out of range: must be in [1, 64]",
        ),
    ] {
        let out = photon_quality(&["--set", knob, "--budgets", "100"], dir.path());
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{knob}");
        assert!(err.contains(words), "{knob}: {err}");
        assert!(
            !err.contains("reference:"),
            "{knob}: rendered before refusing: {err}"
        );
    }
    let out = photon_quality(&["--still-frames", "0", "--budgets", "100"], dir.path());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("--still-frames"),
        "{err}"
    );
}

#[test]
fn table2_puts_the_full_frame_baseline_beside_the_photon_cut() {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("baseline.json");
    let out = cloudlight()
        .args([
            "bench",
            "table2",
            "--technique",
            "photons-video",
            "--seconds",
            "2",
            "--width",
            "64",
            "--height",
            "48",
            "--fps",
            "15",
            "--json",
        ])
        .arg(&json)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    ok(&out);
    for row in [
        "| cornell | photons: client splats |",
        "| cornell | photons-video: cloud renders + encodes |",
        "| paper: Cornell Box | voxels: final frames as video (HW encoder) |",
        "5 ms frame + 4.2 ms encode",
    ] {
        assert!(text.contains(row), "{row} missing: {text}");
    }
    let report = read_json(&json);
    let (p, v) = (
        &report["columns"][0]["photons"],
        &report["columns"][0]["video"],
    );
    assert!(p["server_to_client_mbps"].as_f64().unwrap() > 0.0, "{p}");
    assert!(p["age_ms_p50"].as_f64().unwrap() > 0.0, "{p}");
    for key in [
        "frame_ms_p50",
        "encode_ms_p50",
        "decode_ms_p50",
        "wire_mbps",
    ] {
        assert!(v[key].as_f64().unwrap() > 0.0, "{key}: {v}");
    }
    assert!(
        v["pictures"].as_u64().unwrap() > 0,
        "the thin client showed pictures: {v}"
    );
    assert_eq!(v["decode_errors"], 0, "{v}");
    assert!(v["key_frames"].as_u64().unwrap() >= 1, "{v}");
    assert!(v["age_ms_p50"].as_f64().unwrap() > 0.0, "{v}");
}

#[test]
fn table2_of_voxels_prints_the_papers_voxel_block_beside_ours() {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("voxels.json");
    let out = cloudlight()
        .args([
            "bench",
            "table2",
            "--technique",
            "voxels",
            "--seconds",
            "2",
            "--width",
            "64",
            "--height",
            "48",
            "--fps",
            "15",
            "--set",
            "max_depth=5",
            "--json",
        ])
        .arg(&json)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    ok(&out);
    for row in [
        "| cornell (ours) | paper: Cornell Box |",
        "| Gather |",
        "| 7 ms |",
        "| GI voxel memory |",
        "| 0.13 GB |",
        "| 2.8 Gbps |",
        "| 4.2 ms |",
    ] {
        assert!(text.contains(row), "{row} missing: {text}");
    }
    let c = &read_json(&json)["columns"][0];
    assert_eq!(c["depth"], 5, "{c}");
    for key in [
        "inject_ms",
        "gather_ms",
        "memory_mb",
        "gi_to_frame_mbps",
        "frame_ms_p50",
        "encode_ms_p50",
        "server_to_client_mbps",
    ] {
        assert!(c[key].as_f64().unwrap() > 0.0, "{key}: {c}");
    }
    let ratio = c["delta_ratio_to_raw"].as_f64().unwrap();
    assert!(ratio > 0.0 && ratio < 0.25, "{c}");
    assert!(c["pictures"].as_u64().unwrap() > 0, "{c}");
}

#[test]
fn voxel_quality_sweeps_depth_cones_precision_and_bitrate_and_reports_the_leak() {
    let dir = tempfile::tempdir().unwrap();
    let out = cloudlight()
        .args([
            "bench",
            "quality",
            "--technique",
            "voxels",
            "--width",
            "32",
            "--height",
            "32",
            "--spp",
            "16",
            "--sweep",
            "max_depth=4",
            "--sweep",
            "mantissa_bits=4,23",
            "--sweep",
            "cones=1,6",
            "--sweep",
            "qp=24",
            "--sweep",
            "bitrate_mbps=0.2",
            "--out",
        ])
        .arg(dir.path())
        .output()
        .unwrap();
    ok(&out);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("| depth | gather levels up | cones |"),
        "{text}"
    );
    let report = read_json(dir.path().join("quality.json"));
    let points = report["points"].as_array().unwrap();
    assert_eq!(points.len(), 8, "{report}");
    let at = |bits: u64, cones: u64, video: &str| {
        points
            .iter()
            .find(|p| p["mantissa_bits"] == bits && p["cones"] == cones && p["video"] == video)
            .unwrap_or_else(|| panic!("no point {bits} bits, {cones} cones, {video}: {report}"))
    };
    for p in points {
        assert!(p["before"]["relmse"].as_f64().unwrap().is_finite(), "{p}");
        assert!(p["after"]["relmse"].as_f64().unwrap().is_finite(), "{p}");
        assert!(p["leak"].as_f64().unwrap() > 0.0, "{p}");
        assert!(p["gi_mbps"].as_f64().unwrap() > 0.0, "{p}");
        assert!(p["video_mbps"].as_f64().unwrap() > 0.0, "{p}");
    }
    for cones in [1, 6] {
        // Fewer mantissa bits, fewer bytes.
        assert!(
            at(4, cones, "QP 24")["delta_kbytes"].as_f64()
                < at(23, cones, "QP 24")["delta_kbytes"].as_f64()
        );
    }
    // The cone count changes what is gathered.
    assert_ne!(
        at(23, 1, "QP 24")["before"]["relmse"],
        at(23, 6, "QP 24")["before"]["relmse"]
    );
    // Rate control keeps a second of the still view near its target (0.2 Mbps; openh264
    // overshoots on the key frame of a tiny picture, so within a factor).
    let mbps = at(23, 6, "0.2 Mbps")["video_mbps"].as_f64().unwrap();
    assert!(mbps < 0.6, "{mbps} Mbps");
    assert!(dir.path().join("quality.png").metadata().unwrap().len() > 1000);
    assert!(dir.path().join("reference_indirect.exr").exists());
}

#[test]
fn irradiance_benchmarks_print_the_papers_rows_scale_sweep_and_split_the_frame() {
    let dir = tempfile::tempdir().unwrap();
    // Table 2: the Cornell box beside the paper's, a scene without a light map as n/a.
    let json = dir.path().join("table2.json");
    let out = cloudlight()
        .args([
            "bench",
            "table2",
            "--technique",
            "irradiance",
            "--scene",
            "cornell-animated,cornell",
            "--seconds",
            "1.5",
            "--width",
            "32",
            "--height",
            "24",
            "--set",
            "unwrap_limit_s=0",
            "--json",
        ])
        .arg(&json)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    ok(&out);
    for row in [
        "| Number of basis functions | n/a | 50 |",
        "| Rays per update | n/a | 26k |",
        "TEXCOORD_1",
    ] {
        assert!(text.contains(row), "{row} missing: {text}");
    }
    let out = cloudlight()
        .args([
            "bench",
            "table2",
            "--technique",
            "irradiance",
            "--scene",
            "cornell-animated",
            "--seconds",
            "1.5",
            "--width",
            "32",
            "--height",
            "24",
            "--json",
        ])
        .arg(&json)
        .output()
        .unwrap();
    ok(&out);
    let col = &read_json(&json)["columns"][0];
    assert_eq!(col["na"], serde_json::Value::Null, "{col}");
    assert!((30..=80).contains(&col["bases"].as_u64().unwrap()), "{col}");
    assert_eq!(col["resolution"], 128, "{col}");
    assert!(
        col["server_to_client_mbps"].as_f64().unwrap() > 0.0,
        "{col}"
    );
    assert!(col["maps_blended"].as_u64().unwrap() >= 3, "{col}");
    assert!(col["client_indirect_ms"].as_f64().unwrap() > 0.0, "{col}");
    // Scaling: one gatherer and encoder for every client.
    let scaling = dir.path().join("scaling");
    let out = cloudlight()
        .args([
            "bench",
            "scaling",
            "--technique",
            "irradiance",
            "--clients",
            "1,3",
            "--seconds",
            "1.5",
            "--out",
        ])
        .arg(&scaling)
        .output()
        .unwrap();
    ok(&out);
    let rows = read_json(scaling.join("scaling.json"))["rows"].clone();
    assert_eq!(rows[1]["clients_showing_indirect"], 3, "{rows}");
    // Quality: raw and H.264 errors of each point, and the per-texel point.
    let quality = dir.path().join("quality");
    let out = cloudlight()
        .args([
            "bench",
            "quality",
            "--technique",
            "irradiance",
            "--spp",
            "16",
            "--width",
            "24",
            "--height",
            "24",
            "--sweep",
            "rays_per_basis=128",
            "--sweep",
            "fit=constant,quadratic",
            "--sweep",
            "rays_per_texel=8",
            "--sweep",
            "qp=16,28",
            "--out",
        ])
        .arg(&quality)
        .output()
        .unwrap();
    ok(&out);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("per basis (") && text.contains("fewer rays"),
        "{text}"
    );
    let points = read_json(quality.join("quality.json"))["points"].clone();
    let points = points.as_array().unwrap();
    assert_eq!(points.len(), 5, "two QPs per basis fit, one per texel");
    let fits: Vec<&str> = points.iter().map(|p| p["fit"].as_str().unwrap()).collect();
    assert_eq!(
        fits,
        ["constant", "constant", "quadratic", "quadratic", "-"]
    );
    for p in points {
        for e in [&p["raw"], &p["h264"]] {
            assert!(e["relmse"].as_f64().unwrap().is_finite(), "{p}");
        }
    }
    assert!(quality.join("quality.png").metadata().unwrap().len() > 1000);
    assert!(quality.join("reference_indirect.exr").exists());
    // The client's frame, split by pass.
    let out = cloudlight()
        .args([
            "bench",
            "client",
            "--technique",
            "irradiance",
            "--width",
            "32",
            "--height",
            "24",
            "--frames",
            "2",
        ])
        .output()
        .unwrap();
    ok(&out);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("| indirect |") && text.contains("light map"),
        "{text}"
    );
}

#[test]
fn bench_rays_compares_with_embree_or_says_why_not() {
    let dir = tempfile::tempdir().unwrap();
    for (library, expect_embree) in [(None, true), (Some("/nonexistent/libembree3.so"), false)] {
        let json = dir.path().join("rays.json");
        let mut cmd = cloudlight();
        cmd.args(["bench", "rays", "--scene", "cornell", "--threads", "1"])
            .args(["--passes", "1", "--against-embree", "--json"])
            .arg(&json);
        if let Some(l) = library {
            cmd.env("CLOUDLIGHT_EMBREE", l);
        }
        let out = cmd.output().unwrap();
        ok(&out);
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
        let rows = v["rows"].as_array().unwrap();
        let embree_rows = rows
            .iter()
            .filter(|r| r["backend"].as_str().unwrap().starts_with("Embree"))
            .count();
        let unavailable = v["embree_unavailable"].as_str();
        if expect_embree && unavailable.is_none() {
            // Installed (scripts/setup.sh installs it): three modes on three ray sets.
            assert_eq!(embree_rows, 9, "{v}");
        } else {
            // Not loadable: the flag says so and the project's own rows are still measured.
            assert_eq!(embree_rows, 0, "{v}");
            assert!(
                unavailable.unwrap().contains("Embree 3 is not installed"),
                "{v}"
            );
            let err = String::from_utf8_lossy(&out.stderr);
            assert!(
                err.contains("--against-embree: Embree 3 is not installed"),
                "{err}"
            );
        }
        for r in rows {
            assert!(r["mrays_s"].as_f64().unwrap() > 0.0, "{r}");
            assert!(r["agreement"].as_f64().unwrap() > 0.99, "{r}");
        }
        assert_eq!(
            rows.len() - embree_rows,
            12,
            "three layouts of the project and its streams on three ray sets"
        );
    }
}

#[test]
fn benchmarks_of_missing_techniques_say_so() {
    let out = cloudlight()
        .args(["bench", "table2", "--technique", "rays"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("unknown technique `rays`"));
    for (technique, benches) in [
        ("photons-video", &["quality", "client"][..]),
        ("voxels", &["client"][..]),
    ] {
        for &bench in benches {
            let out = cloudlight()
                .args(["bench", bench, "--technique", technique])
                .output()
                .unwrap();
            assert!(!out.status.success(), "{bench}");
            let err = String::from_utf8_lossy(&out.stderr);
            assert!(
                err.contains(&format!("`{technique}` has no {bench}")),
                "{technique} {bench}: {err}"
            );
        }
    }
    // A knob the technique lacks is refused before anything runs, naming the known ones.
    for bench in ["table2", "scaling", "quality", "client"] {
        let out = cloudlight()
            .args(["bench", bench, "--set", "bases=50"])
            .output()
            .unwrap();
        assert!(!out.status.success(), "{bench}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            err.contains("`photons` has no knob `bases`") && err.contains("batch_size = 10000"),
            "{bench}: {err}"
        );
    }
}

#[test]
fn bench_client_draws_a_still_lights_passes_together() {
    // The photons drawn, from the line that names the scene ("…, N photons[ in P passes], …"),
    // as the batcher sends them unmerged (`merge=0`: it merges a first pass in cells
    // larger than a refinement pass's, so merged counts do not grow with P alone).
    let drawn = |passes: &str| {
        let out = cloudlight()
            .args([
                "bench",
                "client",
                "--technique",
                "photons",
                "--scene",
                "cornell",
            ])
            .args(["--width", "64", "--height", "48", "--frames", "2"])
            .args(["--photons", "1000", "--set", passes, "--set", "merge=0"])
            .output()
            .unwrap();
        ok(&out);
        let text = String::from_utf8_lossy(&out.stdout).to_string();
        let line = text
            .lines()
            .find(|l| l.starts_with("cornell:"))
            .unwrap_or_else(|| panic!("{text}"))
            .to_string();
        let n: usize = line
            .split(", ")
            .find(|f| f.contains(" photons"))
            .and_then(|f| f.split(' ').next())
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("{line}"));
        (n, line)
    };
    // The photons splatted after merging ("…, M splatted (merged), …").
    let splatted = |line: &str| -> Option<usize> {
        line.split(", ")
            .find(|f| f.ends_with(" splatted (merged)"))
            .and_then(|f| f.split(' ').next()?.parse().ok())
    };
    let (one, line) = drawn("passes=1");
    assert!(!line.contains("passes"), "{line}");
    let (three, line) = drawn("passes=3");
    assert!(line.contains(" photons in 3 passes"), "{line}");
    // Three passes of fresh photons of the same budget, drawn together.
    assert!(
        (2.5 * one as f64..=3.5 * one as f64).contains(&(three as f64)),
        "{one} → {three}"
    );
    // Merged (the default) into fewer photons; not at all with `splat_merge=0`.
    let merged = splatted(&line).unwrap_or_else(|| panic!("{line}"));
    assert!(merged > 0 && merged < three, "{line}");
    let (_, line) = drawn("splat_merge=0");
    assert_eq!(splatted(&line), None, "{line}");
}

#[test]
fn bench_client_splits_the_frame_by_pass() {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("client.json");
    let out = cloudlight()
        .args([
            "bench",
            "client",
            "--technique",
            "photons",
            "--scene",
            "cornell-animated",
            "--width",
            "64",
            "--height",
            "48",
            "--frames",
            "3",
            "--photons",
            "2000",
            "--json",
        ])
        .arg(&json)
        .output()
        .unwrap();
    ok(&out);
    let text = String::from_utf8_lossy(&out.stdout);
    // The passes, then the photon pass's own steps.
    let passes = [
        "gbuffer",
        "shadows",
        "direct",
        "indirect",
        "indirect: guides",
        "indirect: splat",
        "indirect: resolve",
        "indirect: upsample",
        "compose",
        "accumulate",
        "readback",
        "total (split)",
    ];
    for pass in passes {
        assert!(text.contains(&format!("| {pass} |")), "{pass}: {text}");
    }
    let report = read_json(&json);
    let names: Vec<&str> = report["passes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["pass"].as_str().unwrap())
        .collect();
    assert_eq!(names, passes);
    assert!(report["frame_p50_ms"].as_f64().unwrap() > 0.0);
    // The light of cornell-animated moves every frame: every split frame re-renders shadows,
    // and the view is never still, so nothing accumulates.
    assert_eq!(report["frames_with_shadows"], 3);
    let accumulate = report["passes"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p["pass"] == "accumulate")
        .unwrap();
    assert_eq!(accumulate["p50_ms"].as_f64(), Some(0.0), "{accumulate}");
    // The raster anchor of TARGETS.md, measured in the same run, and the frame read against it.
    let anchor = &report["anchor"];
    assert!(anchor["triangles"].as_u64().unwrap() >= 100_000, "{anchor}");
    assert_eq!(
        (anchor["width"].as_u64(), anchor["height"].as_u64()),
        (Some(1280), Some(720))
    );
    assert!(anchor["gbuffer_p50_ms"].as_f64().unwrap() > 0.0, "{anchor}");
    assert!(
        text.contains("raster anchor (TARGETS.md: 100k triangles at 1280x720"),
        "{text}"
    );
    // The frame is read at the targets' speed only where the anchor ran on their backend.
    let scaled = anchor["backend"].as_str().unwrap() == "Vulkan";
    assert_eq!(
        text.contains("the whole frame at their speed"),
        scaled,
        "{text}"
    );
    assert_eq!(text.contains("not scaled"), !scaled, "{text}");
    let bad = cloudlight()
        .args(["bench", "client", "--downsample", "3"])
        .output()
        .unwrap();
    assert!(!bad.status.success());
}

/// Runs an example topology for `seconds`; its output folder and each client's (named in
/// `clients`) stage report and `frames.csv`.
fn run_example(
    file: &str,
    seconds: &str,
    clients: &[&str],
) -> (tempfile::TempDir, Vec<(serde_json::Value, String)>) {
    let dir = tempfile::tempdir().unwrap();
    let out = cloudlight()
        .arg("run")
        .arg(example(file))
        .args(["--duration", seconds, "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{file}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let json = read_json(dir.path().join("metrics.json"));
    let found = clients
        .iter()
        .map(|client| {
            let stage = json["stages"]
                .as_array()
                .unwrap()
                .iter()
                .find(|s| s["name"] == *client)
                .unwrap_or_else(|| panic!("{file}: no stage {client}"));
            let folder = dir.path().join(client.replace('[', "-").replace(']', ""));
            let csv = std::fs::read_to_string(folder.join("frames.csv")).unwrap();
            (stage["report"].clone(), csv)
        })
        .collect();
    (dir, found)
}

#[test]
fn the_photon_example_topologies_run_with_the_batcher_anywhere() {
    // Local (one node) and client-side tracing (a batcher on each client's node): the same
    // stages, placed by the topology alone. Each client logs its frames to frames.csv.
    for (file, clients) in [
        ("photons-local.toml", vec!["client"]),
        ("photons-client-traces.toml", vec!["client[0]", "client[1]"]),
    ] {
        for (client, (report, csv)) in clients.iter().zip(run_example(file, "1.5", &clients).1) {
            assert!(
                report["photons_stored"].as_u64().unwrap() > 1000,
                "{file} {client}: {report}"
            );
            let mut lines = csv.lines();
            assert_eq!(
                lines.next(),
                Some("frame,scene_time_s,frame_ms,age_ms,photons_stored")
            );
            assert!(lines.count() >= 2, "{file} {client}: {csv}");
        }
    }
}

#[test]
fn the_irradiance_example_topologies_validate_run_and_write_frames_with_light() {
    // H.264 maps to two clients, the raw f16 map across the cut, and one node.
    for (file, clients) in [
        ("irradiance-cloud.toml", vec!["client[0]", "client[1]"]),
        ("irradiance-raw.toml", vec!["client"]),
        ("irradiance-local.toml", vec!["client"]),
    ] {
        let valid = cloudlight()
            .arg("validate")
            .arg(example(file))
            .output()
            .unwrap();
        assert!(
            valid.status.success(),
            "{file}: {}",
            String::from_utf8_lossy(&valid.stderr)
        );
        let (dir, found) = run_example(file, "2", &clients);
        for (client, (r, csv)) in clients.iter().zip(found) {
            assert!(
                r["maps_blended"].as_u64().unwrap() >= 1,
                "{file} {client}: {r}"
            );
            assert_eq!(r["decode_errors"], 0, "{file} {client}: {r}");
            assert_eq!(r["indirect_shown"], true, "{file} {client}: {r}");
            assert!(
                csv.starts_with("frame,scene_time_s,frame_ms,age_ms,maps_blended"),
                "{csv}"
            );
            let folder = dir.path().join(client.replace('[', "-").replace(']', ""));
            assert!(folder.join("frame_00000.png").exists(), "{file} {client}");
        }
    }
}

#[test]
fn the_voxel_example_topologies_run_on_one_node_split_and_as_video_to_thin_clients() {
    let stage_of = |json: &serde_json::Value, name: &str| {
        json["stages"]
            .as_array()
            .unwrap()
            .iter()
            .find(|s| s["name"] == name)
            .unwrap_or_else(|| panic!("no stage {name}"))["report"]
            .clone()
    };
    // The frame renderer on the GI node's node, and on each client (deltas over the link).
    for (file, clients) in [
        ("voxels-local.toml", vec!["render"]),
        ("voxels-split.toml", vec!["render[0]", "render[1]"]),
    ] {
        let (dir, found) = run_example(file, "2", &clients);
        for (client, (r, csv)) in clients.iter().zip(found) {
            assert!(
                r["updates_complete"].as_u64().unwrap() >= 1,
                "{file} {client}: {r}"
            );
            for refused in [
                "deltas_rejected",
                "deltas_foreign",
                "deltas_out_of_sequence",
            ] {
                assert_eq!(r[refused], 0, "{file} {client}: {r}");
            }
            assert_eq!(r["indirect_shown"], true, "{file} {client}: {r}");
            assert!(
                csv.starts_with(
                    "frame,scene_time_s,frame_ms,age_ms,voxel_updates,volume_from_level"
                ),
                "{csv}"
            );
            let folder = dir.path().join(client.replace('[', "-").replace(']', ""));
            assert!(folder.join("frame_00000.png").exists(), "{file} {client}");
        }
        let json = read_json(dir.path().join("metrics.json"));
        let cones = stage_of(&json, "cones");
        assert!(cones["updates_sent"].as_u64().unwrap() >= 1, "{cones}");
        // The deltas cost a fraction of the raw values (the issue's target: at most 1/4).
        let ratio = cones["ratio_to_raw"].as_f64().unwrap();
        assert!(ratio > 0.0 && ratio < 0.25, "{cones}");
        let inject = stage_of(&json, "inject");
        assert!(inject["bounces_applied"].as_u64().unwrap() >= 1, "{inject}");
    }
    // The paper's deployment: frames rendered on a frame node, H.264 to thin clients.
    let dir = tempfile::tempdir().unwrap();
    let out = cloudlight()
        .arg("run")
        .arg(example("voxels-cloud.toml"))
        .args(["--duration", "3", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    ok(&out);
    let json = read_json(dir.path().join("metrics.json"));
    for i in 0..2 {
        let render = stage_of(&json, &format!("render[{i}]"));
        assert!(
            render["updates_complete"].as_u64().unwrap() >= 1,
            "{render}"
        );
        let viewer = stage_of(&json, &format!("viewer[{i}]"));
        assert!(
            viewer["decoder"]["pictures"].as_u64().unwrap() >= 1,
            "{viewer}"
        );
        assert_eq!(viewer["decoder"]["errors"], 0, "{viewer}");
        assert!(viewer["indirect_shown"].as_bool().unwrap(), "{viewer}");
    }
}

#[test]
fn run_flags_that_cannot_be_durations_are_refused_before_anything_runs() {
    for (flag, value) in [
        ("--duration", "nan"),
        ("--duration", "inf"),
        ("--duration", "1e300"),
        ("--duration", "-1"),
        ("--metrics-interval", "inf"),
        ("--metrics-interval", "nan"),
        ("--metrics-interval", "0"),
        ("--connect-timeout", "nan"),
        ("--connect-timeout", "1e300"),
    ] {
        let out = cloudlight()
            .arg("run")
            .arg(example("probe-local.toml"))
            .arg(format!("{flag}={value}"))
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{flag} {value}: {err}");
        assert!(
            err.contains(flag) && err.contains("out of range"),
            "{flag} {value}: {err}"
        );
    }
}

#[test]
fn reference_refuses_images_views_and_times_it_cannot_render() {
    let dir = tempfile::tempdir().unwrap();
    for args in [
        vec!["--width", "65536", "--height", "65537"],
        vec!["--width", "100000", "--height", "100000"],
        vec!["--time", "nan"],
        vec!["--camera", "0,1,3:0,1,3"],
        vec!["--camera", "0,1,3:0,1,0:0"],
        vec!["--camera", "0,1,3:0,1,0:180"],
        vec!["--camera", "nan,1,3:0,1,0"],
        vec!["--camera", "0,0,0:0,5,0"],
    ] {
        let out = cloudlight()
            .args(["reference", "cornell", "--spp", "1", "--out"])
            .arg(dir.path())
            .args(&args)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains("error:"), "{args:?}: {err}");
    }
}

#[test]
fn validate_refuses_device_files_and_scenes_a_run_could_not_load() {
    let dir = tempfile::tempdir().unwrap();
    // A device as the topology: refused without reading it.
    let out = cloudlight()
        .args(["validate", "/dev/zero"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("not a regular file"), "{err}");
    // A glTF whose buffer is a device.
    let gltf = dir.path().join("zero.gltf");
    std::fs::write(
        &gltf,
        r#"{"asset":{"version":"2.0"},"buffers":[{"uri":"/dev/zero","byteLength":1000000000000}]}"#,
    )
    .unwrap();
    // An unknown scene name, and that glTF, as a topology's scene.
    for (scene, words) in [
        ("no-such-scene".to_string(), "no-such-scene"),
        (gltf.display().to_string(), "not a regular file"),
    ] {
        let topo = dir.path().join("t.toml");
        std::fs::write(
            &topo,
            format!(
                "techniques = [\"probe\"]\nscene = \"{scene}\"\n[[node]]\nname = \"n\"\naddress = \"127.0.0.1:0\"\n"
            ),
        )
        .unwrap();
        let out = cloudlight().arg("validate").arg(&topo).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{scene}: {err}");
        assert!(
            err.contains(words) && err.contains("`scene`"),
            "{scene}: {err}"
        );
    }
}

#[test]
fn bench_video_prints_sdr_and_hdr_rows_beside_the_papers() {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("video.json");
    let out = cloudlight()
        .args([
            "bench",
            "video",
            "--small",
            "--frames",
            "4",
            "--hdr-size",
            "16",
            "--hdr-spp",
            "4",
            "--json",
        ])
        .arg(&json)
        .output()
        .unwrap();
    ok(&out);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("| 640x360 | 3.0 Mbit/s |") && text.contains("| QP 20 |"),
        "{text}"
    );
    assert!(
        text.contains("4.20") || text.contains("1.05"),
        "the paper's encode time: {text}"
    );
    let r = read_json(&json);
    assert_eq!(r["sdr"].as_array().unwrap().len(), 4);
    assert_eq!(r["hdr"].as_array().unwrap().len(), 4);
    for row in r["sdr"].as_array().unwrap() {
        assert!(row["psnr_y_db"].as_f64().unwrap() > 30.0, "{row}");
        assert!(row["encode_ms_p50"].as_f64().unwrap() > 0.0);
    }
}

#[test]
fn the_full_frame_baseline_streams_cloud_rendered_frames_to_thin_clients() {
    // photons-video.toml: the photon client renders in the cloud, its frames go to a video
    // encoder, and thin clients on their own nodes decode and show them.
    let dir = tempfile::tempdir().unwrap();
    // The cloud-side clients record too: a raster client's recording.
    let text = std::fs::read_to_string(example("photons-video.toml"))
        .unwrap()
        .replace(
            "params = { width = 320, height = 240, fps = 8.0 }",
            "params = { width = 320, height = 240, fps = 8.0, record = \"render.mp4\" }",
        );
    let topology = dir.path().join("photons-video.toml");
    std::fs::write(&topology, text).unwrap();
    let out = cloudlight()
        .arg("run")
        .arg(&topology)
        .args(["--duration", "3", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    ok(&out);
    let json = read_json(dir.path().join("metrics.json"));
    let stage = |name: &str| {
        json["stages"]
            .as_array()
            .unwrap()
            .iter()
            .find(|s| s["name"] == name)
            .unwrap_or_else(|| panic!("no stage {name}"))
            .clone()
    };
    for i in 0..2 {
        let enc = stage(&format!("encode[{i}]"))["report"].clone();
        assert!(enc["units"].as_u64().unwrap() >= 1, "{enc}");
        assert!(enc["key_frames"].as_u64().unwrap() >= 1, "{enc}");
        let viewer = stage(&format!("viewer[{i}]"))["report"].clone();
        assert!(
            viewer["decoder"]["pictures"].as_u64().unwrap() >= 1,
            "{viewer}"
        );
        assert_eq!(viewer["decoder"]["errors"], 0, "{viewer}");
        assert!(viewer["indirect_shown"].as_bool().unwrap(), "{viewer}");
        let pngs = std::fs::read_dir(dir.path().join(format!("viewer-{i}")))
            .unwrap()
            .filter(|e| {
                e.as_ref()
                    .unwrap()
                    .path()
                    .extension()
                    .is_some_and(|x| x == "png")
            })
            .count();
        assert!(pngs >= 1, "viewer[{i}] wrote its pictures");
        // Both recordings are MP4s that ffprobe reads frame by frame.
        for (stage_name, file) in [
            (format!("viewer[{i}]"), format!("viewer-{i}/viewer.mp4")),
            (format!("render[{i}]"), format!("render-{i}/render.mp4")),
        ] {
            let report = stage(&stage_name)["report"].clone();
            let frames = report["frames_recorded"].as_u64().unwrap();
            assert!(frames >= 1, "{report}");
            let Ok(probe) = std::process::Command::new("ffprobe")
                .args([
                    "-v",
                    "error",
                    "-count_frames",
                    "-show_entries",
                    "stream=nb_read_frames",
                ])
                .args(["-of", "csv=p=0"])
                .arg(dir.path().join(&file))
                .output()
            else {
                eprintln!("skipped: ffprobe is not installed (scripts/setup.sh installs it)");
                continue;
            };
            let read = String::from_utf8_lossy(&probe.stdout).trim().to_string();
            assert_eq!(
                read,
                frames.to_string(),
                "{file}: {}",
                String::from_utf8_lossy(&probe.stderr)
            );
        }
    }
}

#[test]
fn the_container_image_installs_the_packages_of_the_one_list_and_runs_cloudlight() {
    let dockerfile = std::fs::read_to_string("Dockerfile").unwrap();
    // No second list: packages come from scripts/setup.sh, by role.
    assert!(!dockerfile.contains("apt-get"), "{dockerfile}");
    assert!(dockerfile.contains("setup.sh build"), "{dockerfile}");
    assert!(dockerfile.contains("setup.sh runtime"), "{dockerfile}");
    assert!(
        dockerfile.contains("ENTRYPOINT [\"cloudlight\"]"),
        "{dockerfile}"
    );
    let list = |role: &str| {
        let out = std::process::Command::new("bash")
            .args(["scripts/setup.sh", "--list", role])
            .output()
            .unwrap();
        assert!(out.status.success());
        String::from_utf8(out.stdout)
            .unwrap()
            .split_whitespace()
            .map(String::from)
            .collect::<Vec<_>>()
    };
    let (runtime, build, all) = (list("runtime"), list("build"), list("all"));
    assert!(
        runtime.iter().any(|p| p == "mesa-vulkan-drivers"),
        "{runtime:?}"
    );
    assert!(
        !runtime.iter().any(|p| p == "nasm" || p == "ffmpeg"),
        "{runtime:?}"
    );
    assert!(runtime.iter().all(|p| build.contains(p)) && build.iter().all(|p| all.contains(p)));
    // The build context leaves out what is built or fetched.
    let ignore = std::fs::read_to_string(".dockerignore").unwrap();
    for path in ["target", ".git", "assets", "runs"] {
        assert!(ignore.lines().any(|l| l.trim() == path), "{ignore}");
    }
}

#[test]
fn bench_fronts_draws_saved_quality_runs_together_old_and_swept() {
    let dir = tempfile::tempdir().unwrap();
    let point = |photons: u64, mbps: f64, ms: f64, relmse: f64| {
        serde_json::json!({ "photons": photons, "mbps": mbps, "update_ms": ms,
            "errors": { "relmse": relmse } })
    };
    // A run from before the 8-byte packing (its rows hold 12- and 20-byte points) and a
    // sweep of today's (each variant's rows hold an 8-byte point).
    let before = serde_json::json!({ "technique": "photons", "scene": "cornell", "rows": [
        { "photons": 2500, "twelve": point(2500, 7.2, 3.0, 0.108), "twenty": point(2500, 12.0, 3.0, 0.107) },
        { "photons": 10000, "twelve": point(10000, 28.6, 5.0, 0.079), "twenty": point(10000, 47.0, 5.0, 0.078) },
        // Errors over orders of magnitude: drawn on a log axis.
        { "photons": 80000, "twelve": point(80000, 32.8, 31.3, 438.1) },
    ]});
    let after = serde_json::json!({ "technique": "photons", "scene": "cornell", "swept": ["window"],
    "variants": [
        { "label": "window=1", "rows": [{ "photons": 10000, "eight": point(10000, 6.5, 9.0, 0.0464) }] },
        { "label": "window=4", "rows": [{ "photons": 10000, "eight": point(10000, 6.5, 9.0, 0.0258) }] },
    ]});
    std::fs::create_dir_all(dir.path().join("old")).unwrap();
    let (b, a) = (
        dir.path().join("old/quality.json"),
        dir.path().join("new.json"),
    );
    std::fs::write(&b, before.to_string()).unwrap();
    std::fs::write(&a, after.to_string()).unwrap();
    // A moving light's runs, one per budget, under one label: one front, and one of what
    // the client shows with its window (the window's last row).
    let moving = |photons: u64, one: f64, four: f64| {
        serde_json::json!({ "technique": "photons", "scene": "cornell-animated",
            "rows": [{ "photons": photons, "eight": point(photons, photons as f64 / 1600.0, 9.0, one) }],
            "window": [{ "passes": 1, "errors": { "relmse": one } },
                       { "passes": 4, "errors": { "relmse": four } }] })
    };
    let (m1, m2) = (dir.path().join("m1.json"), dir.path().join("m2.json"));
    std::fs::write(&m1, moving(20000, 0.0387, 0.0185).to_string()).unwrap();
    std::fs::write(&m2, moving(10000, 0.0427, 0.0280).to_string()).unwrap();
    let png = dir.path().join("fronts.png");
    let out = cloudlight()
        .args(["bench", "fronts"])
        .arg(&b)
        .arg(format!("{}=after", a.display()))
        .arg(format!("{}=moving", m1.display()))
        .arg(format!("{}=moving", m2.display()))
        .arg("--out")
        .arg(&png)
        .output()
        .unwrap();
    ok(&out);
    let text = String::from_utf8_lossy(&out.stdout);
    for row in [
        "| old | 2500 | 7.20 | 3.00 | 0.1080 |",
        "| old | 10000 | 28.60 | 5.00 | 0.0790 |",
        "| old | 80000 | 32.80 | 31.30 | 438.1000 |",
        "| after: window=1 | 10000 | 6.50 | 9.00 | 0.0464 |",
        "| after: window=4 | 10000 | 6.50 | 9.00 | 0.0258 |",
        "| moving | 10000 | 6.25 | 9.00 | 0.0427 |\n| moving | 20000 | 12.50 | 9.00 | 0.0387 |",
        "| moving, window of 4 | 10000 | 6.25 | 9.00 | 0.0280 |\n| moving, window of 4 | 20000 | 12.50 | 9.00 | 0.0185 |",
    ] {
        assert!(text.contains(row), "{row} not in:\n{text}");
    }
    let image = image::open(&png).unwrap();
    assert!(image.width() > 400 && image.height() > 200);
    // What is not a photon quality run is refused, naming the file and the reason.
    let wrong = dir.path().join("wrong.json");
    std::fs::write(&wrong, r#"{ "technique": "irradiance", "rows": [] }"#).unwrap();
    let broken = dir.path().join("broken.json");
    std::fs::write(
        &broken,
        serde_json::json!({ "technique": "photons", "rows": [{ "eight": { "photons": 1, "errors": { "relmse": 0.1 } } }] })
            .to_string(),
    )
    .unwrap();
    for (file, says) in [
        (&wrong, "not \"photons\""),
        (&broken, "`mbps` is not a number"),
        (&dir.path().join("missing.json"), "reading"),
    ] {
        let out = cloudlight()
            .args(["bench", "fronts"])
            .arg(file)
            .arg("--out")
            .arg(dir.path().join("x.png"))
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            err.contains(&*file.to_string_lossy()) && err.contains(says),
            "{err}"
        );
    }
}
