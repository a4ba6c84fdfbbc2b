//! Topology files: where each stage instance runs, how edges are set, and what the links
//! between nodes look like.
//!
//! [`Topology::parse`] reads the TOML text (every problem is a [`Diagnostic`] naming file,
//! line and key); [`Plan::build`] checks it against a [`crate::StageRegistry`] (kinds, ports,
//! message types, replica wiring) and expands replicas into instances and edges. The format is
//! documented in the repository README. Programs write topologies as [`TopologySpec`]
//! values, which go through the same parser and planner.

mod parse;
mod plan;
pub mod reader;
mod spec;

use std::fmt;
use std::net::SocketAddr;
use std::ops::Range;
use std::path::Path;

pub use parse::{
    DEFAULT_EDGE_BYTES, MAX_CAPACITY, MAX_EDGE_BYTES, MAX_REPLICAS, MAX_SECONDS, MIN_EDGE_BYTES,
};
pub use plan::{EdgePlan, InstancePlan, Plan};
pub use spec::{EdgeSpec, LinkSpec, NodeSpec, StageSpec, TopologySpec};

use crate::edge::Policy;

/// One problem found in a topology file.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Diagnostic {
    /// File name as given.
    pub file: String,
    /// 1-based line.
    pub line: usize,
    /// 1-based column.
    pub column: usize,
    /// Dotted key path, e.g. `stage[1].replicas`.
    pub key: String,
    /// What is wrong.
    pub message: String,
}

impl fmt::Display for Diagnostic {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{}:{}:{}: `{}`: {}",
            self.file, self.line, self.column, self.key, self.message
        )
    }
}

/// Every problem found in a topology file.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub struct TopologyErrors(pub Vec<Diagnostic>);

impl fmt::Display for TopologyErrors {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for d in &self.0 {
            writeln!(f, "{d}")?;
        }
        write!(
            f,
            "{} problem{} found",
            self.0.len(),
            if self.0.len() == 1 { "" } else { "s" }
        )
    }
}

/// Largest topology file read: far beyond any real one.
const MAX_TOPOLOGY_BYTES: u64 = 16 << 20;

/// Reads a topology file: a regular file of at most 16 MiB (never a device such as
/// `/dev/zero`, which would be read until memory runs out).
pub(crate) fn read_topology(path: &Path) -> Result<String, TopologyErrors> {
    let file = path.display().to_string();
    let meta = std::fs::metadata(path).map_err(|e| unreadable(&file, e))?;
    if !meta.is_file() {
        return Err(unreadable(
            &file,
            std::io::Error::other("not a regular file"),
        ));
    }
    if meta.len() > MAX_TOPOLOGY_BYTES {
        return Err(unreadable(
            &file,
            std::io::Error::other(format!(
                "{} bytes, more than a topology file may be ({MAX_TOPOLOGY_BYTES})",
                meta.len()
            )),
        ));
    }
    std::fs::read_to_string(path).map_err(|e| unreadable(&file, e))
}

pub(crate) fn unreadable(file: &str, e: std::io::Error) -> TopologyErrors {
    TopologyErrors(vec![Diagnostic {
        file: file.to_string(),
        line: 0,
        column: 0,
        key: String::new(),
        message: format!("cannot read: {e}"),
    }])
}

/// Maps byte offsets to lines and columns of one file.
#[derive(Clone, Debug)]
pub struct SourceMap {
    file: String,
    line_starts: Vec<usize>,
}

impl SourceMap {
    fn new(file: &str, text: &str) -> Self {
        let line_starts = std::iter::once(0)
            .chain(text.match_indices('\n').map(|(i, _)| i + 1))
            .collect();
        SourceMap {
            file: file.to_string(),
            line_starts,
        }
    }

    /// The file name.
    pub fn file(&self) -> &str {
        &self.file
    }

    /// A diagnostic at byte span `span`.
    pub fn diag(&self, span: &Range<usize>, key: &str, message: impl Into<String>) -> Diagnostic {
        let line = self
            .line_starts
            .partition_point(|&s| s <= span.start)
            .max(1);
        Diagnostic {
            file: self.file.clone(),
            line,
            column: span.start - self.line_starts[line - 1] + 1,
            key: key.to_string(),
            message: message.into(),
        }
    }
}

/// Where a topology's secret comes from: written in the file (`secret`), an environment
/// variable (`secret_env`) or a file (`secret_file`), so that the topology itself can be kept
/// in version control or a ConfigMap.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub enum SecretSource {
    /// No secret.
    #[default]
    None,
    /// `secret = "..."`.
    Inline,
    /// `secret_env = "NAME"`.
    Env(String),
    /// `secret_file = "PATH"` (as resolved: relative to the topology file's folder).
    File(std::path::PathBuf),
    /// None given: drawn at random for one run of every node in one process.
    Drawn,
}

impl SecretSource {
    /// Where the secret came from, in words (never the secret).
    pub fn describe(&self) -> String {
        match self {
            SecretSource::None => "none".into(),
            SecretSource::Inline => "written in the file (`secret`)".into(),
            SecretSource::Env(name) => format!("environment variable `{name}` (`secret_env`)"),
            SecretSource::File(path) => format!("file `{}` (`secret_file`)", path.display()),
            SecretSource::Drawn => "drawn at random for this run".into(),
        }
    }
}

/// Secrets that appear in documentation and examples: a cluster using one is open to anyone
/// who read them (compared ignoring case, spaces, `-` and `_`).
pub const EXAMPLE_SECRETS: [&str; 8] = [
    "changeme",
    "secret",
    "password",
    "cloudlight",
    "shared",
    "shared secret",
    "test",
    "example",
];

/// Whether `secret` is one of [`EXAMPLE_SECRETS`].
pub fn is_example_secret(secret: &str) -> bool {
    let folded: String = secret
        .chars()
        .filter(|c| !c.is_whitespace() && *c != '-' && *c != '_')
        .flat_map(char::to_lowercase)
        .collect();
    EXAMPLE_SECRETS.iter().any(|e| e.replace(' ', "") == folded)
}

/// A node: one process of the cluster with one UDP address.
#[derive(Clone, Debug, PartialEq)]
pub struct NodeDecl {
    /// Unique node name.
    pub name: String,
    /// UDP address of the node's transport (for a host name: the unspecified address with
    /// the declared port, until [`NodeDecl::resolve`]).
    pub address: SocketAddr,
    /// The host name when the address was given as `host:port` (resolved at start).
    pub host: Option<String>,
    /// What the node listens on when that is not its address (behind NAT, in a container:
    /// `0.0.0.0:7200` while peers dial `cloud.example.net:7200`); `None`: its address.
    pub bind: Option<SocketAddr>,
    /// Where it is declared.
    pub span: Range<usize>,
}

impl NodeDecl {
    /// The node's socket address: the declared one, or its host name resolved now (an IPv4
    /// address when it has one).
    pub fn resolve(&self) -> Result<SocketAddr, String> {
        use std::net::ToSocketAddrs;
        let Some(host) = &self.host else {
            return Ok(self.address);
        };
        let port = self.address.port();
        let found: Vec<SocketAddr> = (host.as_str(), port)
            .to_socket_addrs()
            .map_err(|e| format!("node `{}`: cannot resolve `{host}:{port}`: {e}", self.name))?
            .collect();
        found
            .iter()
            .find(|a| a.is_ipv4())
            .or(found.first())
            .copied()
            .ok_or_else(|| format!("node `{}`: `{host}` resolves to no address", self.name))
    }

    /// The address as declared (`host:port` or IP:port), for messages.
    pub fn declared(&self) -> String {
        match &self.host {
            Some(h) => format!("{h}:{}", self.address.port()),
            None => self.address.to_string(),
        }
    }
}

/// A stage declaration (expanded into `replicas` instances).
#[derive(Clone, Debug, PartialEq)]
pub struct StageDecl {
    /// Unique stage name.
    pub name: String,
    /// Stage kind, looked up in the registry.
    pub kind: String,
    /// Node of each replica (length = replicas).
    pub nodes: Vec<String>,
    /// Kind-specific parameters.
    pub params: toml::Table,
    /// Where it is declared.
    pub span: Range<usize>,
    /// Path of this declaration in the file, e.g. `stage[2]`.
    pub key: String,
}

impl StageDecl {
    /// Number of instances.
    pub fn replicas(&self) -> usize {
        self.nodes.len()
    }
}

/// One end of an edge: `stage` or `stage.port`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PortRef {
    /// Stage name.
    pub stage: String,
    /// Port name; `None` means the stage's only port on that side.
    pub port: Option<String>,
}

impl fmt::Display for PortRef {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.port {
            Some(p) => write!(f, "{}.{p}", self.stage),
            None => f.write_str(&self.stage),
        }
    }
}

/// An edge declaration between two stages' ports.
#[derive(Clone, Debug, PartialEq)]
pub struct EdgeDecl {
    /// Producer side.
    pub from: PortRef,
    /// Consumer side.
    pub to: PortRef,
    /// Capacity, if set here.
    pub capacity: Option<usize>,
    /// Policy, if set here.
    pub policy: Option<Policy>,
    /// Most bytes it may hold, if set here.
    pub max_bytes: Option<u64>,
    /// Where it is declared.
    pub span: Range<usize>,
    /// Path in the file, e.g. `edge[0]`.
    pub key: String,
}

pub use cloudlight_transport::LinkProfile;

/// A link profile from one node to another.
#[derive(Clone, Debug, PartialEq)]
pub struct LinkDecl {
    /// Sending node.
    pub from: String,
    /// Receiving node.
    pub to: String,
    /// Its behaviour.
    pub profile: LinkProfile,
    /// Where it is declared.
    pub span: Range<usize>,
}

/// Transport settings of cut edges (`[transport]`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TransportSettings {
    /// Largest packet handed to laminar, bytes (the UDP datagram adds 5).
    pub max_packet_bytes: usize,
    /// Most unacknowledged packets per peer.
    pub window_packets: usize,
    /// Sending rate cap per peer, megabits per second.
    pub pacing_mbps: Option<f64>,
    /// A peer silent this long is reported lost, milliseconds.
    pub peer_timeout_ms: f64,
    /// Interval between heartbeats, milliseconds.
    pub heartbeat_ms: f64,
    /// How long a node waits at start for the peers it needs, seconds.
    pub connect_timeout_s: f64,
    /// Data unacknowledged this long while the peer answers heartbeats fails the run, seconds.
    pub stall_timeout_s: f64,
    /// A peer lost (silent for `peer_timeout_ms`) that is not back this much later fails the
    /// run, seconds.
    pub rejoin_timeout_s: f64,
    /// Whether cut edges' packets are encrypted (they are always authenticated).
    pub encrypt: bool,
    /// Whether each peer link runs congestion control (pacing at the measured delivery rate;
    /// `pacing_mbps` caps it).
    pub congestion_control: bool,
    /// Whether the socket moves many datagrams per system call (UDP GSO and GRO, packets
    /// sealed in place) instead of one per call through laminar. Nodes on either path talk
    /// to each other.
    pub batched_io: bool,
}

impl Default for TransportSettings {
    fn default() -> Self {
        TransportSettings {
            max_packet_bytes: 1200,
            window_packets: 1024,
            pacing_mbps: None,
            peer_timeout_ms: 2000.0,
            heartbeat_ms: 100.0,
            connect_timeout_s: 60.0,
            stall_timeout_s: 15.0,
            rejoin_timeout_s: 10.0,
            encrypt: true,
            congestion_control: true,
            batched_io: true,
        }
    }
}

/// Defaults for edges that set no capacity or policy (over the ports' own defaults).
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct EdgeDefaults {
    /// Default capacity.
    pub capacity: Option<usize>,
    /// Default policy.
    pub policy: Option<Policy>,
    /// Default byte bound.
    pub max_bytes: Option<u64>,
}

/// A parsed topology file.
#[derive(Clone, Debug)]
pub struct Topology {
    /// Line/column lookup for diagnostics.
    pub source: SourceMap,
    /// Techniques the file runs.
    pub techniques: Vec<String>,
    /// Where the techniques are named.
    pub techniques_span: Range<usize>,
    /// Scene name or path (`cornell`, `city:N`, a glTF file).
    pub scene: String,
    /// Cluster id: nodes of other clusters are strangers.
    pub cluster: String,
    /// Shared secret proving membership of the cluster (empty: none, allowed only with
    /// `insecure`).
    pub secret: String,
    /// Where `secret` is set (empty when it is not).
    pub secret_span: Range<usize>,
    /// Where the secret was read from.
    pub secret_source: SecretSource,
    /// Whether cut edges may run without a secret (loopback demos).
    pub insecure: bool,
    /// Transport settings.
    pub transport: TransportSettings,
    /// Run seed.
    pub seed: u64,
    /// How long `run` lasts by default, seconds; `None` runs until stopped or finished.
    pub duration_s: Option<f64>,
    /// Scene time at the start of the run, seconds.
    pub scene_start_s: f64,
    /// Scene seconds per wall second.
    pub time_scale: f64,
    /// Edge defaults.
    pub defaults: EdgeDefaults,
    /// Nodes.
    pub nodes: Vec<NodeDecl>,
    /// Stages.
    pub stages: Vec<StageDecl>,
    /// Edges.
    pub edges: Vec<EdgeDecl>,
    /// Link profiles, one per direction.
    pub links: Vec<LinkDecl>,
}

impl Topology {
    /// Parses topology text; `file` names it in diagnostics. All problems are reported.
    pub fn parse(file: &str, text: &str) -> Result<Topology, TopologyErrors> {
        let (topology, diags) = parse::parse(file, text);
        if diags.is_empty() {
            Ok(topology)
        } else {
            Err(TopologyErrors(diags))
        }
    }

    /// Reads and parses a topology file.
    pub fn load(path: &Path) -> Result<Topology, TopologyErrors> {
        let file = path.display().to_string();
        let text = read_topology(path)?;
        Self::parse(&file, &text)
    }

    /// Node by name.
    pub fn node(&self, name: &str) -> Option<&NodeDecl> {
        self.nodes.iter().find(|n| n.name == name)
    }

    /// Stage by name.
    pub fn stage(&self, name: &str) -> Option<&StageDecl> {
        self.stages.iter().find(|s| s.name == name)
    }

    /// Link profile from `from` to `to`, if one is declared.
    pub fn link(&self, from: &str, to: &str) -> Option<&LinkProfile> {
        self.links
            .iter()
            .find(|l| l.from == from && l.to == to)
            .map(|l| &l.profile)
    }
}
