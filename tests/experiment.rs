//! Placement experiments: the experiment file is validated like a topology (every problem at
//! once, each with file, line and key), and expands into one valid topology per run, with
//! each cut placing its stages where it says.

use cloudlight::experiment::{Experiment, cuts};
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
            .topology(run)
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
        let plan = e.topology(run).unwrap().plan("t.toml", &registry).unwrap();
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
