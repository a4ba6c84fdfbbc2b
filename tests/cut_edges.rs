//! Edges cut between nodes of one process: every node has its own UDP socket on loopback,
//! messages cross real sockets through laminar and the link emulator, and an edge keeps its
//! capacity and policy end to end.

mod common;

use std::sync::Arc;
use std::sync::atomic::Ordering;

use cloudlight::runtime::{EndReason, RunOptions};
use common::{Shared, plan_text, registry, run_plan, values};

fn two_nodes(body: &str) -> String {
    format!(
        r#"techniques = ["test"]
cluster = "cut-edge-tests"
secret = "not very secret"
[transport]
peer_timeout_ms = 1000
[[node]]
name = "a"
address = "127.0.0.1:0"
[[node]]
name = "b"
address = "127.0.0.1:0"
[[link]]
between = ["a", "b"]
latency_ms = 2.0
jitter_ms = 0.5
loss = 0.02
duplicate = 0.01
reorder = 0.01
{body}"#
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cut_block_edge_keeps_its_capacity_end_to_end() {
    let shared = Arc::new(Shared::default());
    let reg = registry(&shared);
    let p = plan_text(
        &two_nodes(
            r#"
[[stage]]
name = "p"
kind = "producer"
node = "a"
params = { count = 80 }
[[stage]]
name = "c"
kind = "consumer"
node = "b"
params = { work_ms = 3, check_capacity = 4 }
[[edge]]
from = "p"
to = "c"
capacity = 4
policy = "block"
"#,
        ),
        &reg,
    );
    assert!(p.edges[0].cut);
    let report = run_plan(&p, &reg, RunOptions::default()).await.unwrap();
    assert_eq!(report.end, EndReason::Finished);
    assert_eq!(report.undrained, 0);
    assert_eq!(
        values(&shared, "c"),
        (0..80).collect::<Vec<_>>(),
        "all delivered, in order, once"
    );
    assert_eq!(
        shared.violations.load(Ordering::SeqCst),
        0,
        "more than 4 messages were queued, in flight or in hand at once"
    );
    let producer = report
        .metrics
        .stages
        .iter()
        .find(|s| s.name == "p")
        .unwrap();
    assert!(
        producer.blocked_s > 0.0,
        "a slow remote consumer must slow the producer"
    );
    let sending = report
        .metrics
        .edges
        .iter()
        .find(|e| e.name == "p.out -> c.in")
        .unwrap();
    let receiving = report
        .metrics
        .edges
        .iter()
        .find(|e| e.name == "p.out -> c.in (rx)")
        .unwrap();
    assert!(sending.max_depth <= 4 && receiving.max_depth <= 4);
    assert_eq!((sending.dropped, receiving.dropped), (0, 0));
    let wire = sending
        .wire
        .as_ref()
        .expect("a cut edge reports wire figures");
    assert_eq!(wire.peer, "b");
    assert!(wire.wire_bytes > 0 && wire.rtt_ms > 0.0, "{wire:?}");
    assert_eq!(wire.lost + wire.refused, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cut_latest_edge_drops_oldest_and_counts_every_drop() {
    let shared = Arc::new(Shared::default());
    let reg = registry(&shared);
    let p = plan_text(
        &two_nodes(
            r#"
[[stage]]
name = "p"
kind = "producer"
node = "a"
params = { count = 300 }
[[stage]]
name = "c"
kind = "consumer"
node = "b"
params = { work_ms = 2 }
[[edge]]
from = "p"
to = "c"
capacity = 4
policy = "latest"
"#,
        ),
        &reg,
    );
    let report = run_plan(&p, &reg, RunOptions::default()).await.unwrap();
    let got = values(&shared, "c");
    let dropped: u64 = report.metrics.edges.iter().map(|e| e.dropped).sum();
    assert!(
        dropped > 0,
        "an unthrottled producer must overrun a 2 ms consumer"
    );
    assert_eq!(
        got.len() as u64 + dropped,
        300,
        "every message is delivered or counted as dropped"
    );
    assert!(
        got.windows(2).all(|w| w[0] < w[1]),
        "survivors keep their order"
    );
    assert_eq!(
        *got.last().unwrap(),
        299,
        "the newest message always gets through"
    );
    assert!(report.metrics.edges.iter().all(|e| e.max_depth <= 4));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nodes_of_another_secret_never_connect() {
    let shared = Arc::new(Shared::default());
    let reg = registry(&shared);
    // Node b listens with a different secret: a must never see it up.
    let text = two_nodes(
        "[[stage]]\nname = \"p\"\nkind = \"producer\"\nnode = \"a\"\n[[stage]]\nname = \"c\"\nkind = \"consumer\"\nnode = \"b\"\n[[edge]]\nfrom = \"p\"\nto = \"c\"\n",
    );
    let p = plan_text(&text, &reg);
    let mut other = p.clone();
    other.topology.secret = "another secret".into();
    let b_port = std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let a_port = std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    other.topology.nodes[0].address = format!("127.0.0.1:{a_port}").parse().unwrap();
    other.topology.nodes[1].address = format!("127.0.0.1:{b_port}").parse().unwrap();
    let mut mine = other.clone();
    mine.topology.secret = "not very secret".into();
    let quick = || RunOptions {
        connect_timeout: Some(std::time::Duration::from_millis(700)),
        ..RunOptions::default()
    };
    let b = {
        let (other, reg) = (other.clone(), reg.clone());
        tokio::spawn(async move {
            cloudlight::runtime::run(
                &other,
                &reg,
                RunOptions {
                    only_node: Some("b".into()),
                    ..quick()
                },
                std::future::pending(),
            )
            .await
        })
    };
    let a = cloudlight::runtime::run(
        &mine,
        &reg,
        RunOptions {
            only_node: Some("a".into()),
            ..quick()
        },
        std::future::pending(),
    )
    .await;
    let err = a.expect_err("a must not connect").to_string();
    assert!(
        err.contains("peers not reachable") && err.contains("a -> b"),
        "{err}"
    );
    assert!(b.await.unwrap().is_err());
    assert_eq!(shared.emitted.load(Ordering::SeqCst), 0, "nothing ran");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nodes_may_be_addressed_by_host_name() {
    let shared = Arc::new(Shared::default());
    let reg = registry(&shared);
    // `localhost` resolves from /etc/hosts: no query leaves the machine.
    let text = two_nodes(
        r#"
[[stage]]
name = "p"
kind = "producer"
node = "a"
params = { count = 20 }
[[stage]]
name = "c"
kind = "consumer"
node = "b"
[[edge]]
from = "p"
to = "c"
"#,
    )
    .replace("127.0.0.1:0", "localhost:0");
    let p = plan_text(&text, &reg);
    assert_eq!(p.topology.nodes[0].host.as_deref(), Some("localhost"));
    assert!(p.summary().contains("localhost:0"), "{}", p.summary());
    let report = run_plan(&p, &reg, RunOptions::default()).await.unwrap();
    assert_eq!(report.end, EndReason::Finished);
    assert_eq!(values(&shared, "c"), (0..20).collect::<Vec<_>>());
}
