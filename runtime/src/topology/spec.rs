//! Topologies written by programs: [`TopologySpec`] is the file format as typed values (a
//! benchmark or an experiment fills it in), serialized to TOML by the `toml` crate and read
//! back by the same parser and planner as a file — so a generated topology gets every check
//! a hand-written one gets, and can be written out and re-run alone.

use std::net::SocketAddr;

use serde::Serialize;

use super::{LinkProfile, Plan, TopologyErrors};
use crate::edge::Policy;
use crate::stage::StageRegistry;

/// A node: a name and its UDP address (port 0 picks a free one).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct NodeSpec {
    /// Node name.
    pub name: String,
    /// UDP address.
    pub address: SocketAddr,
}

/// A stage declaration.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct StageSpec {
    /// Stage name.
    pub name: String,
    /// Stage kind.
    pub kind: String,
    /// The node of each replica (one entry: one instance).
    pub nodes: Vec<String>,
    /// The kind's parameters.
    pub params: toml::Table,
}

/// An edge declaration.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct EdgeSpec {
    /// `stage` or `stage.port`.
    pub from: String,
    /// `stage` or `stage.port`.
    pub to: String,
    /// Capacity (the port's default when absent).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub capacity: Option<usize>,
    /// Policy (the port's default when absent).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub policy: Option<Policy>,
}

/// A link profile between two nodes, both directions.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct LinkSpec {
    /// The two nodes.
    pub between: [String; 2],
    /// One-way latency, ms.
    pub latency_ms: f64,
    /// Latency standard deviation, ms.
    pub jitter_ms: f64,
    /// Bandwidth cap, Mbit/s.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bandwidth_mbps: Option<f64>,
    /// Loss probability.
    pub loss: f64,
    /// Duplication probability.
    pub duplicate: f64,
    /// Reordering probability.
    pub reorder: f64,
}

/// A whole topology as typed values.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TopologySpec {
    /// Techniques it runs.
    pub techniques: Vec<String>,
    /// Scene name or path.
    pub scene: String,
    /// Run seed.
    pub seed: u64,
    /// Run length, seconds.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub duration_s: Option<f64>,
    /// Cluster id.
    pub cluster: String,
    /// Shared secret.
    pub secret: String,
    /// Nodes.
    #[serde(rename = "node")]
    pub nodes: Vec<NodeSpec>,
    /// Stages.
    #[serde(rename = "stage")]
    pub stages: Vec<StageSpec>,
    /// Edges.
    #[serde(rename = "edge")]
    pub edges: Vec<EdgeSpec>,
    /// Links.
    #[serde(rename = "link")]
    pub links: Vec<LinkSpec>,
}

impl TopologySpec {
    /// A topology of `techniques` on `scene` without nodes yet.
    pub fn new(techniques: &[&str], scene: &str) -> Self {
        TopologySpec {
            techniques: techniques.iter().map(|t| t.to_string()).collect(),
            scene: scene.to_string(),
            seed: 0,
            duration_s: None,
            cluster: "cloudlight".into(),
            secret: cloudlight_transport::crypto::random_secret(),
            nodes: Vec::new(),
            stages: Vec::new(),
            edges: Vec::new(),
            links: Vec::new(),
        }
    }

    /// Adds a node.
    pub fn node(mut self, name: &str, address: SocketAddr) -> Self {
        self.nodes.push(NodeSpec {
            name: name.into(),
            address,
        });
        self
    }

    /// Adds a stage with one instance per entry of `nodes`.
    pub fn stage(mut self, name: &str, kind: &str, nodes: &[&str], params: toml::Table) -> Self {
        self.stages.push(StageSpec {
            name: name.into(),
            kind: kind.into(),
            nodes: nodes.iter().map(|n| n.to_string()).collect(),
            params,
        });
        self
    }

    /// Adds an edge.
    pub fn edge(
        mut self,
        from: &str,
        to: &str,
        capacity: Option<usize>,
        policy: Option<Policy>,
    ) -> Self {
        self.edges.push(EdgeSpec {
            from: from.into(),
            to: to.into(),
            capacity,
            policy,
        });
        self
    }

    /// Adds a link between `a` and `b` (both directions behave as `profile`).
    pub fn link(mut self, a: &str, b: &str, profile: LinkProfile) -> Self {
        self.links.push(LinkSpec {
            between: [a.into(), b.into()],
            latency_ms: profile.latency_ms,
            jitter_ms: profile.jitter_ms,
            bandwidth_mbps: profile.bandwidth_mbps,
            loss: profile.loss,
            duplicate: profile.duplicate,
            reorder: profile.reorder,
        });
        self
    }

    /// The topology file's text.
    pub fn to_toml(&self) -> String {
        toml::to_string(self).unwrap_or_else(|e| format!("# cannot write this topology: {e}\n"))
    }

    /// Parses and plans it like a file named `file`.
    pub fn plan(&self, file: &str, registry: &StageRegistry) -> Result<Plan, TopologyErrors> {
        Plan::from_str(file, &self.to_toml(), registry)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::topology::Topology;

    #[test]
    fn a_spec_reads_back_as_the_same_topology() {
        let mut params = toml::Table::new();
        params.insert("rate_hz".into(), 50.0.into());
        let mut spec = TopologySpec::new(&["probe"], "city:2000")
            .node("a", "127.0.0.1:0".parse().unwrap())
            .node("b", "127.0.0.1:7000".parse().unwrap())
            .stage("src", "probe_source", &["a"], params.clone())
            .stage("sink", "probe_sink", &["b", "b"], toml::Table::new())
            .edge("src.out", "sink", Some(8), Some(Policy::Latest))
            .link("a", "b", LinkProfile::CAMPUS);
        spec.seed = 9;
        spec.duration_s = Some(2.5);
        spec.secret = "s3".into();
        let t = Topology::parse("<spec>", &spec.to_toml()).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(t.techniques, ["probe"]);
        assert_eq!(
            (t.scene.as_str(), t.seed, t.duration_s),
            ("city:2000", 9, Some(2.5))
        );
        assert_eq!(t.secret, "s3");
        assert_eq!(t.nodes.len(), 2);
        assert_eq!(t.stages[0].params, params);
        assert_eq!(t.stages[1].nodes, ["b", "b"]);
        assert_eq!(t.edges[0].capacity, Some(8));
        assert_eq!(t.edges[0].policy, Some(Policy::Latest));
        assert_eq!(t.edges[0].from.port.as_deref(), Some("out"));
        assert_eq!(t.link("a", "b"), Some(&LinkProfile::CAMPUS));
        assert_eq!(t.link("b", "a"), Some(&LinkProfile::CAMPUS));
    }
}
