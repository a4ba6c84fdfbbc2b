//! TOML text → [`Topology`], collecting every problem instead of stopping at the first.
//!
//! The walker reads `toml`'s spanned document (`DeTable`), so every key and value keeps its
//! byte span and each diagnostic names its line. Keys not read by the walker are reported as
//! unknown. Checks that need only the file (names, addresses, numbers, references between
//! nodes, stages and links) live here; checks against stage kinds live in `plan`.

use std::net::SocketAddr;

use toml::Spanned;

use super::reader::{Tbl, Walker, check_name, kind, plain};
use super::{
    Diagnostic, EdgeDecl, EdgeDefaults, LinkDecl, LinkProfile, NodeDecl, PortRef, SecretSource,
    StageDecl, Topology, TransportSettings,
};
use crate::edge::Policy;

const TOP_KEYS: &[&str] = &[
    "techniques",
    "technique",
    "scene",
    "cluster",
    "secret",
    "secret_env",
    "secret_file",
    "insecure",
    "transport",
    "seed",
    "duration_s",
    "scene_start_s",
    "time_scale",
    "defaults",
    "node",
    "stage",
    "edge",
    "link",
];

pub(super) fn parse(file: &str, text: &str) -> (Topology, Vec<Diagnostic>) {
    let mut w = Walker::new(file, text);
    let mut topo = Topology {
        source: w.map.clone(),
        techniques: Vec::new(),
        techniques_span: 0..0,
        scene: "cornell".into(),
        cluster: "cloudlight".into(),
        secret: String::new(),
        secret_span: 0..0,
        secret_source: SecretSource::None,
        insecure: false,
        transport: TransportSettings::default(),
        seed: 0,
        duration_s: None,
        scene_start_s: 0.0,
        time_scale: 1.0,
        defaults: EdgeDefaults::default(),
        nodes: Vec::new(),
        stages: Vec::new(),
        edges: Vec::new(),
        links: Vec::new(),
    };
    let Some(root) = w.document(text) else {
        return (topo, w.diags);
    };
    let mut top = Tbl::new(root.get_ref(), root.span(), String::new());

    // Techniques and scene.
    match (
        top.table.get("techniques").is_some(),
        top.table.get("technique").is_some(),
    ) {
        (true, true) => {
            let span = top
                .table
                .get("technique")
                .map(|v| v.span())
                .unwrap_or_default();
            w.err(
                &span,
                "technique",
                "give either `technique` or `techniques`, not both",
            );
        }
        (false, false) => w.err(
            &(0..0),
            "techniques",
            "missing required key (e.g. `techniques = [\"photons\"]`)",
        ),
        _ => {}
    }
    if let Some(list) = top.strings(&mut w, "techniques") {
        if list.is_empty() {
            let span = top
                .table
                .get("techniques")
                .map(|v| v.span())
                .unwrap_or_default();
            w.err(&span, "techniques", "names no technique");
        }
        topo.techniques_span = top
            .table
            .get("techniques")
            .map(|v| v.span())
            .unwrap_or_default();
        topo.techniques = list.into_iter().map(|s| s.into_inner()).collect();
    }
    if let Some(t) = top.string(&mut w, "technique") {
        topo.techniques_span = t.span();
        topo.techniques = vec![t.into_inner()];
    }
    if let Some(s) = top.string(&mut w, "scene") {
        topo.scene = s.into_inner();
    }
    if let Some(c) = top.string(&mut w, "cluster") {
        if c.get_ref().is_empty() || c.get_ref().len() > 255 {
            w.err(&c.span(), "cluster", "must be 1 to 255 bytes");
        }
        topo.cluster = c.into_inner();
    }
    secret(&mut w, &mut top, &mut topo, file);
    if let Some(b) = top.boolean(&mut w, "insecure") {
        topo.insecure = b.into_inner();
    }
    if let Some(mut t) = top.table(&mut w, "transport") {
        topo.transport = transport(&mut w, &mut t);
        t.finish(
            &mut w,
            &[
                "max_packet_bytes",
                "window_packets",
                "pacing_mbps",
                "peer_timeout_ms",
                "heartbeat_ms",
                "connect_timeout_s",
                "stall_timeout_s",
                "rejoin_timeout_s",
                "encrypt",
                "congestion_control",
                "batched_io",
            ],
        );
    }
    if let Some(s) = top.uint(&mut w, "seed") {
        topo.seed = s.into_inner();
    }
    if let Some(d) = bounded(
        &mut w,
        &mut top,
        "duration_s",
        Bound::above(0.0, MAX_SECONDS),
        "s",
    ) {
        topo.duration_s = Some(d);
    }
    if let Some(s) = bounded(
        &mut w,
        &mut top,
        "scene_start_s",
        Bound::closed(-MAX_SECONDS, MAX_SECONDS),
        "s",
    ) {
        topo.scene_start_s = s;
    }
    if let Some(s) = bounded(
        &mut w,
        &mut top,
        "time_scale",
        Bound::above(0.0, 1e6),
        "scene s per s",
    ) {
        topo.time_scale = s;
    }
    if let Some(mut d) = top.table(&mut w, "defaults") {
        topo.defaults = EdgeDefaults {
            capacity: capacity(&mut w, &mut d),
            policy: policy(&mut w, &mut d),
            max_bytes: max_bytes(&mut w, &mut d),
        };
        d.finish(&mut w, &["capacity", "policy", "max_bytes"]);
    }

    parse_nodes(&mut w, &mut top, &mut topo);
    parse_stages(&mut w, &mut top, &mut topo);
    parse_edges(&mut w, &mut top, &mut topo);
    parse_links(&mut w, &mut top, &mut topo);
    top.finish(&mut w, TOP_KEYS);
    w.diags.sort_by_key(|d| (d.line, d.column));
    (topo, w.diags)
}

fn transport(w: &mut Walker, t: &mut Tbl<'_, '_>) -> TransportSettings {
    let mut s = TransportSettings::default();
    if let Some(v) = t.uint(w, "max_packet_bytes") {
        if !(128..=65_000).contains(v.get_ref()) {
            w.err(
                &v.span(),
                &t.key("max_packet_bytes"),
                "must be in [128, 65000]",
            );
        }
        s.max_packet_bytes = *v.get_ref() as usize;
    }
    if let Some(v) = t.uint(w, "window_packets") {
        if !(1..=65_536).contains(v.get_ref()) {
            w.err(&v.span(), &t.key("window_packets"), "must be in [1, 65536]");
        }
        s.window_packets = *v.get_ref() as usize;
    }
    for (k, slot, range, unit) in [
        (
            "peer_timeout_ms",
            &mut s.peer_timeout_ms,
            Bound::closed(10.0, 3_600_000.0),
            "ms",
        ),
        (
            "heartbeat_ms",
            &mut s.heartbeat_ms,
            Bound::closed(1.0, 60_000.0),
            "ms",
        ),
        (
            "connect_timeout_s",
            &mut s.connect_timeout_s,
            Bound::above(0.0, 86_400.0),
            "s",
        ),
        (
            "stall_timeout_s",
            &mut s.stall_timeout_s,
            Bound::closed(0.01, 86_400.0),
            "s",
        ),
        (
            "rejoin_timeout_s",
            &mut s.rejoin_timeout_s,
            Bound::closed(0.0, 86_400.0),
            "s",
        ),
    ] {
        if let Some(v) = bounded(w, t, k, range, unit) {
            *slot = v;
        }
    }
    if let Some(v) = t.boolean(w, "encrypt") {
        s.encrypt = v.into_inner();
    }
    if let Some(v) = t.boolean(w, "congestion_control") {
        s.congestion_control = v.into_inner();
    }
    if let Some(v) = t.boolean(w, "batched_io") {
        s.batched_io = v.into_inner();
    }
    if let Some(v) = bounded(
        w,
        t,
        "pacing_mbps",
        MBPS_RANGE,
        "Mbit/s (leave it out for no pacing)",
    ) {
        s.pacing_mbps = Some(v);
    }
    s
}

/// Most seconds any duration in a topology may be (a year): far beyond any run, and always
/// convertible to a wall-clock `Duration` and deadline.
pub const MAX_SECONDS: f64 = 365.0 * 86_400.0;
/// Largest edge capacity: each slot may hold a message, and a `block` edge's permits are
/// counted in memory.
pub const MAX_CAPACITY: u64 = 1_000_000;
/// Most bytes an edge holds unless it says otherwise (`max_bytes`): messages queued plus,
/// under `block`, being handled (and, for a cut edge, in flight). With capacity alone, a
/// million slots of 64 MiB messages would be allowed.
pub const DEFAULT_EDGE_BYTES: u64 = 256 << 20;
/// Smallest `max_bytes`.
pub const MIN_EDGE_BYTES: u64 = 1024;
/// Largest `max_bytes` (4 GiB − 1).
pub const MAX_EDGE_BYTES: u64 = u32::MAX as u64;
/// Longest one-way delay or jitter a link may emulate (a minute): any more is an outage,
/// which the emulator models by loss.
const MAX_LINK_DELAY_MS: f64 = 60_000.0;
/// Rates in Mbit/s (link bandwidth, pacing): from 1 bit/s to 1 Tbit/s.
const MBPS_RANGE: Bound = Bound {
    low: 1e-6,
    high: 1e6,
    open_low: false,
};
/// Most replicas of one stage: every instance is an actor with its own state.
pub const MAX_REPLICAS: u64 = 10_000;

/// An allowed range of a number: `low` itself is allowed unless `open_low`.
#[derive(Clone, Copy)]
struct Bound {
    low: f64,
    high: f64,
    open_low: bool,
}

impl Bound {
    fn closed(low: f64, high: f64) -> Self {
        Bound {
            low,
            high,
            open_low: false,
        }
    }
    fn above(low: f64, high: f64) -> Self {
        Bound {
            low,
            high,
            open_low: true,
        }
    }
    fn contains(&self, v: f64) -> bool {
        v <= self.high && (v > self.low || (!self.open_low && v == self.low))
    }
    fn describe(&self, unit: &str) -> String {
        let open = if self.open_low { "(" } else { "[" };
        format!("{open}{}, {}] {unit}", self.low, self.high)
            .trim_end()
            .to_string()
    }
}

/// A number at key `k` that must lie in `range` (finite; NaN and infinities are refused by
/// the reader); the error names the value and the range.
fn bounded(
    w: &mut Walker,
    t: &mut Tbl<'_, '_>,
    k: &'static str,
    range: Bound,
    unit: &str,
) -> Option<f64> {
    let v = t.float(w, k)?;
    if !range.contains(*v.get_ref()) {
        w.err(
            &v.span(),
            &t.key(k),
            format!(
                "{} is out of range: must be in {}",
                v.get_ref(),
                range.describe(unit)
            ),
        );
        return None;
    }
    Some(v.into_inner())
}

fn max_bytes(w: &mut Walker, t: &mut Tbl<'_, '_>) -> Option<u64> {
    let c = t.uint(w, "max_bytes")?;
    if !(MIN_EDGE_BYTES..=MAX_EDGE_BYTES).contains(c.get_ref()) {
        w.err(
            &c.span(),
            &t.key("max_bytes"),
            format!(
                "{} is out of range: must be in [{MIN_EDGE_BYTES}, {MAX_EDGE_BYTES}] bytes",
                c.get_ref()
            ),
        );
        return None;
    }
    Some(*c.get_ref())
}

fn capacity(w: &mut Walker, t: &mut Tbl<'_, '_>) -> Option<usize> {
    let c = t.uint(w, "capacity")?;
    if !(1..=MAX_CAPACITY).contains(c.get_ref()) {
        w.err(
            &c.span(),
            &t.key("capacity"),
            format!(
                "{} is out of range: must be in [1, {MAX_CAPACITY}]",
                c.get_ref()
            ),
        );
        return None;
    }
    Some(*c.get_ref() as usize)
}

fn policy(w: &mut Walker, t: &mut Tbl<'_, '_>) -> Option<Policy> {
    let p = t.string(w, "policy")?;
    match p.get_ref().parse() {
        Ok(p) => Some(p),
        Err(e) => {
            w.err(&p.span(), &t.key("policy"), e);
            None
        }
    }
}

/// The secret: inline (`secret`), from an environment variable (`secret_env`) or from a file
/// (`secret_file`, relative to the topology file's folder; one trailing line break dropped).
/// One of them at most; a variable that is unset, a file that cannot be read, or an empty
/// secret is an error at its key.
fn secret(w: &mut Walker, top: &mut Tbl<'_, '_>, topo: &mut Topology, file: &str) {
    let given: Vec<(&str, Spanned<String>)> = ["secret", "secret_env", "secret_file"]
        .into_iter()
        .filter_map(|k| top.string(w, k).map(|v| (k, v)))
        .collect();
    for (key, value) in given.iter().skip(1) {
        w.err(
            &value.span(),
            key,
            format!(
                "the secret is already given by `{}`: give it one way (`secret`, `secret_env` or `secret_file`)",
                given[0].0
            ),
        );
    }
    let Some((key, value)) = given.into_iter().next() else {
        return;
    };
    let span = value.span();
    let (secret, source) = match key {
        "secret" => (value.into_inner(), SecretSource::Inline),
        "secret_env" => {
            let name = value.into_inner();
            match std::env::var(&name) {
                Ok(v) => (v, SecretSource::Env(name)),
                Err(std::env::VarError::NotPresent) => {
                    w.err(
                        &span,
                        key,
                        format!("environment variable `{name}` is not set (it holds the cluster's secret)"),
                    );
                    return;
                }
                Err(std::env::VarError::NotUnicode(_)) => {
                    w.err(
                        &span,
                        key,
                        format!("environment variable `{name}` is not UTF-8"),
                    );
                    return;
                }
            }
        }
        _ => {
            let given = std::path::PathBuf::from(value.into_inner());
            let path = match std::path::Path::new(file).parent() {
                Some(dir) if given.is_relative() && !dir.as_os_str().is_empty() => dir.join(&given),
                _ => given,
            };
            match std::fs::read_to_string(&path) {
                Ok(text) => {
                    let text = text.strip_suffix('\n').unwrap_or(&text);
                    let text = text.strip_suffix('\r').unwrap_or(text);
                    (text.to_string(), SecretSource::File(path))
                }
                Err(e) => {
                    w.err(&span, key, format!("cannot read `{}`: {e}", path.display()));
                    return;
                }
            }
        }
    };
    if secret.is_empty() {
        w.err(
            &span,
            key,
            format!("the secret from {} is empty", source.describe()),
        );
        return;
    }
    topo.secret = secret;
    topo.secret_span = span;
    topo.secret_source = source;
}

/// Where a node listens, for finding two nodes of one host on one port: the host it is
/// dialled at (an IP or a name), the IP it binds (`None`: a host name's, unknown) and port.
struct Listener {
    host: String,
    ip: Option<std::net::IpAddr>,
    port: u16,
    node: String,
}

impl Listener {
    /// Whether `self` and `other` would bind the same port on the same machine.
    fn clashes(&self, other: &Listener) -> bool {
        let overlap = match (self.ip, other.ip) {
            (Some(a), Some(b)) => a == b || a.is_unspecified() || b.is_unspecified(),
            _ => true,
        };
        self.port != 0 && self.port == other.port && self.host == other.host && overlap
    }
}

fn parse_nodes(w: &mut Walker, top: &mut Tbl<'_, '_>, topo: &mut Topology) {
    let mut addresses: Vec<(String, String)> = Vec::new();
    let mut listeners: Vec<Listener> = Vec::new();
    for (mut t, span) in top.tables(w, "node") {
        let name = t.req_string(w, "name");
        let address = t.req_string(w, "address");
        let mut bind_span = None;
        let bind = t.string(w, "bind").and_then(|b| match b.get_ref().parse::<SocketAddr>() {
            Ok(a) => {
                bind_span = Some(b.span());
                Some(a)
            }
            Err(_) => {
                w.err(
                    &b.span(),
                    &t.key("bind"),
                    format!(
                        "`{}` is not an IP:port address to listen on (e.g. 0.0.0.0:7200; peers dial `address`)",
                        b.get_ref()
                    ),
                );
                None
            }
        });
        t.finish(w, &["name", "address", "bind"]);
        let Some(name) = name else { continue };
        check_name(w, &name, &t.key("name"));
        if topo.node(name.get_ref()).is_some() {
            w.err(
                &name.span(),
                &t.key("name"),
                format!("duplicate node name `{}`", name.get_ref()),
            );
            continue;
        }
        // A node whose address is missing or bad is still declared (at an unspecified
        // address), so that the stages, edges and links naming it report nothing more.
        let unspecified = SocketAddr::from(([0, 0, 0, 0], 0));
        let (addr, host) = match &address {
            None => (unspecified, None),
            Some(a) => match node_address(a.get_ref()) {
                Ok(parsed) => parsed,
                Err(why) => {
                    w.err(&a.span(), &t.key("address"), why);
                    (unspecified, None)
                }
            },
        };
        if let Some(address) = &address
            && addr.port() != 0
        {
            let key = match &host {
                Some(h) => format!("{h}:{}", addr.port()),
                None => addr.to_string(),
            };
            let mut clashed = false;
            if let Some((_, other)) = addresses.iter().find(|(a, _)| *a == key) {
                w.err(
                    &address.span(),
                    &t.key("address"),
                    format!("address {key} is already used by node `{other}`"),
                );
                clashed = true;
            }
            addresses.push((key, name.get_ref().clone()));
            // Two nodes dialled at one host must not listen on one port there.
            let me = Listener {
                host: host.clone().unwrap_or_else(|| addr.ip().to_string()),
                ip: match (bind, &host) {
                    (Some(b), _) => Some(b.ip()),
                    (None, None) => Some(addr.ip()),
                    (None, Some(_)) => None,
                },
                port: bind.map_or(addr.port(), |b| b.port()),
                node: name.get_ref().clone(),
            };
            if !clashed && let Some(other) = listeners.iter().find(|l| l.clashes(&me)) {
                let (key, span) = match &bind_span {
                    Some(s) => (t.key("bind"), s.clone()),
                    None => (t.key("address"), address.span()),
                };
                w.err(
                    &span,
                    &key,
                    format!(
                        "node `{}` would listen on port {} of host {}, as node `{}` does: two \
                         nodes of one host need two ports",
                        me.node, me.port, me.host, other.node
                    ),
                );
            }
            listeners.push(me);
        }
        topo.nodes.push(NodeDecl {
            name: name.into_inner(),
            address: addr,
            host,
            bind,
            span,
        });
    }
}

/// `IP:port`, or `host:port` with a host name as DNS writes it (letters, digits, `-`, `.`;
/// labels of at most 63 bytes, 253 in all), resolved when the node starts.
fn node_address(text: &str) -> Result<(SocketAddr, Option<String>), String> {
    if let Ok(addr) = text.parse::<SocketAddr>() {
        return Ok((addr, None));
    }
    let bad = || {
        format!(
            "`{text}` is not an IP:port or host:port address (e.g. 127.0.0.1:7100, gi-node.lan:7100)"
        )
    };
    let (host, port) = text.rsplit_once(':').ok_or_else(bad)?;
    let port: u16 = port.parse().map_err(|_| bad())?;
    let label_ok = |l: &str| {
        (1..=63).contains(&l.len())
            && l.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-')
            && !l.starts_with('-')
            && !l.ends_with('-')
    };
    let host = host.strip_suffix('.').unwrap_or(host);
    if host.len() > 253
        || !host.split('.').all(label_ok)
        || host.parse::<std::net::IpAddr>().is_ok()
    {
        return Err(bad());
    }
    // All-numeric dotted names are IPv4 typos (e.g. 127.0.0.300), not host names.
    if host
        .split('.')
        .all(|l| l.bytes().all(|b| b.is_ascii_digit()))
    {
        return Err(bad());
    }
    Ok((
        SocketAddr::from(([0, 0, 0, 0], port)),
        Some(host.to_string()),
    ))
}

fn parse_stages(w: &mut Walker, top: &mut Tbl<'_, '_>, topo: &mut Topology) {
    for (mut t, span) in top.tables(w, "stage") {
        let name = t.req_string(w, "name");
        let kind_name = t.req_string(w, "kind");
        let node = t.string(w, "node");
        let nodes = t.strings(w, "nodes");
        let replicas = t.uint(w, "replicas");
        let params = t.get("params");
        t.finish(w, &["name", "kind", "node", "nodes", "replicas", "params"]);
        let (Some(name), Some(kind_name)) = (name, kind_name) else {
            continue;
        };
        check_name(w, &name, &t.key("name"));
        if topo.stage(name.get_ref()).is_some() {
            w.err(
                &name.span(),
                &t.key("name"),
                format!("duplicate stage name `{}`", name.get_ref()),
            );
            continue;
        }
        if let Some(r) = &replicas
            && !(1..=MAX_REPLICAS).contains(r.get_ref())
        {
            w.err(
                &r.span(),
                &t.key("replicas"),
                format!(
                    "replica count {} is out of range: must be in [1, {MAX_REPLICAS}]",
                    r.get_ref()
                ),
            );
            continue;
        }
        let placed: Vec<Spanned<String>> = match (node, nodes) {
            (Some(_), Some(_)) => {
                w.err(
                    &span,
                    &t.key("node"),
                    "give either `node` or `nodes`, not both",
                );
                continue;
            }
            (None, None) => {
                w.err(
                    &span,
                    &t.key("node"),
                    format!(
                        "stage `{}` is not placed: give `node = \"...\"` or `nodes = [...]`",
                        name.get_ref()
                    ),
                );
                continue;
            }
            (Some(n), None) => {
                let count = replicas.as_ref().map_or(1, |r| *r.get_ref() as usize);
                vec![n; count]
            }
            (None, Some(list)) => {
                if list.is_empty() {
                    w.err(&span, &t.key("nodes"), "lists no node");
                    continue;
                }
                if list.len() as u64 > MAX_REPLICAS {
                    w.err(
                        &span,
                        &t.key("nodes"),
                        format!(
                            "lists {} nodes, one per replica: at most {MAX_REPLICAS}",
                            list.len()
                        ),
                    );
                    continue;
                }
                if let Some(r) = &replicas
                    && *r.get_ref() as usize != list.len()
                {
                    w.err(
                        &r.span(),
                        &t.key("replicas"),
                        format!(
                            "replicas = {} but `nodes` lists {} nodes (one per replica)",
                            r.get_ref(),
                            list.len()
                        ),
                    );
                    continue;
                }
                list
            }
        };
        let mut ok = true;
        for n in &placed {
            if topo.node(n.get_ref()).is_none() {
                w.err(
                    &n.span(),
                    &t.key("node"),
                    format!("unknown node `{}`", n.get_ref()),
                );
                ok = false;
                break;
            }
        }
        let params = match params {
            None => toml::Table::new(),
            Some(v) => match plain(v.get_ref()) {
                Some(toml::Value::Table(p)) => p,
                _ => {
                    w.err(
                        &v.span(),
                        &t.key("params"),
                        format!("expected a table, found {}", kind(v.get_ref())),
                    );
                    ok = false;
                    toml::Table::new()
                }
            },
        };
        if ok {
            topo.stages.push(StageDecl {
                name: name.into_inner(),
                kind: kind_name.into_inner(),
                nodes: placed.into_iter().map(|n| n.into_inner()).collect(),
                params,
                span,
                key: t.path.clone(),
            });
        }
    }
}

fn port_ref(
    w: &mut Walker,
    t: &mut Tbl<'_, '_>,
    k: &'static str,
    topo: &Topology,
) -> Option<PortRef> {
    let s = t.req_string(w, k)?;
    let (stage, port) = match s.get_ref().split_once('.') {
        Some((st, p)) => (st.to_string(), Some(p.to_string())),
        None => (s.get_ref().clone(), None),
    };
    if stage.is_empty() || port.as_deref() == Some("") {
        w.err(
            &s.span(),
            &t.key(k),
            format!("`{}` is not `stage` or `stage.port`", s.get_ref()),
        );
        return None;
    }
    if topo.stage(&stage).is_none() {
        w.err(&s.span(), &t.key(k), format!("unknown stage `{stage}`"));
        return None;
    }
    Some(PortRef { stage, port })
}

fn parse_edges(w: &mut Walker, top: &mut Tbl<'_, '_>, topo: &mut Topology) {
    for (mut t, span) in top.tables(w, "edge") {
        let from = port_ref(w, &mut t, "from", topo);
        let to = port_ref(w, &mut t, "to", topo);
        let capacity = capacity(w, &mut t);
        let policy = policy(w, &mut t);
        let max_bytes = max_bytes(w, &mut t);
        t.finish(w, &["from", "to", "capacity", "policy", "max_bytes"]);
        if let (Some(from), Some(to)) = (from, to) {
            topo.edges.push(EdgeDecl {
                from,
                to,
                capacity,
                policy,
                max_bytes,
                span,
                key: t.path.clone(),
            });
        }
    }
}

fn parse_links(w: &mut Walker, top: &mut Tbl<'_, '_>, topo: &mut Topology) {
    for (mut t, span) in top.tables(w, "link") {
        let between = t.strings(w, "between");
        let from = t.string(w, "from");
        let to = t.string(w, "to");
        let mut ok = true;
        // A named profile is the base; the keys given beside it override its figures.
        let mut profile = match t.string(w, "profile") {
            None => LinkProfile::default(),
            Some(name) => LinkProfile::named(name.get_ref()).unwrap_or_else(|| {
                w.err(
                    &name.span(),
                    &t.key("profile"),
                    format!(
                        "unknown link profile `{}` (known: {})",
                        name.get_ref(),
                        LinkProfile::names()
                    ),
                );
                ok = false;
                LinkProfile::default()
            }),
        };
        for (k, slot, range, unit) in [
            (
                "latency_ms",
                &mut profile.latency_ms,
                Bound::closed(0.0, MAX_LINK_DELAY_MS),
                "ms",
            ),
            (
                "jitter_ms",
                &mut profile.jitter_ms,
                Bound::closed(0.0, MAX_LINK_DELAY_MS),
                "ms",
            ),
            ("loss", &mut profile.loss, Bound::closed(0.0, 1.0), ""),
            (
                "duplicate",
                &mut profile.duplicate,
                Bound::closed(0.0, 1.0),
                "",
            ),
            ("reorder", &mut profile.reorder, Bound::closed(0.0, 1.0), ""),
        ] {
            if t.table.get(k).is_some() {
                match bounded(w, &mut t, k, range, unit) {
                    Some(v) => *slot = v,
                    None => ok = false,
                }
            }
        }
        if t.table.get("bandwidth_mbps").is_some() {
            match bounded(
                w,
                &mut t,
                "bandwidth_mbps",
                MBPS_RANGE,
                "Mbit/s (leave it out for no cap)",
            ) {
                Some(b) => profile.bandwidth_mbps = Some(b),
                None => ok = false,
            }
        }
        t.finish(
            w,
            &[
                "between",
                "from",
                "to",
                "profile",
                "latency_ms",
                "jitter_ms",
                "bandwidth_mbps",
                "loss",
                "duplicate",
                "reorder",
            ],
        );
        let pairs: Vec<(Spanned<String>, Spanned<String>)> = match (between, from, to) {
            (Some(b), None, None) if b.len() == 2 => {
                vec![(b[0].clone(), b[1].clone()), (b[1].clone(), b[0].clone())]
            }
            (Some(_), None, None) => {
                w.err(&span, &t.key("between"), "must name exactly two nodes");
                continue;
            }
            (None, Some(f), Some(to)) => vec![(f, to)],
            _ => {
                w.err(
                    &span,
                    &t.key("between"),
                    "give `between = [a, b]` (both directions) or `from` and `to` (one direction)",
                );
                continue;
            }
        };
        for (f, to) in pairs {
            for n in [&f, &to] {
                if topo.node(n.get_ref()).is_none() {
                    w.err(
                        &n.span(),
                        &t.path,
                        format!("unknown node `{}`", n.get_ref()),
                    );
                    ok = false;
                }
            }
            if f.get_ref() == to.get_ref() {
                w.err(&f.span(), &t.path, "a link joins two different nodes");
                ok = false;
            }
            if ok && topo.link(f.get_ref(), to.get_ref()).is_some() {
                w.err(
                    &span,
                    &t.path,
                    format!(
                        "a link from `{}` to `{}` is already declared",
                        f.get_ref(),
                        to.get_ref()
                    ),
                );
                ok = false;
            }
            if ok {
                topo.links.push(LinkDecl {
                    from: f.into_inner(),
                    to: to.into_inner(),
                    profile,
                    span: span.clone(),
                });
            }
        }
    }
}
