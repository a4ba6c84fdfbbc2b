//! Kubernetes manifests from a topology: per node a headless Service and a one-replica
//! StatefulSet running `cloudlight node`, the topology (with the pods' stable DNS names as
//! addresses) in a ConfigMap, the secret in a Secret read through `secret_env`.
//!
//! Manifests are written as JSON (which `kubectl apply -f` and every YAML reader take), one
//! object per file, so that nothing here writes YAML by hand.

use std::path::{Path, PathBuf};

use anyhow::Context;
use cloudlight_runtime::Plan;
use serde_json::{Value, json};

/// Port the metrics endpoint listens on in every pod.
pub const METRICS_PORT: u16 = 9100;
/// First transport port given to nodes whose address has port 0.
pub const FIRST_PORT: u16 = 7200;
/// The environment variable the pods read the secret from.
pub const SECRET_ENV: &str = "CLOUDLIGHT_SECRET";
/// Where the topology is mounted in the pods.
const TOPOLOGY_DIR: &str = "/etc/cloudlight";

/// What to generate.
#[derive(Clone, Debug)]
pub struct Options {
    /// Container image.
    pub image: String,
    /// Namespace.
    pub namespace: String,
}

/// One node as deployed.
#[derive(Clone, Debug, PartialEq)]
pub struct DeployedNode {
    /// Its name in the topology.
    pub node: String,
    /// Its Service and StatefulSet name (a DNS label).
    pub name: String,
    /// Its UDP port.
    pub port: u16,
    /// The address its peers dial: the pod's stable DNS name.
    pub address: String,
}

/// What was written.
#[derive(Clone, Debug)]
pub struct Deployment {
    /// The nodes.
    pub nodes: Vec<DeployedNode>,
    /// Every file, in the order to apply them.
    pub files: Vec<PathBuf>,
    /// The topology as the pods run it.
    pub topology: String,
}

/// `name` as a DNS-1123 label: lower case, `a-z0-9-`, at most 63 bytes, starting and ending
/// with a letter or digit.
pub fn dns_label(name: &str) -> String {
    let mut s: String = name
        .to_ascii_lowercase()
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '-' })
        .collect();
    s.truncate(63);
    let s = s.trim_matches('-').to_string();
    if s.is_empty() { "node".into() } else { s }
}

/// What a node's pod requests: CPU in millicores and memory in bytes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Footprint {
    /// CPU, millicores.
    pub cpu_m: u64,
    /// Memory, bytes.
    pub bytes: u64,
}

// Calibrated on the example topologies, each node run alone (`cloudlight node`, release
// build, 8-10 s, maximum resident set): photons-cloud's cloud 22 MiB and clients 152 MiB;
// irradiance-cloud's cloud 25 MiB and clients 149 MiB; voxels-split's gi node (three voxel
// stages, depth 6) 78 MiB and clients 219 MiB.

/// The process itself (runtime, transport, tokio, allocator slack).
const PROCESS_BYTES: u64 = 24 << 20;
/// A stage that computes lighting or encodes: its threads' buffers and scratch.
const COMPUTE_BYTES: u64 = 16 << 20;
/// Every stage instance loads the scene: mesh, BVH and per-triangle data.
const BYTES_PER_TRIANGLE: u64 = 512;
/// A stage that renders holds a software GPU device (lavapipe) and its frame buffers.
const RENDER_DEVICE_BYTES: u64 = 128 << 20;
/// A photon as the batcher holds it (record, packed copy, the previous generation).
const BYTES_PER_TRACED_PHOTON: u64 = 96;
/// A photon as a client holds it (packed, plus its splat instance).
const BYTES_PER_HELD_PHOTON: u64 = 32;
/// A light-map texel (irradiance RGB in f32, the blend's history, the f16 or H.264 copy).
const BYTES_PER_TEXEL: u64 = 64;

/// What one stage instance of `kind` with `params` needs on `scene`, from `plan`'s estimates
/// for that scene (photons per iteration, occupied voxels at the stage's depth — its own
/// `max_depth`, else `voxel_depth`, the light injector's — light-map texels), with the
/// per-item sizes above; CPU is a whole core for a stage that computes lighting, encodes or
/// renders, a tenth of one for the rest.
pub fn footprint(
    kind: &str,
    params: &toml::Table,
    voxel_depth: Option<u64>,
    scene: &cloudlight_scenes::Scene,
) -> Footprint {
    use cloudlight_render::plan::{PlanSettings, plan};
    let int = |key: &str| {
        params
            .get(key)
            .and_then(|v| v.as_integer())
            .map(|v| v.max(0) as u64)
    };
    let float = |key: &str| params.get(key).and_then(|v| v.as_float());
    let scene_bytes = scene.triangle_count() as u64 * BYTES_PER_TRIANGLE;
    let photons = || match (float("photons_per_watt"), int("photons")) {
        (Some(per_watt), _) => {
            let settings = PlanSettings {
                photons_per_watt: Some(per_watt),
                ..PlanSettings::default()
            };
            plan(scene, &settings)
                .lights
                .iter()
                .map(|l| l.photons)
                .sum()
        }
        (None, Some(n)) => n,
        (None, None) => cloudlight_render::photon::DEFAULT_PHOTONS,
    };
    let voxels = || {
        let settings = PlanSettings {
            octree_levels: int("max_depth").or(voxel_depth).unwrap_or(9) as u32,
            ..PlanSettings::default()
        };
        let all: u64 = plan(scene, &settings).voxels_per_level.iter().sum();
        let bytes = all * cloudlight_render::voxel::BYTES_PER_VOXEL;
        float("budget_mb").map_or(bytes, |mb| bytes.min((mb * 1048576.0) as u64))
    };
    let texels = || plan(scene, &PlanSettings::default()).lightmap_texels * BYTES_PER_TEXEL;
    let (cpu_m, own) = match kind {
        "photon_batcher" => (1000, COMPUTE_BYTES + photons() * BYTES_PER_TRACED_PHOTON),
        "photon_reconstructor" => (
            1000,
            RENDER_DEVICE_BYTES + photons() * BYTES_PER_HELD_PHOTON,
        ),
        "light_injector" | "octree_filter" | "cone_tracer" => (1000, COMPUTE_BYTES + voxels()),
        // Cone tracing per pixel over its own octree: the device and twice the compute.
        "frame_renderer" => (1000, RENDER_DEVICE_BYTES + 4 * COMPUTE_BYTES + voxels()),
        "basis_gatherer" => (1000, COMPUTE_BYTES + texels()),
        "irradiance_reconstructor" | "irradiance_raw_reconstructor" => {
            (1000, RENDER_DEVICE_BYTES + texels())
        }
        "video_encoder" => (1000, COMPUTE_BYTES),
        "video_client" => (500, RENDER_DEVICE_BYTES),
        _ => (100, 8 << 20),
    };
    Footprint {
        cpu_m,
        bytes: scene_bytes + own,
    }
}

/// What node `node` requests: the process, each stage instance's [`footprint`], and the bytes
/// its queues may hold where the messages' size is known ([`cloudlight_runtime::topology`]'s
/// per-edge bound; edges of unknown size are bounded by `max_bytes` but reserve nothing).
pub fn node_footprint(
    plan: &Plan,
    node: &str,
    scene: Option<&cloudlight_scenes::Scene>,
) -> Footprint {
    let mut total = Footprint {
        cpu_m: 0,
        bytes: PROCESS_BYTES,
    };
    // The octree's depth, where stages downstream of the injector do not say it.
    let voxel_depth = plan
        .topology
        .stages
        .iter()
        .filter(|s| s.kind == "light_injector")
        .find_map(|s| s.params.get("max_depth").and_then(|v| v.as_integer()))
        .map(|d| d.max(0) as u64);
    for i in plan.instances.iter().filter(|i| i.node == node) {
        let stage = plan.topology.stage(&i.stage).expect("planned stages exist");
        let f = match scene {
            Some(s) => footprint(&i.kind, &stage.params, voxel_depth, s),
            None => Footprint {
                cpu_m: 250,
                bytes: 32 << 20,
            },
        };
        total.cpu_m += f.cpu_m;
        total.bytes += f.bytes;
    }
    total.bytes += plan
        .edges
        .iter()
        .filter(|e| plan.instances[e.from].node == node && e.bytes_bound < e.max_bytes)
        .map(|e| e.bytes_bound)
        .sum::<u64>();
    total.cpu_m = total.cpu_m.max(100);
    total
}

/// Writes the manifests of the topology in `plan` (read from `file`) into `out`.
pub fn kubernetes(
    plan: &Plan,
    file: &Path,
    options: &Options,
    out: &Path,
) -> anyhow::Result<Deployment> {
    let t = &plan.topology;
    let namespace = dns_label(&options.namespace);
    let cluster = dns_label(&t.cluster);
    let mut nodes = Vec::new();
    for (i, n) in t.nodes.iter().enumerate() {
        let name = dns_label(&format!("{cluster}-{}", n.name));
        if let Some(other) = nodes.iter().find(|d: &&DeployedNode| d.name == name) {
            anyhow::bail!(
                "nodes `{}` and `{}` would share the Kubernetes name `{name}`: rename one",
                other.node,
                n.name
            );
        }
        let port = match n.address.port() {
            0 => FIRST_PORT + i as u16,
            p => p,
        };
        nodes.push(DeployedNode {
            node: n.name.clone(),
            address: format!("{name}-0.{name}.{namespace}.svc.cluster.local:{port}"),
            name,
            port,
        });
    }
    // The topology the pods run: the same file, the nodes at their pods' names, the secret
    // from the environment.
    let text =
        std::fs::read_to_string(file).with_context(|| format!("reading {}", file.display()))?;
    let mut doc: toml::Table =
        toml::from_str(&text).with_context(|| format!("reading {}", file.display()))?;
    let secret = if t.secret.is_empty() {
        cloudlight_transport::crypto::random_secret()
    } else {
        t.secret.clone()
    };
    // A pod runs until stopped (a run that ended would be restarted by its StatefulSet).
    for key in ["secret", "secret_file", "insecure", "duration_s"] {
        doc.remove(key);
    }
    doc.insert("secret_env".into(), SECRET_ENV.into());
    if let Some(toml::Value::Array(tables)) = doc.get_mut("node") {
        for table in tables.iter_mut() {
            let Some(table) = table.as_table_mut() else {
                continue;
            };
            let name = table
                .get("name")
                .and_then(|v| v.as_str())
                .unwrap_or("")
                .to_string();
            if let Some(d) = nodes.iter().find(|d| d.node == name) {
                table.insert("address".into(), d.address.clone().into());
                table.insert("bind".into(), format!("0.0.0.0:{}", d.port).into());
            }
        }
    }
    let topology = format!(
        "# {} as deployed by `cloudlight deploy kubernetes`: nodes at their pods' DNS names,\n# the secret from ${SECRET_ENV}, no duration (a pod runs until stopped).\n{}",
        file.display(),
        toml::to_string(&doc)?
    );
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let mut files = Vec::new();
    let mut write = |name: &str, value: Value| -> anyhow::Result<()> {
        let path = out.join(name);
        std::fs::write(&path, serde_json::to_string_pretty(&value)? + "\n")
            .with_context(|| format!("writing {}", path.display()))?;
        files.push(path);
        Ok(())
    };
    let labels = |name: &str| json!({ "app.kubernetes.io/name": "cloudlight", "app.kubernetes.io/instance": cluster, "cloudlight/node": name });
    let config = format!("{cluster}-topology");
    let secret_name = format!("{cluster}-secret");
    write(
        "00-configmap.json",
        json!({
            "apiVersion": "v1", "kind": "ConfigMap",
            "metadata": { "name": config, "namespace": namespace, "labels": labels("") },
            "data": { "topology.toml": topology },
        }),
    )?;
    write(
        "01-secret.json",
        json!({
            "apiVersion": "v1", "kind": "Secret", "type": "Opaque",
            "metadata": { "name": secret_name, "namespace": namespace, "labels": labels("") },
            "stringData": { "secret": secret },
        }),
    )?;
    let scene = cloudlight_scenes::load(&t.scene).ok();
    let triangles = scene.as_ref().map_or(0, |s| s.triangle_count());
    for d in &nodes {
        let need = node_footprint(plan, &d.node, scene.as_ref());
        let args = [
            "node".to_string(),
            format!("{TOPOLOGY_DIR}/topology.toml"),
            "--node".into(),
            d.node.clone(),
            "--bind".into(),
            format!("0.0.0.0:{}", d.port),
            "--metrics-listen".into(),
            format!("0.0.0.0:{METRICS_PORT}"),
            "--out".into(),
            "/tmp/cloudlight-run".into(),
        ];
        write(
            &format!("10-service-{}.json", d.name),
            json!({
                "apiVersion": "v1", "kind": "Service",
                "metadata": { "name": d.name, "namespace": namespace, "labels": labels(&d.node) },
                "spec": {
                    "clusterIP": "None",
                    "publishNotReadyAddresses": true,
                    "selector": { "cloudlight/node": d.node, "app.kubernetes.io/instance": cluster },
                    "ports": [
                        { "name": "transport", "protocol": "UDP", "port": d.port, "targetPort": d.port },
                        { "name": "metrics", "protocol": "TCP", "port": METRICS_PORT, "targetPort": METRICS_PORT },
                    ],
                },
            }),
        )?;
        write(
            &format!("20-statefulset-{}.json", d.name),
            json!({
                "apiVersion": "apps/v1", "kind": "StatefulSet",
                "metadata": { "name": d.name, "namespace": namespace, "labels": labels(&d.node) },
                "spec": {
                    "serviceName": d.name,
                    "replicas": 1,
                    "selector": { "matchLabels": { "cloudlight/node": d.node, "app.kubernetes.io/instance": cluster } },
                    "template": {
                        "metadata": {
                            "labels": labels(&d.node),
                            "annotations": {
                                "prometheus.io/scrape": "true",
                                "prometheus.io/port": METRICS_PORT.to_string(),
                                "prometheus.io/path": "/metrics",
                            },
                        },
                        "spec": {
                            "containers": [{
                                "name": "cloudlight",
                                "image": options.image,
                                "args": args,
                                "env": [{
                                    "name": SECRET_ENV,
                                    "valueFrom": { "secretKeyRef": { "name": secret_name, "key": "secret" } },
                                }],
                                "ports": [
                                    { "name": "transport", "containerPort": d.port, "protocol": "UDP" },
                                    { "name": "metrics", "containerPort": METRICS_PORT, "protocol": "TCP" },
                                ],
                                "readinessProbe": {
                                    "httpGet": { "path": "/healthz", "port": METRICS_PORT },
                                    "periodSeconds": 5,
                                    "failureThreshold": 2,
                                },
                                "resources": {
                                    "requests": {
                                        "cpu": format!("{}m", need.cpu_m),
                                        "memory": format!("{}Mi", need.bytes.div_ceil(1 << 20)),
                                    },
                                },
                                "volumeMounts": [{ "name": "topology", "mountPath": TOPOLOGY_DIR, "readOnly": true }],
                            }],
                            "volumes": [{ "name": "topology", "configMap": { "name": config } }],
                        },
                    },
                },
            }),
        )?;
    }
    let listing: Vec<String> = nodes
        .iter()
        .map(|d| {
            format!(
                "- `10-service-{n}.json`, `20-statefulset-{n}.json`: node `{}` ({} stage instances), UDP {} at `{}`, metrics on TCP {METRICS_PORT}",
                d.node,
                plan.instances.iter().filter(|i| i.node == d.node).count(),
                d.port,
                d.address,
                n = d.name
            )
        })
        .collect();
    let readme = format!(
        "# `{}` on Kubernetes\n\nGenerated by `cloudlight deploy kubernetes` from `{}`.\n\n\
         ```sh\nkubectl create namespace {namespace}   # once\nkubectl apply -f .\n```\n\n\
         - `00-configmap.json`: the topology the pods run (`topology.toml`), each node at its pod's stable DNS name, \
         listening on `0.0.0.0`, the secret read from `${SECRET_ENV}`.\n\
         - `01-secret.json`: the cluster's secret (from the topology, or drawn at random when it had none). Keep it \
         out of version control, or replace it with your own Secret of the same name and key `secret`.\n{}\n\n\
         Each StatefulSet runs one pod, `cloudlight node ... --node NAME --bind 0.0.0.0:PORT --metrics-listen \
         0.0.0.0:{METRICS_PORT}`; its headless Service gives the pod the DNS name its peers dial. Readiness is \
         `/healthz` (ready while the run is running and every peer is up); Prometheus scrapes `/metrics` (annotations \
         `prometheus.io/*`). Requests come from what `cloudlight plan` estimates for the scene ({triangles} \
         triangles) and each stage's parameters: per stage instance the scene (512 bytes a triangle: mesh, BVH, \
         per-triangle data) and its own working set (photons per iteration, occupied voxels at its depth within its \
         `budget_mb`, light-map texels, a software GPU device of 128 MiB for stages that render; calibrated on the examples' measured memory), plus 24 MiB for \
         the process and what its queues may hold where message sizes are known; a whole core for a stage that \
         computes lighting, encodes or renders, a tenth of one for the rest.\n",
        t.cluster,
        file.display(),
        listing.join("\n")
    );
    let readme_path = out.join("README.md");
    std::fs::write(&readme_path, readme)
        .with_context(|| format!("writing {}", readme_path.display()))?;
    Ok(Deployment {
        nodes,
        files,
        topology,
    })
}
