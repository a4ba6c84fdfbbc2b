//! Wiring a plan's edges in this process: in-process edges, the two halves of cut edges, a
//! transport per local node with cut edges, and the wait for peers.

use std::sync::Arc;
use std::time::{Duration, Instant};

use super::{EdgeRun, RunError, RunOptions};
use crate::clock::{SceneClock, now_unix_ns};
use crate::control::RunControl;
use crate::edge::Edge;
use crate::net::{NetArgs, NodeNet};
use crate::topology::Plan;
use tokio::sync::mpsc::{UnboundedReceiver, UnboundedSender};

/// The local halves of one plan edge: the edge a producer sends into and the edge a
/// consumer reads from (the same edge unless the plan edge is cut).
pub(super) struct Wired {
    pub(super) producer: Option<Arc<Edge>>,
    pub(super) consumer: Option<Arc<Edge>>,
    pub(super) runs: Vec<EdgeRun>,
}

/// Creates the local edges of the plan, starts a transport for every local node with cut
/// edges, waits until the peers they need are up, and returns the run's clock (whose epoch
/// is the earliest among the node and its peers, so that nodes agree on scene time).
pub(super) async fn wire_edges(
    plan: &Plan,
    local: &impl Fn(usize) -> bool,
    control: &Arc<RunControl>,
    options: &RunOptions,
    failures: UnboundedSender<String>,
    failed: &mut UnboundedReceiver<String>,
) -> Result<(Vec<Wired>, Vec<NodeNet>, SceneClock), RunError> {
    let t = &plan.topology;
    let mut wired = Vec::new();
    for (i, e) in plan.edges.iter().enumerate() {
        let mut w = Wired {
            producer: None,
            consumer: None,
            runs: Vec::new(),
        };
        if !e.cut {
            if local(e.from) {
                let edge = Edge::bounded(
                    e.name.clone(),
                    e.settings,
                    Some(e.max_bytes),
                    control.clone(),
                );
                w.producer = Some(edge.clone());
                w.consumer = Some(edge.clone());
                w.runs.push(EdgeRun {
                    edge,
                    cut: false,
                    net: None,
                });
            }
        } else {
            if local(e.from) {
                // The sending half holds each message until its consumer finished it (credit
                // came back), so its byte bound covers the whole edge; the receiving half is
                // bounded by the credit it grants.
                let edge = Edge::bounded(
                    e.name.clone(),
                    e.settings,
                    Some(e.max_bytes),
                    control.clone(),
                );
                w.producer = Some(edge.clone());
                w.runs.push(EdgeRun {
                    edge,
                    cut: true,
                    net: Some((i as u32, plan.instances[e.from].node.clone())),
                });
            }
            if local(e.to) {
                let edge = Edge::new(format!("{} (rx)", e.name), e.settings, control.clone());
                w.consumer = Some(edge.clone());
                w.runs.push(EdgeRun {
                    edge,
                    cut: true,
                    net: Some((i as u32, plan.instances[e.to].node.clone())),
                });
            }
        }
        wired.push(w);
    }

    // One transport per local node that has a cut edge.
    let epoch = now_unix_ns();
    let mut net_nodes: Vec<String> = wired
        .iter()
        .flat_map(|w| &w.runs)
        .filter_map(|r| r.net.as_ref().map(|(_, n)| n.clone()))
        .collect();
    net_nodes.sort();
    net_nodes.dedup();
    let mut nets = Vec::new();
    let digest = plan.digest();
    for node in &net_nodes {
        let decl = t.node(node).expect("plan nodes are declared");
        let advertised = decl.resolve().map_err(RunError::Resolve)?;
        // What it listens on: `--bind` for the one node a process runs, else its `bind`,
        // else the address its peers dial.
        let addr = match (&options.only_node, options.bind) {
            (Some(only), Some(bind)) if only == node => bind,
            _ => decl.bind.unwrap_or(advertised),
        };
        let net = NodeNet::bind(NetArgs {
            node,
            addr,
            cluster: &t.cluster,
            secret: &t.secret,
            epoch_unix_ns: epoch,
            settings: &t.transport,
            seed: t.seed,
            digest,
            failures: failures.clone(),
        })
        .map_err(|e| RunError::Transport {
            node: node.clone(),
            addr,
            error: e.to_string(),
        })?;
        tracing::info!(%node, addr = %net.local_addr(), "transport bound");
        nets.push(net);
    }
    // A peer in this process is dialled where it listens (on loopback when it listens on
    // every interface).
    let addr_of = |peer: &str, nets: &[NodeNet]| -> Option<std::net::SocketAddr> {
        nets.iter().find(|n| n.node == peer).map(|n| {
            let a = n.local_addr();
            match a.ip() {
                std::net::IpAddr::V4(ip) if ip.is_unspecified() => {
                    std::net::SocketAddr::from((std::net::Ipv4Addr::LOCALHOST, a.port()))
                }
                std::net::IpAddr::V6(ip) if ip.is_unspecified() => {
                    std::net::SocketAddr::from((std::net::Ipv6Addr::LOCALHOST, a.port()))
                }
                _ => a,
            }
        })
    };
    for (i, e) in plan.edges.iter().enumerate() {
        if !e.cut {
            continue;
        }
        let (from_node, to_node) = (&plan.instances[e.from].node, &plan.instances[e.to].node);
        for (here, there, sending) in [(from_node, to_node, true), (to_node, from_node, false)] {
            let Some(k) = nets.iter().position(|n| &n.node == here) else {
                continue;
            };
            let addr = match addr_of(there, &nets) {
                Some(a) => a,
                None => {
                    let declared = t
                        .node(there)
                        .expect("declared")
                        .resolve()
                        .map_err(RunError::Resolve)?;
                    if declared.port() == 0 {
                        return Err(RunError::EphemeralPeer {
                            node: here.clone(),
                            peer: there.clone(),
                            addr: declared,
                        });
                    }
                    declared
                }
            };
            let link = t.link(here, there).copied().unwrap_or_default();
            let net = &mut nets[k];
            net.add_peer(there, addr, link);
            if sending {
                let edge = wired[i].producer.clone().expect("local producer half");
                net.add_sender(i as u32, there, edge, e.ty, control.clone());
            } else {
                let edge = wired[i].consumer.clone().expect("local consumer half");
                net.add_receiver(i as u32, there, edge, e.ty);
            }
        }
    }
    for n in &mut nets {
        n.start();
    }

    // Wait for the peers every local node needs.
    let waited = Instant::now();
    let limit = options
        .connect_timeout
        .unwrap_or(Duration::from_secs_f64(t.transport.connect_timeout_s));
    let mut last_log = Instant::now();
    loop {
        let missing: Vec<String> = nets
            .iter()
            .flat_map(|n| {
                n.needed_peers()
                    .into_iter()
                    .filter(|p| !n.board.get(p).up)
                    .map(move |p| (n.node.clone(), p))
            })
            .map(|(n, p): (String, String)| {
                let addr = addr_of(&p, &nets).map_or_else(
                    || t.node(&p).expect("declared").declared(),
                    |a| a.to_string(),
                );
                format!("{n} -> {p} @ {addr}")
            })
            .collect();
        if missing.is_empty() {
            break;
        }
        if let Ok(why) = failed.try_recv() {
            for n in &mut nets {
                n.shutdown(true);
            }
            return Err(RunError::Link(why));
        }
        if waited.elapsed() >= limit {
            for n in &mut nets {
                n.shutdown(true);
            }
            return Err(RunError::PeersUnreachable {
                peers: missing.join(", "),
                waited_s: waited.elapsed().as_secs_f64(),
            });
        }
        if last_log.elapsed() >= Duration::from_secs(2) {
            tracing::info!("waiting for peers: {}", missing.join(", "));
            last_log = Instant::now();
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let adopted = nets
        .iter()
        .flat_map(|n| n.needed_peers().into_iter().map(|p| n.board.get(&p).epoch))
        .filter(|&e| e > 0)
        .fold(epoch, u64::min);
    if !nets.is_empty() {
        tracing::info!(
            nodes = nets.len(),
            waited_ms = waited.elapsed().as_millis() as u64,
            "all peers up"
        );
    }
    let clock = SceneClock::new(adopted, t.scene_start_s, t.time_scale);
    Ok((wired, nets, clock))
}
