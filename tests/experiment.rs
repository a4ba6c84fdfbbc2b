//! Placement experiments: the experiment file is validated like a topology (every problem at
//! once, each with file, line and key), and expands into one valid topology per run, with
//! each cut placing its stages where it says.

use std::path::Path;

use cloudlight::experiment::run::{self, RunSettings};
use cloudlight::experiment::{Experiment, cuts, report};
use cloudlight::runtime::Plan;

fn problems(text: &str) -> Vec<String> {
    match Experiment::parse("bad.toml", text, "bad") {
        Ok(e) => panic!("accepted a bad file: {e:?}"),
        Err(errors) => errors.0.iter().map(|d| d.to_string()).collect(),
    }
}

#[track_caller]
fn has(problems: &[String], words: &[&str]) {
    assert!(
        problems.iter().any(|p| words.iter().all(|w| p.contains(w))),
        "no problem mentioning {words:?} in:\n{}",
        problems.join("\n")
    );
}

#[test]
fn the_paper_cuts_expand_into_valid_topologies_that_place_each_cut_where_it_says() {
    let e = Experiment::load(std::path::Path::new("examples/experiments/paper-cuts.toml"))
        .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(e.links, ["home-wifi", "campus", "city"]);
    let runs = e.runs();
    assert_eq!(runs.len(), 27, "9 cuts × 3 links × 1 client count");
    let registry = cloudlight::actors::registry();
    for run in &runs {
        let spec = e
            .topology(run, None)
            .unwrap_or_else(|err| panic!("{}: {err:#}", run.id()));
        let plan = spec
            .plan(&format!("{}.toml", run.id()), &registry)
            .unwrap_or_else(|err| panic!("{}: {err}\n{}", run.id(), spec.to_toml()));
        // The link profile joins the cloud and the clients' node.
        let link = cloudlight::transport::LinkProfile::named(&run.link).unwrap();
        assert_eq!(
            plan.topology.link("cloud", "home"),
            Some(&link),
            "{}",
            run.id()
        );
        let on = |node: &str| {
            spec.stages
                .iter()
                .filter(|s| s.nodes.iter().any(|n| n == node))
                .count()
        };
        let kinds_home: Vec<&str> = spec
            .stages
            .iter()
            .filter(|s| s.nodes.iter().any(|n| n == "home"))
            .map(|s| s.kind.as_str())
            .collect();
        match run.cut.as_str() {
            // Nothing on the cloud: nothing crosses the network.
            "local" => assert_eq!(on("cloud"), 0, "{}", run.id()),
            // Thin clients: they decode video.
            "video" => assert_eq!(kinds_home, ["video_client"], "{}", run.id()),
            "cloud" => assert_eq!(kinds_home, ["photon_reconstructor"], "{}", run.id()),
            "h264" => assert_eq!(kinds_home, ["irradiance_reconstructor"], "{}", run.id()),
            "raw" => assert_eq!(kinds_home, ["irradiance_raw_reconstructor"], "{}", run.id()),
            "deltas" => assert_eq!(kinds_home, ["frame_renderer"], "{}", run.id()),
            other => panic!("unexpected cut {other}"),
        }
        if run.cut != "local" {
            assert!(on("cloud") > 0 && !kinds_home.is_empty(), "{}", run.id());
        }
        // Every client renders what it shows, samples it and records it.
        let client = spec.stages.iter().find(|s| s.name == "client").unwrap();
        for (key, value) in [
            ("render", toml::Value::Boolean(true)),
            (
                "sample_every_s",
                toml::Value::Float(e.measure.sample_every_s),
            ),
            ("record", toml::Value::String("client.mp4".into())),
        ] {
            assert_eq!(client.params.get(key), Some(&value), "{} {key}", run.id());
        }
    }
    // Every cut of every technique is in the example.
    for t in cuts::TECHNIQUES {
        for c in cuts::cuts(t).unwrap() {
            assert!(
                runs.iter().any(|r| r.technique == *t && r.cut == c.name),
                "{t} {}",
                c.name
            );
        }
    }
}

#[test]
fn added_latency_lengthens_each_link_by_it_and_names_its_runs() {
    let e = Experiment::load(std::path::Path::new("examples/experiments/latency.toml"))
        .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(e.extra_latency_ms, [0.0, 100.0, 250.0, 500.0, 1000.0]);
    let runs = e.runs();
    assert_eq!(runs.len(), 15, "3 cuts × 5 latencies");
    let registry = cloudlight::actors::registry();
    let campus = cloudlight::transport::LinkProfile::CAMPUS;
    for run in &runs {
        let plan = e
            .topology(run, None)
            .unwrap()
            .plan("t.toml", &registry)
            .unwrap();
        let link = plan.topology.link("cloud", "home").unwrap();
        assert_eq!(
            link.latency_ms,
            campus.latency_ms + f64::from(run.extra_latency_ms),
            "{}",
            run.id()
        );
        assert_eq!(link.bandwidth_mbps, campus.bandwidth_mbps);
    }
    let ids: Vec<String> = runs.iter().map(|r| r.id()).collect();
    assert!(
        ids.contains(&"photons-cloud-campus-1c".to_string()),
        "{ids:?}"
    );
    assert!(
        ids.contains(&"voxels-video-campus-1000ms-1c".to_string()),
        "{ids:?}"
    );
    let p = problems(
        "extra_latency_ms = [0, -5, 20000]\n[[technique]]\nname = \"photons\"\ncuts = [\"cloud\"]\n",
    );
    has(
        &p,
        &["bad.toml:1:", "`extra_latency_ms[1]`", "milliseconds"],
    );
    has(
        &p,
        &["bad.toml:1:", "`extra_latency_ms[2]`", "milliseconds"],
    );
    assert_eq!(p.len(), 2, "{}", p.join("\n"));
}

#[test]
fn bad_experiment_files_name_every_problem_with_its_line_and_key() {
    let text = r#"scene = "cornell"
colour = 3
clients = [1, -2]
links = ["campus", "moon"]
duration_s = 0
[[technique]]
name = "photons"
cuts = ["cloud", "deltas", "cloud"]
[[technique]]
name = "voxels"
cuts = ["h264"]
set = { max_depth = "deep" }
[[technique]]
name = "radiosity"
cuts = ["local"]
[[technique]]
name = "irradiance"
"#;
    let p = problems(text);
    has(&p, &["bad.toml:2:", "`colour`", "unknown key"]);
    has(&p, &["bad.toml:3:", "`clients[1]`"]);
    has(
        &p,
        &[
            "bad.toml:4:",
            "`links[1]`",
            "unknown link profile `moon`",
            "home-wifi",
        ],
    );
    has(&p, &["bad.toml:5:", "`duration_s`", "out of range"]);
    has(
        &p,
        &[
            "bad.toml:8:",
            "`technique[0].cuts[1]`",
            "`photons` has no cut `deltas`",
            "cloud, local, video",
        ],
    );
    has(
        &p,
        &["bad.toml:8:", "`technique[0].cuts[2]`", "named twice"],
    );
    has(
        &p,
        &[
            "bad.toml:11:",
            "`technique[1].cuts[0]`",
            "`voxels` has no cut `h264`",
            "video, deltas, local",
        ],
    );
    has(&p, &["bad.toml:12:", "`technique[1].set`", "max_depth"]);
    has(
        &p,
        &[
            "bad.toml:14:",
            "`technique[2].name`",
            "unknown technique `radiosity`",
        ],
    );
    has(
        &p,
        &[
            "`technique[3].cuts`",
            "name the cuts to try",
            "h264, raw, local",
        ],
    );
    assert_eq!(p.len(), 10, "{}", p.join("\n"));
    // The measurement settings.
    let p = problems(
        "width = 101\nfps = 0\nreference_spp = 0\n[[technique]]\nname = \"photons\"\ncuts = [\"cloud\"]\n",
    );
    has(&p, &["bad.toml:1:", "`width`", "even number of pixels"]);
    has(&p, &["bad.toml:2:", "`fps`", "out of range"]);
    has(&p, &["bad.toml:3:", "`reference_spp`", "out of range"]);
    assert_eq!(p.len(), 3, "{}", p.join("\n"));
    // Syntax, and a file without techniques.
    has(&problems("scene = \n"), &["bad.toml:1:", "invalid TOML"]);
    has(
        &problems("scene = \"cornell\"\n"),
        &["`technique`", "at least one"],
    );
}

#[test]
fn the_cli_emits_one_valid_topology_per_run_and_refuses_a_bad_file() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("small.toml");
    std::fs::write(
        &file,
        "clients = [1, 2]\nlinks = [\"city\", \"continental-3600km\"]\n[[technique]]\nname = \"voxels\"\ncuts = [\"deltas\"]\n",
    )
    .unwrap();
    let out = assert_cmd::Command::cargo_bin("cloudlight")
        .unwrap()
        .args(["experiment"])
        .arg(&file)
        .arg("--emit")
        .arg(dir.path().join("emitted"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let mut files: Vec<String> = std::fs::read_dir(dir.path().join("emitted"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    files.sort();
    assert_eq!(
        files,
        [
            "voxels-deltas-city-1c.toml",
            "voxels-deltas-city-2c.toml",
            "voxels-deltas-continental-3600km-1c.toml",
            "voxels-deltas-continental-3600km-2c.toml"
        ]
    );
    let registry = cloudlight::actors::registry();
    for f in &files {
        let path = dir.path().join("emitted").join(f);
        let plan = Plan::load(&path, &registry).unwrap_or_else(|e| panic!("{f}: {e}"));
        let renderers = plan
            .instances
            .iter()
            .filter(|i| i.kind == "frame_renderer")
            .count();
        assert_eq!(renderers, if f.ends_with("1c.toml") { 1 } else { 2 }, "{f}");
    }
    // A bad file: every problem, exit 2, nothing written.
    std::fs::write(&file, "links = [\"moon\"]\n").unwrap();
    let out = assert_cmd::Command::cargo_bin("cloudlight")
        .unwrap()
        .args(["experiment"])
        .arg(&file)
        .arg("--emit")
        .arg(dir.path().join("none"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("small.toml:1:") && err.contains("moon") && err.contains("technique"),
        "{err}"
    );
    assert!(!dir.path().join("none").exists());
}

/// A short experiment on the Cornell box: `scene`, the irradiance map as H.264 (and photons
/// when `photons`) over the campus link with `latencies` added, small frames and references.
fn short_experiment(scene: &str, duration_s: f64, latencies: &[u32], photons: bool) -> Experiment {
    let latencies: Vec<String> = latencies.iter().map(|l| l.to_string()).collect();
    let photons = if photons {
        "[[technique]]\nname = \"photons\"\ncuts = [\"cloud\"]\nset = { photons = 5000 }\n"
    } else {
        ""
    };
    let text = format!(
        "scene = \"{scene}\"\nduration_s = {duration_s}\nlinks = [\"campus\"]\nextra_latency_ms = [{}]\n\
         width = 128\nheight = 72\nreference_spp = 32\nsample_every_s = 0.5\nwarmup_s = 1.5\n\
         [[technique]]\nname = \"irradiance\"\ncuts = [\"h264\"]\n{photons}",
        latencies.join(", ")
    );
    Experiment::parse("short.toml", &text, "short").unwrap_or_else(|e| panic!("{e}"))
}

fn quiet() -> RunSettings {
    RunSettings {
        fresh: false,
        progress: false,
    }
}

/// ffprobe's count of the frames it decodes in `path` (`None` without ffprobe).
fn decoded_frames(path: &Path) -> Option<u64> {
    let out = std::process::Command::new("ffprobe")
        .args(["-v", "error", "-count_frames", "-show_entries"])
        .args(["stream=nb_read_frames", "-of", "csv=p=0"])
        .arg(path)
        .output()
        .ok()?;
    assert!(
        out.status.success(),
        "ffprobe {}: {}",
        path.display(),
        String::from_utf8_lossy(&out.stderr)
    );
    Some(
        String::from_utf8_lossy(&out.stdout)
            .trim()
            .parse()
            .unwrap_or_else(|e| panic!("{}: {e}", path.display())),
    )
}

#[test]
fn an_interrupted_experiment_resumes_without_rerunning_finished_runs_and_reports_what_it_measured()
{
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path();
    let e = short_experiment("cornell-animated", 3.0, &[0], true);
    let first = run::run(&e, out, &quiet()).unwrap();
    assert_eq!((first.ran, first.reused), (2, 0));
    for r in &first.results {
        assert!(r.ok(), "{r:?}");
        assert!(!r.samples.is_empty(), "{}: no sample compared", r.id);
        let e = r.relmse.unwrap();
        assert!(e.is_finite() && e > 0.0 && e < 1.0, "{}: relMSE {e}", r.id);
        let energy = r.energy_ratio.unwrap();
        assert!((0.7..1.3).contains(&energy), "{}: energy {energy}", r.id);
        assert!(r.fps > 5.0 && r.client_frame_ms_p50 > 0.0, "{r:?}");
        assert!(r.server_update_ms.is_some_and(|ms| ms > 0.0), "{r:?}");
        assert!(r.mbps_per_client > 0.0 && r.age_ms_p50 > 0.0, "{r:?}");
    }
    // Interrupted during the second run: its line never made it, and the process died
    // while writing a line.
    let results = out.join(run::RESULTS);
    let text = std::fs::read_to_string(&results).unwrap();
    let kept = text.lines().next().unwrap().to_string();
    std::fs::write(&results, format!("{kept}\n{{\"id\": \"irradi")).unwrap();
    let again = run::run(&e, out, &quiet()).unwrap();
    assert_eq!((again.ran, again.reused), (1, 1));
    let reused: run::RunResult = serde_json::from_str(&kept).unwrap();
    let same = again.results.iter().find(|r| r.id == reused.id).unwrap();
    assert_eq!(same, &reused, "the finished run was not run again");
    // A third time runs nothing.
    let third = run::run(&e, out, &quiet()).unwrap();
    assert_eq!((third.ran, third.reused), (0, 2));
    // A changed setting is a different run.
    let mut longer = e.clone();
    longer.duration_s = 2.5;
    assert_ne!(
        longer.fingerprint(&longer.runs()[0]).unwrap(),
        e.fingerprint(&e.runs()[0]).unwrap()
    );

    // The report: every file the page names exists, and every video decodes.
    let written = report::write(&e, &third.results, out).unwrap();
    let html = std::fs::read_to_string(&written.html).unwrap();
    let files = report::html_files(&html);
    assert!(
        files.iter().any(|f| f.ends_with("reference.mp4")),
        "{files:?}"
    );
    assert!(
        files.iter().filter(|f| f.ends_with("client.mp4")).count() >= 2,
        "{files:?}"
    );
    for f in &files {
        let path = out.join(f);
        assert!(path.is_file(), "report.html names {f}, which is missing");
        if f.ends_with(".mp4") {
            match decoded_frames(&path) {
                Some(n) => assert!(n >= 2, "{f}: {n} frames"),
                None => {
                    eprintln!("skipped: ffprobe is not installed (scripts/setup.sh installs it)")
                }
            }
        }
    }
    let md = std::fs::read_to_string(&written.markdown).unwrap();
    for words in [
        "## Link `campus`",
        "## Recommendation",
        "| campus | thin",
        "| campus | powerful",
    ] {
        assert!(md.contains(words), "report.md lacks {words:?}:\n{md}");
    }
    // A powerful client can run either cut; the one recommended has the least error.
    let powerful = written
        .recommendations
        .iter()
        .find(|r| r.client == cuts::ClientClass::Powerful)
        .unwrap();
    let least = third
        .results
        .iter()
        .filter_map(|r| r.relmse)
        .fold(f64::INFINITY, f64::min);
    assert_eq!(powerful.relmse, Some(least), "{powerful:?}");
    assert!(out.join("error-campus.png").is_file());
}

#[test]
fn error_grows_with_injected_latency_for_a_moving_light_and_stays_flat_for_a_static_one() {
    // Over the same sample moments (a longer link starts showing light later): relMSE with
    // 1 s added against none. Measured: moving 0.120 → 0.153, static 0.093 → 0.090.
    let growth = |scene: &str| {
        let dir = tempfile::tempdir().unwrap();
        let e = short_experiment(scene, 6.5, &[0, 1000], false);
        let outcome = run::run(&e, dir.path(), &quiet()).unwrap();
        let runs: Vec<&run::RunResult> = outcome.results.iter().collect();
        for r in &runs {
            assert!(r.ok(), "{r:?}");
        }
        let times = run::common_times(&runs);
        assert!(!times.is_empty(), "{scene}: no common sample: {runs:?}");
        let at = |i: usize| runs[i].relmse_at(&times).unwrap();
        (at(0), at(1))
    };
    let (moving_0, moving_1000) = growth("cornell-animated");
    let (static_0, static_1000) = growth("cornell");
    assert!(
        moving_1000 > 1.12 * moving_0,
        "a moving light: relMSE {moving_0:.3} without added latency, {moving_1000:.3} with 1 s"
    );
    assert!(
        (static_1000 - static_0).abs() < 0.1 * static_0,
        "a static light: relMSE {static_0:.3} without added latency, {static_1000:.3} with 1 s"
    );
}
