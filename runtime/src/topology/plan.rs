//! [`Topology`] + [`StageRegistry`] → [`Plan`]: stage kinds, ports and message types are
//! checked, replicas are expanded into instances, and every edge declaration becomes one
//! edge per pair of joined instances, with its capacity, policy and whether it is cut.

use std::collections::{BTreeMap, HashSet};
use std::fmt::Write as _;
use std::path::Path;

use super::{Diagnostic, Topology, TopologyErrors, parse};
use crate::edge::{EdgeSettings, Policy};
use crate::message::MessageType;
use crate::stage::StageRegistry;

/// One stage instance (a replica of a stage declaration) placed on a node.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct InstancePlan {
    /// `stage` or `stage[i]`.
    pub name: String,
    /// Stage declaration name.
    pub stage: String,
    /// Stage kind.
    pub kind: String,
    /// Node it runs on.
    pub node: String,
    /// Replica index.
    pub replica: usize,
    /// Replica count of the stage.
    pub replicas: usize,
}

/// One edge between two instances.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct EdgePlan {
    /// `producer.port -> consumer.port`.
    pub name: String,
    /// Producer instance (index into [`Plan::instances`]).
    pub from: usize,
    /// Producer output port.
    pub from_port: &'static str,
    /// Consumer instance.
    pub to: usize,
    /// Consumer input port.
    pub to_port: &'static str,
    /// Capacity and policy.
    pub settings: EdgeSettings,
    /// Most bytes of encoded messages it holds (queued, being handled, in flight).
    pub max_bytes: u64,
    /// What it may hold at most: `max_bytes`, or less when the producer's message size is
    /// known (capacity × size).
    pub bytes_bound: u64,
    /// Payload type.
    pub ty: MessageType,
    /// Whether producer and consumer are on different nodes.
    pub cut: bool,
}

/// A checked topology, expanded into instances and edges.
#[derive(Clone, Debug)]
pub struct Plan {
    /// The topology it came from.
    pub topology: Topology,
    /// Every stage instance.
    pub instances: Vec<InstancePlan>,
    /// Every edge.
    pub edges: Vec<EdgePlan>,
    /// Things that are allowed but probably unintended (e.g. an unconnected input).
    pub warnings: Vec<Diagnostic>,
}

/// For each edge, whether it lies on a cycle of the instance graph (both ends in one strongly
/// connected component, a self-loop included); Kosaraju's algorithm, iterative.
fn on_cycle(edges: &[EdgePlan], n: usize) -> Vec<bool> {
    let mut out_adj = vec![Vec::new(); n];
    let mut in_adj = vec![Vec::new(); n];
    for e in edges {
        out_adj[e.from].push(e.to);
        in_adj[e.to].push(e.from);
    }
    // Finishing order of a depth-first search over the edges.
    let mut order = Vec::with_capacity(n);
    let mut seen = vec![false; n];
    for root in 0..n {
        if seen[root] {
            continue;
        }
        seen[root] = true;
        let mut stack = vec![(root, 0usize)];
        while let Some((v, i)) = stack.pop() {
            if let Some(&w) = out_adj[v].get(i) {
                stack.push((v, i + 1));
                if !seen[w] {
                    seen[w] = true;
                    stack.push((w, 0));
                }
            } else {
                order.push(v);
            }
        }
    }
    // Components over the reversed edges, in reverse finishing order.
    let mut comp = vec![usize::MAX; n];
    for (c, &root) in order.iter().rev().enumerate() {
        if comp[root] != usize::MAX {
            continue;
        }
        comp[root] = c;
        let mut stack = vec![root];
        while let Some(v) = stack.pop() {
            for &w in &in_adj[v] {
                if comp[w] == usize::MAX {
                    comp[w] = c;
                    stack.push(w);
                }
            }
        }
    }
    edges.iter().map(|e| comp[e.from] == comp[e.to]).collect()
}

fn instance_name(stage: &str, replica: usize, replicas: usize) -> String {
    if replicas == 1 {
        stage.to_string()
    } else {
        format!("{stage}[{replica}]")
    }
}

impl Plan {
    /// Reads, parses and plans a topology file, reporting every problem of both phases.
    pub fn load(path: &Path, registry: &StageRegistry) -> Result<Plan, TopologyErrors> {
        let file = path.display().to_string();
        let text = super::read_topology(path)?;
        Self::from_str(&file, &text, registry)
    }

    /// Parses and plans topology text named `file`.
    pub fn from_str(
        file: &str,
        text: &str,
        registry: &StageRegistry,
    ) -> Result<Plan, TopologyErrors> {
        let (topology, mut diags) = parse::parse(file, text);
        if diags.iter().any(|d| d.key == "<syntax>") {
            return Err(TopologyErrors(diags));
        }
        match Self::build(topology, registry) {
            Ok(plan) if diags.is_empty() => Ok(plan),
            Ok(_) => Err(TopologyErrors(diags)),
            Err(TopologyErrors(more)) => {
                diags.extend(more);
                diags.sort_by_key(|d| (d.line, d.column));
                Err(TopologyErrors(diags))
            }
        }
    }

    /// Checks every stage's parameters against the loaded scene ([`StageKind::check_scene`](crate::StageKind::check_scene)),
    /// each problem naming file:line:key.
    pub fn check_scene(
        &self,
        registry: &StageRegistry,
        scene: &crate::stage::AnyScene,
    ) -> Result<(), TopologyErrors> {
        let map = &self.topology.source;
        let errors: Vec<Diagnostic> = self
            .topology
            .stages
            .iter()
            .filter_map(|s| {
                let kind = registry.get(&s.kind)?;
                let e = kind.check_scene(&s.params, scene).err()?;
                Some(map.diag(&s.span, &format!("{}.params", s.key), e))
            })
            .collect();
        if errors.is_empty() {
            Ok(())
        } else {
            Err(TopologyErrors(errors))
        }
    }

    /// Checks a parsed topology against the stage kinds and expands it.
    pub fn build(topology: Topology, registry: &StageRegistry) -> Result<Plan, TopologyErrors> {
        let map = topology.source.clone();
        let mut errors = Vec::new();
        let mut warnings = Vec::new();
        let known_techniques: HashSet<&str> =
            registry.kinds().map(|k| k.technique.as_str()).collect();
        for t in &topology.techniques {
            if !known_techniques.contains(t.as_str()) {
                let mut list: Vec<_> = known_techniques.iter().copied().collect();
                list.sort();
                errors.push(map.diag(
                    &topology.techniques_span,
                    "techniques",
                    format!("unknown technique `{t}` (known: {})", list.join(", ")),
                ));
            }
        }

        // Instances, with kind and parameter checks.
        let mut instances = Vec::new();
        let mut first_instance = BTreeMap::new();
        for s in &topology.stages {
            let Some(kind) = registry.get(&s.kind) else {
                let list: Vec<_> = registry.kinds().map(|k| k.name.as_str()).collect();
                errors.push(map.diag(
                    &s.span,
                    &format!("{}.kind", s.key),
                    format!(
                        "unknown stage kind `{}` (known: {})",
                        s.kind,
                        list.join(", ")
                    ),
                ));
                continue;
            };
            if !topology.techniques.contains(&kind.technique) {
                errors.push(map.diag(
                    &s.span,
                    &format!("{}.kind", s.key),
                    format!(
                        "kind `{}` belongs to technique `{}`, which `techniques` does not list",
                        kind.name, kind.technique
                    ),
                ));
            }
            if let Err(e) = kind.check_params(&s.params) {
                errors.push(map.diag(&s.span, &format!("{}.params", s.key), e));
            }
            first_instance.insert(s.name.clone(), instances.len());
            for (replica, node) in s.nodes.iter().enumerate() {
                instances.push(InstancePlan {
                    name: instance_name(&s.name, replica, s.replicas()),
                    stage: s.name.clone(),
                    kind: s.kind.clone(),
                    node: node.clone(),
                    replica,
                    replicas: s.replicas(),
                });
            }
        }

        // Edges.
        let mut edges: Vec<EdgePlan> = Vec::new();
        let mut connected: HashSet<(String, &'static str)> = HashSet::new();
        let mut seen_edges: HashSet<(usize, &'static str, usize, &'static str)> = HashSet::new();
        let mut decl_of: Vec<usize> = Vec::new();
        for (decl, e) in topology.edges.iter().enumerate() {
            let (Some(from_stage), Some(to_stage)) =
                (topology.stage(&e.from.stage), topology.stage(&e.to.stage))
            else {
                continue;
            };
            let (Some(from_kind), Some(to_kind)) =
                (registry.get(&from_stage.kind), registry.get(&to_stage.kind))
            else {
                continue; // unknown kind already reported
            };
            let out = from_kind.find_output(e.from.port.as_deref());
            let inp = to_kind.find_input(e.to.port.as_deref());
            let (out, inp) = match (out, inp) {
                (Ok(o), Ok(i)) => (o, i),
                (o, i) => {
                    if let Err(m) = o {
                        errors.push(map.diag(
                            &e.span,
                            &format!("{}.from", e.key),
                            format!("{}: {m}", e.from),
                        ));
                    }
                    if let Err(m) = i {
                        errors.push(map.diag(
                            &e.span,
                            &format!("{}.to", e.key),
                            format!("{}: {m}", e.to),
                        ));
                    }
                    continue;
                }
            };
            if out.ty != inp.ty {
                errors.push(map.diag(
                    &e.span,
                    &e.key,
                    format!(
                        "{} sends {} but {} takes {}",
                        e.from,
                        out.ty.name(),
                        e.to,
                        inp.ty.name()
                    ),
                ));
                continue;
            }
            let (r_from, r_to) = (from_stage.replicas(), to_stage.replicas());
            let pairs: Vec<(usize, usize)> = if r_from == 1 {
                (0..r_to).map(|j| (0, j)).collect()
            } else if r_to == 1 {
                (0..r_from).map(|i| (i, 0)).collect()
            } else if r_from == r_to {
                (0..r_from).map(|i| (i, i)).collect()
            } else {
                errors.push(map.diag(
                    &e.span,
                    &e.key,
                    format!(
                        "cannot join {r_from} replicas of `{}` to {r_to} replicas of `{}`: use equal counts (one to one), or 1 on one side (fan-out / fan-in)",
                        from_stage.name, to_stage.name
                    ),
                ));
                continue;
            };
            let default = inp.default.unwrap_or(EdgeSettings {
                capacity: 4,
                policy: Policy::Block,
            });
            let settings = EdgeSettings {
                capacity: e
                    .capacity
                    .or(topology.defaults.capacity)
                    .unwrap_or(default.capacity),
                policy: e
                    .policy
                    .or(topology.defaults.policy)
                    .unwrap_or(default.policy),
            };
            let max_bytes = e
                .max_bytes
                .or(topology.defaults.max_bytes)
                .unwrap_or(crate::topology::DEFAULT_EDGE_BYTES);
            // Capacity × message size, where the producer knows its size, against the bound.
            let message = from_kind.estimated_message_bytes(&from_stage.params);
            let bytes_bound = match message {
                Some(m) => (settings.capacity as u64).saturating_mul(m).min(max_bytes),
                None => max_bytes,
            };
            if let Some(m) = message {
                let want = (settings.capacity as u64).saturating_mul(m);
                if want > max_bytes {
                    warnings.push(map.diag(
                        &e.span,
                        &e.key,
                        format!(
                            "{} -> {}: capacity {} × {} messages would be {}, over the edge's \
                             `max_bytes` of {}: it holds {} at a time ({})",
                            e.from,
                            e.to,
                            settings.capacity,
                            human_bytes(m),
                            human_bytes(want),
                            human_bytes(max_bytes),
                            (max_bytes / m).max(1),
                            if m > max_bytes {
                                "each travels alone"
                            } else {
                                "set `max_bytes` to hold more"
                            }
                        ),
                    ));
                }
            }
            for (i, j) in pairs {
                let from = first_instance[&from_stage.name] + i;
                let to = first_instance[&to_stage.name] + j;
                if !seen_edges.insert((from, out.name, to, inp.name)) {
                    errors.push(map.diag(
                        &e.span,
                        &e.key,
                        format!("duplicate edge {} -> {}", e.from, e.to),
                    ));
                    break;
                }
                connected.insert((instances[to].name.clone(), inp.name));
                decl_of.push(decl);
                edges.push(EdgePlan {
                    name: format!(
                        "{}.{} -> {}.{}",
                        instances[from].name, out.name, instances[to].name, inp.name
                    ),
                    from,
                    from_port: out.name,
                    to,
                    to_port: inp.name,
                    settings,
                    max_bytes,
                    bytes_bound,
                    ty: out.ty,
                    cut: instances[from].node != instances[to].node,
                });
            }
        }
        let mut reported = HashSet::new();
        let cyclic = on_cycle(&edges, instances.len());
        for (k, e) in edges.iter().enumerate() {
            let decl = &topology.edges[decl_of[k]];
            if e.settings.policy == Policy::Block && cyclic[k] && reported.insert(decl_of[k]) {
                errors.push(map.diag(
                    &decl.span,
                    &decl.key,
                    format!(
                        "{} -> {} is a `block` edge on a cycle: producers waiting on each other \
                         around it can deadlock; make an edge of the cycle `latest`",
                        decl.from, decl.to
                    ),
                ));
            }
        }
        for s in &topology.stages {
            let Some(kind) = registry.get(&s.kind) else {
                continue;
            };
            for port in kind.inputs.iter().filter(|p| !p.optional) {
                let name = instance_name(&s.name, 0, s.replicas());
                if !connected.contains(&(name, port.name)) {
                    warnings.push(map.diag(
                        &s.span,
                        &s.key,
                        format!(
                            "input `{}.{}` has no edge: it will receive nothing",
                            s.name, port.name
                        ),
                    ));
                }
            }
        }
        if edges.iter().any(|e| e.cut) && topology.secret.is_empty() && !topology.insecure {
            // `run` draws one per run; `node` refuses to start without one (RunError::NoSecret).
            warnings.push(map.diag(
                &(0..0),
                "secret",
                "no secret: `cloudlight run` draws a random one for each run of the whole \
                 topology, but nodes started one by one (`cloudlight node`) need a shared one: \
                 set `secret_env = \"NAME\"` (or `secret_file`, or `secret`, e.g. the output \
                 of `openssl rand -hex 16`)",
            ));
        }
        if crate::topology::is_example_secret(&topology.secret) {
            warnings.push(map.diag(
                &topology.secret_span,
                "secret",
                format!(
                    "the secret, {}, is a well-known example: anyone who read it can join \
                     the cluster; use a random one (e.g. `openssl rand -hex 16`)",
                    topology.secret_source.describe()
                ),
            ));
        }
        if errors.is_empty() {
            Ok(Plan {
                topology,
                instances,
                edges,
                warnings,
            })
        } else {
            errors.sort_by_key(|d| (d.line, d.column));
            Err(TopologyErrors(errors))
        }
    }

    /// What every node of a cluster must agree on, hashed: cluster, techniques, scene, seed
    /// and clock, nodes and addresses, instances with their kinds, nodes and parameters, and
    /// edges with their ports, capacities, policies and cuts, and the packet format. Nodes
    /// whose digests differ refuse each other at the handshake.
    pub fn digest(&self) -> [u8; cloudlight_transport::wire::DIGEST_BYTES] {
        let t = &self.topology;
        let mut s = String::new();
        let _ = writeln!(
            s,
            "cluster {:?} techniques {:?} scene {:?} seed {} start {} scale {}",
            t.cluster, t.techniques, t.scene, t.seed, t.scene_start_s, t.time_scale
        );
        let _ = writeln!(
            s,
            "packets {} encrypt {} congestion control {}",
            t.transport.max_packet_bytes, t.transport.encrypt, t.transport.congestion_control
        );
        for n in &t.nodes {
            let _ = writeln!(s, "node {:?} {}", n.name, n.declared());
        }
        for st in &t.stages {
            let _ = writeln!(
                s,
                "stage {:?} {:?} {:?} {}",
                st.name, st.kind, st.nodes, st.params
            );
        }
        for i in &self.instances {
            let _ = writeln!(s, "instance {:?} {:?} {:?}", i.name, i.kind, i.node);
        }
        for (k, e) in self.edges.iter().enumerate() {
            let _ = writeln!(
                s,
                "edge {k} {:?} {} {} {} {} {}",
                e.name,
                e.ty.name(),
                e.settings.capacity,
                e.settings.policy,
                e.max_bytes,
                e.cut
            );
        }
        cloudlight_transport::crypto::digest(s.as_bytes())
    }

    /// Node names in declaration order.
    pub fn nodes(&self) -> impl Iterator<Item = &str> {
        self.topology.nodes.iter().map(|n| n.name.as_str())
    }

    /// Instance index by name.
    pub fn instance(&self, name: &str) -> Option<usize> {
        self.instances.iter().position(|i| i.name == name)
    }

    /// A human-readable summary: stages per node, edges, and which edges are cut.
    pub fn summary(&self) -> String {
        let t = &self.topology;
        let mut s = String::new();
        let _ = writeln!(
            s,
            "{}: techniques {}, scene `{}`, seed {}",
            t.source.file(),
            t.techniques.join(", "),
            t.scene,
            t.seed
        );
        let _ = writeln!(
            s,
            "secret: {}{}",
            t.secret_source.describe(),
            if t.secret.is_empty() {
                String::new()
            } else {
                format!(", {} bytes", t.secret.len())
            }
        );
        for node in &t.nodes {
            let here: Vec<_> = self
                .instances
                .iter()
                .filter(|i| i.node == node.name)
                .map(|i| format!("{} ({})", i.name, i.kind))
                .collect();
            // Local edges and sending halves live with their producer (a sending half holds
            // each message until its consumer finished it).
            let queued: u64 = self
                .edges
                .iter()
                .filter(|e| self.instances[e.from].node == node.name)
                .map(|e| e.bytes_bound)
                .sum();
            let _ = writeln!(
                s,
                "node {} @ {}: {}{}",
                node.name,
                node.declared(),
                if here.is_empty() {
                    "no stages".to_string()
                } else {
                    here.join(", ")
                },
                if queued > 0 {
                    format!("; its queues hold at most {}", human_bytes(queued))
                } else {
                    String::new()
                }
            );
        }
        let _ = writeln!(s, "edges:");
        for e in &self.edges {
            let cut = if e.cut {
                let (a, b) = (&self.instances[e.from].node, &self.instances[e.to].node);
                match t.link(a, b) {
                    Some(p) => format!(
                        "  CUT {a} -> {b} (link {} ms ± {} ms, {}, loss {})",
                        p.latency_ms,
                        p.jitter_ms,
                        p.bandwidth_mbps
                            .map_or("uncapped".to_string(), |b| format!("{b} Mbps")),
                        p.loss
                    ),
                    None => format!("  CUT {a} -> {b} (no link profile: plain loopback/network)"),
                }
            } else {
                String::new()
            };
            let _ = writeln!(
                s,
                "  {} [{} {}, ≤ {}]{}",
                e.name,
                e.settings.policy,
                e.settings.capacity,
                human_bytes(e.bytes_bound),
                cut
            );
        }
        let cut = self.edges.iter().filter(|e| e.cut).count();
        let _ = write!(
            s,
            "{} instances on {} nodes, {} edges, {} cut",
            self.instances.len(),
            t.nodes.len(),
            self.edges.len(),
            cut
        );
        s
    }
}

/// Bytes in binary units: `812 B`, `64.0 KiB`, `256 MiB`, `1.5 GiB`, `64 TiB`.
pub fn human_bytes(b: u64) -> String {
    const UNITS: [&str; 5] = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut v = b as f64;
    let mut u = 0;
    while v >= 1024.0 && u + 1 < UNITS.len() {
        v /= 1024.0;
        u += 1;
    }
    if u == 0 || v.fract() == 0.0 {
        format!("{v:.0} {}", UNITS[u])
    } else {
        format!("{v:.1} {}", UNITS[u])
    }
}
