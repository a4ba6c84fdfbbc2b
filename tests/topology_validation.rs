//! Topology files: every malformed file is rejected with every problem named by file, line
//! and key; valid files expand into the expected instances and edges.

use cloudlight::runtime::{Diagnostic, EdgeSettings, Plan, Policy, StageKind, StageRegistry};

const GOOD_HEAD: &str = r#"techniques = ["probe"]
[[node]]
name = "cloud"
address = "127.0.0.1:7300"
[[node]]
name = "client"
address = "127.0.0.1:7301"
"#;

fn registry() -> StageRegistry {
    let mut r = cloudlight::actors::registry();
    // A kind that takes another message type, to check type mismatches.
    r.register(
        StageKind::new("float_sink", "probe", "takes f32", |_| {
            anyhow::bail!("not built in these tests")
        })
        .input(
            cloudlight::runtime::Port::<f32>::new("in"),
            EdgeSettings {
                capacity: 1,
                policy: Policy::Latest,
            },
        ),
    );
    r
}

fn diagnostics(text: &str) -> Vec<Diagnostic> {
    match Plan::from_str("bad.toml", text, &registry()) {
        Ok(_) => panic!("accepted a malformed file:\n{text}"),
        Err(e) => e.0,
    }
}

/// Asserts that one diagnostic has this line and key and mentions `words`.
#[track_caller]
fn expect(diags: &[Diagnostic], line: usize, key: &str, words: &str) {
    assert!(
        diags.iter().any(|d| d.file == "bad.toml"
            && d.line == line
            && d.key == key
            && d.message.contains(words)),
        "no diagnostic at line {line} for `{key}` mentioning {words:?}; got:\n{}",
        diags
            .iter()
            .map(|d| d.to_string())
            .collect::<Vec<_>>()
            .join("\n")
    );
}

#[test]
fn unknown_top_level_key() {
    let d = diagnostics(&format!("colour = 3\n{GOOD_HEAD}"));
    expect(&d, 1, "colour", "unknown key");
    // After a table header, keys belong to that table.
    let d = diagnostics(&format!("{GOOD_HEAD}colour = 3\n"));
    expect(
        &d,
        8,
        "node[1].colour",
        "unknown key (expected one of: name, address, bind)",
    );
}

#[test]
fn unknown_key_in_a_stage() {
    let d = diagnostics(&format!(
        "{GOOD_HEAD}[[stage]]\nname = \"s\"\nkind = \"probe_sink\"\nnode = \"cloud\"\nnodee = \"x\"\n"
    ));
    expect(&d, 12, "stage[0].nodee", "unknown key");
}

#[test]
fn unknown_node() {
    let d = diagnostics(&format!(
        "{GOOD_HEAD}[[stage]]\nname = \"s\"\nkind = \"probe_source\"\nnode = \"mars\"\n"
    ));
    expect(&d, 11, "stage[0].node", "unknown node `mars`");
}

#[test]
fn unplaced_stage() {
    let d = diagnostics(&format!(
        "{GOOD_HEAD}[[stage]]\nname = \"s\"\nkind = \"probe_source\"\n"
    ));
    expect(&d, 8, "stage[0].node", "not placed");
}

#[test]
fn bad_addresses() {
    let d = diagnostics(
        "techniques = [\"probe\"]\n[[node]]\nname = \"a\"\naddress = \"127.0.0.1\"\n[[node]]\nname = \"b\"\naddress = \"localhost:99999\"\n",
    );
    expect(&d, 4, "node[0].address", "not an IP:port");
    expect(&d, 7, "node[1].address", "not an IP:port");
}

#[test]
fn zero_capacity() {
    let d = diagnostics(&format!(
        "{GOOD_HEAD}[[stage]]\nname = \"a\"\nkind = \"probe_source\"\nnode = \"cloud\"\n[[stage]]\nname = \"b\"\nkind = \"probe_sink\"\nnode = \"cloud\"\n[[edge]]\nfrom = \"a\"\nto = \"b\"\ncapacity = 0\n"
    ));
    expect(&d, 19, "edge[0].capacity", "must be in [1,");
}

#[test]
fn negative_latency_and_loss_out_of_range() {
    let d = diagnostics(&format!(
        "{GOOD_HEAD}[[link]]\nbetween = [\"cloud\", \"client\"]\nlatency_ms = -5\nloss = 1.5\n"
    ));
    expect(&d, 10, "link[0].latency_ms", "must be in [0, 60000] ms");
    expect(&d, 11, "link[0].loss", "in [0, 1]");
}

#[test]
fn zero_replicas() {
    let d = diagnostics(&format!(
        "{GOOD_HEAD}[[stage]]\nname = \"s\"\nkind = \"probe_sink\"\nnode = \"client\"\nreplicas = 0\n"
    ));
    expect(&d, 12, "stage[0].replicas", "must be in [1,");
}

#[test]
fn duplicate_names() {
    let d = diagnostics(&format!(
        "{GOOD_HEAD}[[node]]\nname = \"cloud\"\naddress = \"127.0.0.1:7302\"\n[[stage]]\nname = \"s\"\nkind = \"probe_source\"\nnode = \"cloud\"\n[[stage]]\nname = \"s\"\nkind = \"probe_source\"\nnode = \"cloud\"\n"
    ));
    expect(&d, 9, "node[2].name", "duplicate node name");
    expect(&d, 16, "stage[1].name", "duplicate stage name");
}

#[test]
fn duplicate_address() {
    let d = diagnostics(
        "techniques = [\"probe\"]\n[[node]]\nname = \"a\"\naddress = \"127.0.0.1:9\"\n[[node]]\nname = \"b\"\naddress = \"127.0.0.1:9\"\n",
    );
    expect(&d, 7, "node[1].address", "already used by node `a`");
    // Two nodes of one host listening on one port: `b` binds every interface on a's port.
    let d = diagnostics(
        "techniques = [\"probe\"]\n[[node]]\nname = \"a\"\naddress = \"127.0.0.1:7400\"\n[[node]]\nname = \"b\"\naddress = \"127.0.0.1:7401\"\nbind = \"0.0.0.0:7400\"\n",
    );
    expect(
        &d,
        8,
        "node[1].bind",
        "port 7400 of host 127.0.0.1, as node `a` does",
    );
    // On two hosts, or on two ports, both may bind every interface.
    let r = registry();
    for (a, b) in [
        ("10.0.0.1:7400", "10.0.0.2:7400"),
        ("127.0.0.1:7400", "127.0.0.1:7401"),
    ] {
        let text = format!(
            "techniques = [\"probe\"]\n[[node]]\nname = \"a\"\naddress = \"{a}\"\nbind = \"0.0.0.0:{}\"\n[[node]]\nname = \"b\"\naddress = \"{b}\"\nbind = \"0.0.0.0:{}\"\n",
            &a[a.len() - 4..],
            &b[b.len() - 4..]
        );
        Plan::from_str("ok.toml", &text, &r).unwrap_or_else(|e| panic!("{e}"));
    }
}

#[test]
fn unknown_kind_and_technique() {
    let d = diagnostics(
        "techniques = [\"photonz\"]\n[[node]]\nname = \"a\"\naddress = \"127.0.0.1:0\"\n[[stage]]\nname = \"s\"\nkind = \"photon_batcherr\"\nnode = \"a\"\n",
    );
    expect(&d, 1, "techniques", "unknown technique `photonz`");
    expect(
        &d,
        5,
        "stage[0].kind",
        "unknown stage kind `photon_batcherr`",
    );
}

#[test]
fn wrong_value_types_and_bad_policy() {
    let d = diagnostics(&format!(
        "seed = \"one\"\n{GOOD_HEAD}[[stage]]\nname = \"a\"\nkind = \"probe_source\"\nnode = \"cloud\"\n[[stage]]\nname = \"b\"\nkind = \"probe_sink\"\nnode = \"cloud\"\n[[edge]]\nfrom = \"a\"\nto = \"b\"\ncapacity = \"four\"\npolicy = \"newest\"\n"
    ));
    expect(&d, 1, "seed", "expected an integer");
    expect(&d, 20, "edge[0].capacity", "expected an integer");
    expect(&d, 21, "edge[0].policy", "unknown policy `newest`");
}

#[test]
fn syntax_error_names_its_line() {
    let d = diagnostics(&format!("{GOOD_HEAD}[[stage]\nname = \"s\"\n"));
    expect(&d, 8, "<syntax>", "invalid TOML");
}

#[test]
fn unknown_ports_stages_and_type_mismatch() {
    let d = diagnostics(&format!(
        "{GOOD_HEAD}[[stage]]\nname = \"a\"\nkind = \"probe_source\"\nnode = \"cloud\"\n[[stage]]\nname = \"f\"\nkind = \"float_sink\"\nnode = \"client\"\n\
         [[edge]]\nfrom = \"a.output\"\nto = \"f\"\n[[edge]]\nfrom = \"a\"\nto = \"f\"\n[[edge]]\nfrom = \"a\"\nto = \"ghost\"\n"
    ));
    expect(&d, 16, "edge[0].from", "no output port `output`");
    expect(&d, 19, "edge[1]", "takes f32");
    expect(&d, 24, "edge[2].to", "unknown stage `ghost`");
}

#[test]
fn bad_params_and_replica_mismatch() {
    let d = diagnostics(&format!(
        "{GOOD_HEAD}[[stage]]\nname = \"a\"\nkind = \"probe_source\"\nnode = \"cloud\"\nreplicas = 2\nparams = {{ rate = 3 }}\n\
         [[stage]]\nname = \"b\"\nkind = \"probe_sink\"\nnodes = [\"client\", \"client\", \"cloud\"]\n[[edge]]\nfrom = \"a\"\nto = \"b\"\n"
    ));
    expect(&d, 8, "stage[0].params", "unknown field `rate`");
    expect(&d, 18, "edge[0]", "cannot join 2 replicas");
}

#[test]
fn every_problem_of_a_file_is_reported_at_once() {
    let text = r#"techniques = ["probe"]
speed = 2
[[node]]
name = "cloud"
address = "nowhere"
[[stage]]
name = "a"
kind = "probe_source"
node = "moon"
[[stage]]
name = "b"
kind = "probe_sink"
node = "cloud"
replicas = 0
[[link]]
between = ["cloud", "cloud"]
latency_ms = -1
"#;
    let d = diagnostics(text);
    expect(&d, 2, "speed", "unknown key");
    expect(&d, 5, "node[0].address", "not an IP:port");
    expect(&d, 9, "stage[0].node", "unknown node `moon`");
    expect(&d, 14, "stage[1].replicas", "must be in [1,");
    expect(&d, 17, "link[0].latency_ms", "must be in [0,");
    assert!(d.len() >= 5);
    let shown = cloudlight::runtime::TopologyErrors(d).to_string();
    assert!(
        shown.starts_with("bad.toml:2:1: `speed`: unknown key"),
        "{shown}"
    );
}

#[test]
fn example_topologies_are_valid_and_expand_as_declared() {
    let reg = cloudlight::actors::registry();
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/topologies");
    let mut seen = 0;
    for entry in std::fs::read_dir(&root).unwrap() {
        let path = entry.unwrap().path();
        Plan::load(&path, &reg).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        seen += 1;
    }
    assert!(seen >= 2);
    let plan = Plan::load(&root.join("probe-cluster.toml"), &reg).unwrap();
    let names: Vec<_> = plan.instances.iter().map(|i| i.name.as_str()).collect();
    assert_eq!(names, ["source", "relay", "client[0]", "client[1]"]);
    assert_eq!(plan.edges.len(), 3);
    assert!(plan.edges.iter().all(|e| e.cut));
    let last = &plan.edges[2];
    assert_eq!(last.name, "relay.out -> client[1].in");
    assert_eq!(
        last.settings,
        EdgeSettings {
            capacity: 2,
            policy: Policy::Latest
        }
    );
    assert_eq!(
        plan.edges[0].settings,
        EdgeSettings {
            capacity: 8,
            policy: Policy::Block
        }
    );
    let link = plan.topology.link("home", "edge").unwrap();
    assert_eq!(
        (link.latency_ms, link.bandwidth_mbps, link.loss),
        (20.0, Some(50.0), 0.01)
    );
    assert!(plan.summary().contains("CUT edge -> home"));
}

#[test]
fn the_default_topology_uses_the_one_campus_link_of_the_benchmarks() {
    let reg = cloudlight::actors::registry();
    let plan = Plan::from_str(
        cloudlight::DEFAULT_TOPOLOGY_NAME,
        cloudlight::DEFAULT_TOPOLOGY,
        &reg,
    )
    .unwrap();
    assert!(!plan.topology.links.is_empty());
    for l in &plan.topology.links {
        assert_eq!(
            l.profile,
            cloudlight::transport::LinkProfile::CAMPUS,
            "{} -> {}",
            l.from,
            l.to
        );
    }
}

#[test]
fn a_benchmark_topology_is_planned_like_a_file() {
    use cloudlight::bench::photons::{PhotonOptions, Photons};
    use cloudlight::bench::{ClusterOptions, cluster_topology};
    let reg = cloudlight::actors::registry();
    let cluster = ClusterOptions {
        scene: "cornell".into(),
        seconds: 1.0,
        link: Some(cloudlight::transport::LinkProfile::CAMPUS),
        seed: 3,
    };
    let spec = cluster_topology::<Photons>(&PhotonOptions::default(), &cluster, 3).unwrap();
    let plan = spec.plan("<bench>", &reg).unwrap_or_else(|e| panic!("{e}"));
    let names: Vec<_> = plan.instances.iter().map(|i| i.name.as_str()).collect();
    assert_eq!(names, ["server", "client[0]", "client[1]", "client[2]"]);
    assert!(plan.edges.iter().all(|e| e.cut));
    assert_eq!(
        plan.topology.link("cloud", "home"),
        Some(&cloudlight::transport::LinkProfile::CAMPUS)
    );
    // The text it writes is a topology file of its own.
    let again = Plan::from_str("<again>", &spec.to_toml(), &reg).unwrap();
    assert_eq!(again.instances.len(), 4);
}

const CUT: &str = "[[stage]]\nname = \"a\"\nkind = \"probe_source\"\nnode = \"cloud\"\n[[stage]]\nname = \"b\"\nkind = \"probe_sink\"\nnode = \"client\"\n[[edge]]\nfrom = \"a\"\nto = \"b\"\n";

#[test]
fn cut_edges_without_a_secret_are_warned_about_and_a_lone_node_refuses_to_start() {
    let r = registry();
    let warnings = |text: &str| {
        Plan::from_str("ok.toml", text, &r)
            .unwrap_or_else(|e| panic!("{e}"))
            .warnings
            .iter()
            .map(|w| w.to_string())
            .collect::<Vec<_>>()
            .join("\n")
    };
    // `run` draws one; `node` needs one: valid, with a warning that says so.
    let w = warnings(&format!("{GOOD_HEAD}{CUT}"));
    assert!(w.contains("no secret") && w.contains("secret_env"), "{w}");
    assert!(!warnings(&format!("insecure = true\n{GOOD_HEAD}{CUT}")).contains("secret"));
    let mine = warnings(&format!("secret = \"9f2e4d61c0b3a857\"\n{GOOD_HEAD}{CUT}"));
    assert!(!mine.contains("secret"), "{mine}");
    // A secret from the documentation is one anyone can use.
    for example in ["change me", "Change-Me", "secret", "password"] {
        let w = warnings(&format!("secret = \"{example}\"\n{GOOD_HEAD}{CUT}"));
        assert!(
            w.contains("ok.toml:1:10: `secret`") && w.contains("well-known example"),
            "{example}: {w}"
        );
        if example != "secret" {
            assert!(!w.contains(example), "the secret is printed: {w}");
        }
    }
    // Without a cut edge nothing crosses the network: no secret needed.
    let local = CUT.replace("node = \"client\"", "node = \"cloud\"");
    assert!(warnings(&format!("{GOOD_HEAD}{local}")).is_empty());

    // A node on its own refuses to start without one; the whole topology in one process
    // draws one and runs.
    let plan = Plan::from_str("ok.toml", &format!("{GOOD_HEAD}{CUT}"), &r).unwrap();
    let rt = tokio::runtime::Runtime::new().unwrap();
    let alone = cloudlight::runtime::RunOptions {
        only_node: Some("client".into()),
        duration: Some(std::time::Duration::from_millis(300)),
        ..Default::default()
    };
    let err = rt
        .block_on(cloudlight::runtime::run(
            &plan,
            &r,
            alone,
            std::future::pending(),
        ))
        .unwrap_err();
    assert!(
        matches!(err, cloudlight::runtime::RunError::NoSecret(ref n) if n == "client"),
        "{err}"
    );
    let dir = tempfile::tempdir().unwrap();
    let whole = cloudlight::runtime::RunOptions {
        duration: Some(std::time::Duration::from_millis(500)),
        out_dir: Some(dir.path().to_path_buf()),
        ..Default::default()
    };
    let report = rt
        .block_on(cloudlight::runtime::run(
            &plan,
            &r,
            whole,
            std::future::pending(),
        ))
        .unwrap_or_else(|e| panic!("{e}"));
    let sink = report
        .metrics
        .stages
        .iter()
        .find(|s| s.name == "b")
        .unwrap();
    assert!(sink.handled > 0, "{sink:?}");
}

#[test]
fn pacing_below_a_bit_per_second_is_refused() {
    let d = diagnostics(&format!("[transport]\npacing_mbps = 1e-300\n{GOOD_HEAD}"));
    expect(&d, 2, "transport.pacing_mbps", "must be");
}

#[test]
fn every_node_must_agree_on_the_digest_and_any_change_alters_it() {
    let r = registry();
    let base = format!("secret = \"x\"\n{GOOD_HEAD}{CUT}");
    let digest = |t: &str| Plan::from_str("d.toml", t, &r).unwrap().digest();
    assert_eq!(digest(&base), digest(&base));
    assert_ne!(digest(&base), digest(&format!("{base}capacity = 9\n")));
    assert_ne!(digest(&base), digest(&base.replace("7301", "7302")));
    assert_ne!(digest(&base), digest(&format!("seed = 4\n{base}")));
    // Secrets are not part of it (they prove membership; a wrong one is a stranger).
    assert_eq!(digest(&base), digest(&base.replace("\"x\"", "\"y\"")));
}

#[test]
fn numbers_that_cannot_be_held_or_converted_are_refused_with_their_range() {
    for (text, line, key) in [
        ("duration_s = 1e300\n", 1, "duration_s"),
        ("duration_s = -3\n", 1, "duration_s"),
        ("time_scale = 1e300\n", 1, "time_scale"),
        ("scene_start_s = 1e300\n", 1, "scene_start_s"),
        (
            "[transport]\npeer_timeout_ms = 1e300\n",
            2,
            "transport.peer_timeout_ms",
        ),
        (
            "[transport]\nheartbeat_ms = 1e-300\n",
            2,
            "transport.heartbeat_ms",
        ),
        (
            "[transport]\nconnect_timeout_s = 1e300\n",
            2,
            "transport.connect_timeout_s",
        ),
        (
            "[transport]\nstall_timeout_s = 0\n",
            2,
            "transport.stall_timeout_s",
        ),
        (
            "[defaults]\ncapacity = 9223372036854775807\n",
            2,
            "defaults.capacity",
        ),
        (
            "[transport]\npacing_mbps = 1e300\n",
            2,
            "transport.pacing_mbps",
        ),
    ] {
        let d = diagnostics(&format!("{text}{GOOD_HEAD}"));
        expect(&d, line, key, "out of range");
    }
    let d = diagnostics(&format!(
        "{GOOD_HEAD}[[stage]]\nname = \"s\"\nkind = \"probe_sink\"\nnode = \"client\"\nreplicas = 1000000000\n"
    ));
    expect(&d, 12, "stage[0].replicas", "out of range");
}

#[test]
fn link_delays_and_rates_the_emulator_cannot_hold_are_refused() {
    for (value, key) in [
        ("latency_ms = 1e300", "latency_ms"),
        ("jitter_ms = 1e300", "jitter_ms"),
        ("latency_ms = -0.5", "latency_ms"),
        ("bandwidth_mbps = 1e-300", "bandwidth_mbps"),
        ("bandwidth_mbps = 1e300", "bandwidth_mbps"),
        ("duplicate = 2.0", "duplicate"),
        ("reorder = nan", "reorder"),
    ] {
        let d = diagnostics(&format!(
            "{GOOD_HEAD}[[link]]\nbetween = [\"cloud\", \"client\"]\n{value}\n"
        ));
        assert_eq!(d.len(), 1, "{value}: {d:?}");
        let words = if value.contains("nan") {
            ""
        } else {
            "out of range"
        };
        expect(&d, 10, &format!("link[0].{key}"), words);
    }
}

#[test]
fn node_names_longer_than_the_handshake_carries_are_refused() {
    let long = "n".repeat(256);
    let d = diagnostics(&format!(
        "{GOOD_HEAD}[[node]]\nname = \"{long}\"\naddress = \"127.0.0.1:7302\"\n"
    ));
    expect(&d, 9, "node[2].name", "1 to 255");
}

#[test]
fn many_replicas_plan_without_a_quadratic_check() {
    // 10,000 replicas fan out from one source: 10,000 edges, each checked for duplicates.
    let text = format!(
        "secret = \"x\"\n{GOOD_HEAD}[[stage]]\nname = \"a\"\nkind = \"probe_source\"\nnode = \"cloud\"\n[[stage]]\nname = \"b\"\nkind = \"probe_sink\"\nnode = \"client\"\nreplicas = 10000\n[[edge]]\nfrom = \"a\"\nto = \"b\"\n"
    );
    let plan = Plan::from_str("many.toml", &text, &registry()).unwrap();
    assert_eq!(plan.edges.len(), 10_000);
}

#[test]
fn cycles_of_block_edges_are_refused_and_latest_cycles_allowed() {
    let stages = "[[stage]]\nname = \"a\"\nkind = \"probe_relay\"\nnode = \"cloud\"\n[[stage]]\nname = \"b\"\nkind = \"probe_relay\"\nnode = \"cloud\"\n";
    let cycle = |policy: &str| {
        format!(
            "{GOOD_HEAD}{stages}[[edge]]\nfrom = \"a\"\nto = \"b\"\npolicy = \"{policy}\"\n[[edge]]\nfrom = \"b\"\nto = \"a\"\npolicy = \"latest\"\n"
        )
    };
    let d = diagnostics(&cycle("block"));
    expect(&d, 16, "edge[0]", "cycle");
    assert_eq!(d.len(), 1, "only the block edge is named: {d:?}");
    assert!(Plan::from_str("ok.toml", &cycle("latest"), &registry()).is_ok());
    let self_loop =
        format!("{GOOD_HEAD}{stages}[[edge]]\nfrom = \"a\"\nto = \"a\"\npolicy = \"block\"\n");
    expect(&diagnostics(&self_loop), 16, "edge[0]", "cycle");
}

#[test]
fn stage_parameters_out_of_range_are_refused_by_name() {
    let stage = |kind: &str, params: &str| {
        format!(
            "{}[[stage]]\nname = \"s\"\nkind = \"{kind}\"\nnode = \"cloud\"\nparams = {{ {params} }}\n",
            GOOD_HEAD.replace("[\"probe\"]", "[\"probe\", \"photons\"]")
        )
    };
    for (kind, params, words) in [
        ("probe_source", "rate_hz = 1e-300", "rate_hz"),
        ("probe_source", "rate_hz = nan", "rate_hz"),
        (
            "probe_source",
            "payload_bytes = 3000000000",
            "payload_bytes",
        ),
        // The transport's limit itself: the message's envelope would push it over.
        ("probe_source", "payload_bytes = 67108864", "payload_bytes"),
        ("probe_relay", "work_ms = inf", "work_ms"),
        ("probe_sink", "work_ms = -1.0", "work_ms"),
        ("photon_batcher", "resend_s = 1e300", "resend_s"),
        (
            "photon_batcher",
            "photons_per_watt = -1.0",
            "photons_per_watt",
        ),
        (
            "photon_batcher",
            "photons_per_watt = nan",
            "photons_per_watt",
        ),
        ("photon_batcher", "radius_m = -1.0", "radius_m"),
        (
            "photon_batcher",
            "photons_per_disk = 0.0",
            "photons_per_disk",
        ),
        ("photon_batcher", "photons = 1000000000000", "photons"),
        ("photon_reconstructor", "fps = 0.0", "fps"),
        ("photon_reconstructor", "fps = inf", "fps"),
        ("photon_reconstructor", "width = 100000", "width"),
        ("photon_reconstructor", "shadow_size = 0", "shadow_size"),
        ("photon_reconstructor", "write_every = 0", "write_every"),
    ] {
        let d = diagnostics(&stage(kind, params));
        expect(&d, 8, "stage[0].params", words);
        assert!(
            d.iter().any(|x| x.message.contains("out of range")),
            "{kind} {params}: {d:?}"
        );
    }
}

#[test]
fn one_bad_node_address_is_one_error_not_a_cascade() {
    let text = GOOD_HEAD.replace("127.0.0.1:7300", "local_host:7300");
    let d = diagnostics(&format!(
        "secret = \"x\"\n{text}{CUT}[[link]]\nbetween = [\"cloud\", \"client\"]\nlatency_ms = 5\n"
    ));
    assert_eq!(d.len(), 1, "{d:?}");
    expect(&d, 5, "node[0].address", "not an IP:port");
}

#[test]
fn node_addresses_are_ip_or_host_names_with_ports() {
    for (address, ok) in [
        ("gi-node.lan:7300", true),
        ("localhost:7300", true),
        ("[::1]:7300", true),
        ("localhost", false),
        ("localhost:99999", false),
        ("local_host:7300", false),
        ("-bad.lan:7300", false),
        ("127.0.0.300:7300", false),
        ("a..b:7300", false),
    ] {
        let text = GOOD_HEAD.replace("127.0.0.1:7300", address);
        match Plan::from_str("bad.toml", &text, &registry()) {
            Ok(_) => assert!(ok, "{address} accepted"),
            Err(e) => {
                assert!(!ok, "{address}: {e}");
                assert_eq!(e.0.len(), 1, "{address}: {e}");
                expect(&e.0, 4, "node[0].address", "not an IP:port or host:port");
            }
        }
    }
}

#[test]
fn a_node_list_longer_than_the_replica_limit_is_refused() {
    let nodes = vec!["\"cloud\""; 10_001].join(",");
    let d = diagnostics(&format!(
        "{GOOD_HEAD}[[stage]]\nname = \"s\"\nkind = \"probe_sink\"\nnodes = [{nodes}]\n"
    ));
    expect(&d, 8, "stage[0].nodes", "at most 10000");
}

#[test]
fn links_may_name_a_profile_and_override_its_figures() {
    use cloudlight::transport::LinkProfile;
    // Every named profile: its figures, both directions.
    for (name, profile) in LinkProfile::NAMED {
        let text = format!(
            "{GOOD_HEAD}[[link]]\nbetween = [\"cloud\", \"client\"]\nprofile = \"{name}\"\n"
        );
        let plan =
            Plan::from_str("good.toml", &text, &registry()).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            plan.topology.link("cloud", "client"),
            Some(&profile),
            "{name}"
        );
        assert_eq!(
            plan.topology.link("client", "cloud"),
            Some(&profile),
            "{name}"
        );
    }
    // Keys beside the profile override its figures; the rest stay.
    let text = format!(
        "{GOOD_HEAD}[[link]]\nfrom = \"cloud\"\nto = \"client\"\nprofile = \"continental-3600km\"\nlatency_ms = 500\n"
    );
    let plan = Plan::from_str("good.toml", &text, &registry()).unwrap_or_else(|e| panic!("{e}"));
    let link = plan.topology.link("cloud", "client").unwrap();
    assert_eq!(link.latency_ms, 500.0);
    assert_eq!(
        link.bandwidth_mbps,
        LinkProfile::CONTINENTAL_3600KM.bandwidth_mbps
    );
    assert_eq!(link.loss, LinkProfile::CONTINENTAL_3600KM.loss);
    // An unknown profile names its line and key and lists the known ones, beside the
    // file's other problems.
    let d = diagnostics(&format!(
        "{GOOD_HEAD}[[link]]\nbetween = [\"cloud\", \"client\"]\nprofile = \"moon\"\nloss = 2\n"
    ));
    expect(&d, 10, "link[0].profile", "unknown link profile `moon`");
    expect(&d, 10, "link[0].profile", "home-wifi, campus, city");
    expect(&d, 11, "link[0].loss", "");
    // The profiles get slower and farther in the order the paper lists its networks.
    let latencies: Vec<f64> = LinkProfile::NAMED
        .iter()
        .map(|(_, p)| p.latency_ms)
        .collect();
    assert!(latencies.windows(2).all(|w| w[0] < w[1]), "{latencies:?}");
}

#[test]
fn the_secret_comes_from_the_file_an_environment_variable_or_a_file_and_is_never_printed() {
    let registry = cloudlight::actors::registry();
    let dir = tempfile::tempdir().unwrap();
    let body = "[[node]]\nname = \"a\"\naddress = \"127.0.0.1:0\"\n[[stage]]\nname = \"s\"\nkind = \"probe_source\"\nnode = \"a\"\n";
    let topo = |first: &str| format!("techniques = [\"probe\"]\n{first}\n{body}");
    // From a file beside the topology (one trailing line break dropped).
    std::fs::write(dir.path().join("cluster.secret"), "from-a-file\n").unwrap();
    let path = dir.path().join("t.toml");
    std::fs::write(&path, topo("secret_file = \"cluster.secret\"")).unwrap();
    let plan = cloudlight::runtime::Plan::load(&path, &registry).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(plan.topology.secret, "from-a-file");
    let summary = plan.summary();
    assert!(
        summary.contains("secret: file `")
            && summary.contains("cluster.secret` (`secret_file`), 11 bytes"),
        "{summary}"
    );
    assert!(!summary.contains("from-a-file"), "{summary}");
    // From an environment variable (one every process has; the multi-process test sets its
    // own in the nodes' environment).
    let plan =
        cloudlight::runtime::Plan::from_str("t.toml", &topo("secret_env = \"PATH\""), &registry)
            .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(plan.topology.secret, std::env::var("PATH").unwrap());
    let summary = plan.summary();
    assert!(
        summary.contains("secret: environment variable `PATH` (`secret_env`)"),
        "{summary}"
    );
    assert!(!summary.contains(&plan.topology.secret), "{summary}");
    // Problems, each at its line and key: an unset variable, a missing file, two sources,
    // an empty secret.
    let problems = |first: &str| {
        cloudlight::runtime::Plan::from_str("t.toml", &topo(first), &registry)
            .err()
            .map(|e| e.to_string())
            .unwrap_or_else(|| panic!("accepted {first}"))
    };
    let e = problems("secret_env = \"CLOUDLIGHT_NO_SUCH_VARIABLE\"");
    assert!(
        e.contains("t.toml:2:")
            && e.contains("`secret_env`")
            && e.contains("CLOUDLIGHT_NO_SUCH_VARIABLE` is not set"),
        "{e}"
    );
    let e = problems("secret_file = \"/nonexistent/cluster.secret\"");
    assert!(
        e.contains("t.toml:2:") && e.contains("`secret_file`") && e.contains("cannot read"),
        "{e}"
    );
    let e = problems("secret = \"x\"\nsecret_env = \"PATH\"");
    assert!(
        e.contains("t.toml:3:") && e.contains("already given by `secret`"),
        "{e}"
    );
    let e = problems("secret = \"\"");
    assert!(e.contains("t.toml:2:") && e.contains("is empty"), "{e}");
    // A bind address is an IP and a port.
    let e = cloudlight::runtime::Plan::from_str(
        "t.toml",
        &topo("secret = \"x\"").replace(
            "address = \"127.0.0.1:0\"",
            "address = \"127.0.0.1:0\"\nbind = \"anywhere:7200\"",
        ),
        &registry,
    )
    .err()
    .unwrap()
    .to_string();
    assert!(
        e.contains("t.toml:6:") && e.contains("`node[0].bind`") && e.contains("IP:port"),
        "{e}"
    );
}
