//! Kubernetes manifests generated from every example topology: valid against Kubernetes' schemas
//! (PyPI's kubernetes-validate, offline, installed by scripts/setup.sh), and consistent with
//! each other: every peer's address is a pod of a Service the same files define, on the port
//! the pod binds, with the secret and the topology wired in.

use std::path::{Path, PathBuf};

use cloudlight::deploy;
use serde_json::Value;

/// The Kubernetes version the manifests are checked against.
const KUBERNETES: &str = "1.33.0";

fn validator() -> Option<PathBuf> {
    let venv = std::env::var_os("CLOUDLIGHT_VENV")
        .map(PathBuf::from)
        .or_else(|| {
            std::env::var_os("HOME").map(|h| Path::new(&h).join(".cache/cloudlight/venv"))
        })?;
    let tool = venv.join("bin/kubernetes-validate");
    tool.is_file().then_some(tool)
}

#[test]
fn manifests_of_every_example_topology_are_valid_and_wired_together() {
    let registry = cloudlight::actors::registry();
    let tool = validator();
    if tool.is_none() {
        eprintln!(
            "skipped the schema check: kubernetes-validate is not installed (scripts/setup.sh installs it)"
        );
    }
    let mut examples: Vec<PathBuf> = std::fs::read_dir("examples/topologies")
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    examples.sort();
    assert!(examples.len() >= 5);
    for example in &examples {
        let dir = tempfile::tempdir().unwrap();
        let plan = cloudlight::runtime::Plan::load(example, &registry).unwrap();
        let options = deploy::Options {
            image: "registry.example/cloudlight:test".into(),
            namespace: "lights".into(),
        };
        let d = deploy::kubernetes(&plan, example, &options, dir.path())
            .unwrap_or_else(|e| panic!("{}: {e:#}", example.display()));
        let what = example.display().to_string();
        if let Some(tool) = &tool {
            let out = std::process::Command::new(tool)
                .args(["--strict", "-k", KUBERNETES])
                .args(&d.files)
                .output()
                .unwrap();
            assert!(
                out.status.success(),
                "{what}: {}{}",
                String::from_utf8_lossy(&out.stdout),
                String::from_utf8_lossy(&out.stderr)
            );
        }
        let objects: Vec<Value> = d
            .files
            .iter()
            .map(|f| serde_json::from_slice(&std::fs::read(f).unwrap()).unwrap())
            .collect();
        let of_kind = |kind: &'static str| objects.iter().filter(move |o| o["kind"] == kind);
        let config = of_kind("ConfigMap").next().unwrap();
        let secret = of_kind("Secret").next().unwrap();
        assert!(
            secret["stringData"]["secret"]
                .as_str()
                .is_some_and(|s| !s.is_empty())
        );
        // The topology the pods run is valid (the secret stands in for the environment's),
        // and every node's address is its pod in its Service, on the port it binds.
        let topology = config["data"]["topology.toml"].as_str().unwrap();
        assert_eq!(topology, d.topology);
        assert!(
            topology.contains("secret_env = \"CLOUDLIGHT_SECRET\""),
            "{what}"
        );
        let deployed = cloudlight::runtime::Plan::from_str(
            "topology.toml",
            &topology.replace("secret_env = \"CLOUDLIGHT_SECRET\"", "secret = \"x\""),
            &registry,
        )
        .unwrap_or_else(|e| panic!("{what}: {e}"));
        assert_eq!(deployed.topology.nodes.len(), plan.topology.nodes.len());
        for node in &deployed.topology.nodes {
            let host = node.host.as_deref().expect("a DNS name");
            let port = node.address.port();
            let (pod, rest) = host.split_once('.').unwrap();
            let (service_name, domain) = rest.split_once('.').unwrap();
            assert_eq!(domain, "lights.svc.cluster.local", "{what}");
            assert_eq!(pod, format!("{service_name}-0"), "{what}");
            assert_eq!(node.bind, Some(format!("0.0.0.0:{port}").parse().unwrap()));
            let service = of_kind("Service")
                .find(|s| s["metadata"]["name"] == service_name)
                .unwrap_or_else(|| panic!("{what}: no Service `{service_name}`"));
            assert_eq!(service["spec"]["clusterIP"], "None");
            let ports = service["spec"]["ports"].as_array().unwrap();
            assert!(
                ports
                    .iter()
                    .any(|p| p["protocol"] == "UDP" && p["port"] == port)
            );
            let set = of_kind("StatefulSet")
                .find(|s| s["spec"]["serviceName"] == service_name)
                .unwrap_or_else(|| panic!("{what}: no StatefulSet of `{service_name}`"));
            assert_eq!(set["spec"]["replicas"], 1);
            // The selector picks this node's pod, and the Service selects the same labels.
            let pod_labels = &set["spec"]["template"]["metadata"]["labels"];
            for (k, v) in service["spec"]["selector"].as_object().unwrap() {
                assert_eq!(&pod_labels[k], v, "{what}: selector {k}");
            }
            let c = &set["spec"]["template"]["spec"]["containers"][0];
            let args: Vec<&str> = c["args"]
                .as_array()
                .unwrap()
                .iter()
                .map(|a| a.as_str().unwrap())
                .collect();
            let after = |flag: &str| args[args.iter().position(|a| *a == flag).unwrap() + 1];
            assert_eq!(after("--node"), node.name);
            assert_eq!(after("--bind"), format!("0.0.0.0:{port}"));
            let metrics: u16 = after("--metrics-listen")
                .rsplit(':')
                .next()
                .unwrap()
                .parse()
                .unwrap();
            assert_eq!(c["readinessProbe"]["httpGet"]["port"], metrics);
            assert_eq!(c["readinessProbe"]["httpGet"]["path"], "/healthz");
            assert!(
                ports
                    .iter()
                    .any(|p| p["protocol"] == "TCP" && p["port"] == metrics)
            );
            let annotations = &set["spec"]["template"]["metadata"]["annotations"];
            assert_eq!(annotations["prometheus.io/port"], metrics.to_string());
            // The secret and the topology are the ones these files define.
            let env = &c["env"][0];
            assert_eq!(env["name"], "CLOUDLIGHT_SECRET");
            assert_eq!(
                env["valueFrom"]["secretKeyRef"]["name"],
                secret["metadata"]["name"]
            );
            assert_eq!(env["valueFrom"]["secretKeyRef"]["key"], "secret");
            let volume = &set["spec"]["template"]["spec"]["volumes"][0];
            assert_eq!(volume["configMap"]["name"], config["metadata"]["name"]);
            assert_eq!(
                after(args[0]),
                format!(
                    "{}/topology.toml",
                    c["volumeMounts"][0]["mountPath"].as_str().unwrap()
                )
            );
            assert!(
                c["resources"]["requests"]["memory"]
                    .as_str()
                    .is_some_and(|m| m.ends_with("Mi"))
            );
        }
        assert!(dir.path().join("README.md").is_file());
    }
}

#[test]
fn requests_follow_what_the_stages_hold() {
    let scene = cloudlight::scenes::load("cornell").unwrap();
    let city = cloudlight::scenes::load("city:20000").unwrap();
    let table = |text: &str| -> toml::Table { toml::from_str(text).unwrap() };
    let f = |kind: &str, params: &str, scene: &cloudlight::scenes::Scene| {
        deploy::footprint(kind, &table(params), None, scene)
    };
    // More photons per iteration, more memory; a bigger scene, more memory for every stage.
    let few = f("photon_batcher", "photons = 10000", &scene);
    let many = f("photon_batcher", "photons = 1000000", &scene);
    assert!(many.bytes > few.bytes + 50_000_000, "{few:?} {many:?}");
    assert!(f("probe_relay", "", &city).bytes > f("probe_relay", "", &scene).bytes);
    // A deeper octree holds more voxels, within the stage's budget.
    let shallow = f("light_injector", "max_depth = 5", &scene);
    let deep = f("light_injector", "max_depth = 9", &scene);
    let capped = f("light_injector", "max_depth = 9\nbudget_mb = 1.0", &scene);
    assert!(
        deep.bytes > shallow.bytes + 50_000_000,
        "{shallow:?} {deep:?}"
    );
    assert!(capped.bytes < shallow.bytes + (2 << 20), "{capped:?}");
    // Rendering stages hold a device; the probe takes a tenth of a core.
    assert!(f("photon_reconstructor", "", &scene).bytes > 100 << 20);
    assert_eq!(f("probe_sink", "", &scene).cpu_m, 100);
    assert_eq!(f("cone_tracer", "", &scene).cpu_m, 1000);
}
