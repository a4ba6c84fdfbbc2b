//! What a run does when its network fails: each failure is either harmless and counted, or
//! a named failure of the run — never a silent stall that exits 0.

use std::time::{Duration, Instant};

use cloudlight::runtime::{Cluster, EndReason, Plan, RunError, RunOptions, RunReport};

fn free_ports(n: usize) -> Vec<u16> {
    let sockets: Vec<_> = (0..n)
        .map(|_| std::net::UdpSocket::bind("127.0.0.1:0").unwrap())
        .collect();
    sockets
        .iter()
        .map(|s| s.local_addr().unwrap().port())
        .collect()
}

/// Runs `plan` for `duration` (or until it ends by itself), within a minute.
async fn run(plan: &Plan, duration: Option<Duration>) -> Result<RunReport, RunError> {
    let registry = cloudlight::actors::registry();
    let options = RunOptions {
        duration,
        ..RunOptions::default()
    };
    tokio::time::timeout(
        Duration::from_secs(60),
        cloudlight::runtime::run(plan, &registry, options, std::future::pending()),
    )
    .await
    .expect("the run ends within a minute")
}

fn plan(text: &str) -> Plan {
    Plan::from_str("test.toml", text, &cloudlight::actors::registry())
        .unwrap_or_else(|e| panic!("{e}"))
}

/// Two nodes and two probe pipelines; `edges` lists the edges in the file's order.
fn two_pipelines(ports: &[u16], edges: &[(&str, &str)]) -> String {
    let mut t = format!(
        r#"techniques = ["probe"]
cluster = "mismatch-test"
secret = "s"
duration_s = 5.0
[transport]
connect_timeout_s = 20
[[node]]
name = "a"
address = "127.0.0.1:{}"
[[node]]
name = "b"
address = "127.0.0.1:{}"
[[stage]]
name = "s1"
kind = "probe_source"
node = "a"
params = {{ rate_hz = 50.0 }}
[[stage]]
name = "s2"
kind = "probe_source"
node = "a"
params = {{ rate_hz = 50.0 }}
[[stage]]
name = "k1"
kind = "probe_sink"
node = "b"
[[stage]]
name = "k2"
kind = "probe_sink"
node = "b"
"#,
        ports[0], ports[1]
    );
    for (from, to) in edges {
        t.push_str(&format!("[[edge]]\nfrom = \"{from}\"\nto = \"{to}\"\n"));
    }
    t
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nodes_with_different_topologies_refuse_each_other_and_say_so() {
    // The same stages, edges declared in another order: edge ids differ, so every message
    // would land on the wrong edge. Both nodes must refuse, quickly and by name.
    let ports = free_ports(2);
    let a = plan(&two_pipelines(&ports, &[("s1", "k1"), ("s2", "k2")]));
    let b = plan(&two_pipelines(&ports, &[("s2", "k2"), ("s1", "k1")]));
    let registry = cloudlight::actors::registry();
    let options = |node: &str| RunOptions {
        only_node: Some(node.into()),
        ..RunOptions::default()
    };
    let started = Instant::now();
    let (ra, rb) = tokio::join!(
        cloudlight::runtime::run(&a, &registry, options("a"), std::future::pending()),
        cloudlight::runtime::run(&b, &registry, options("b"), std::future::pending()),
    );
    for r in [ra, rb] {
        match r {
            Err(RunError::Link(why)) => assert!(why.contains("different topology"), "{why}"),
            Err(e) => panic!("expected a topology mismatch, got: {e}"),
            Ok(r) => panic!("a mismatched cluster ran: {:?}", r.end),
        }
    }
    assert!(
        started.elapsed() < Duration::from_secs(10),
        "refused after {:?}, not at the connect timeout",
        started.elapsed()
    );
}

fn two_nodes(body: &str) -> String {
    format!(
        r#"techniques = ["probe"]
cluster = "failure-test"
secret = "s"
[transport]
peer_timeout_ms = 500
[[node]]
name = "a"
address = "127.0.0.1:0"
[[node]]
name = "b"
address = "127.0.0.1:0"
{body}"#
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn messages_over_the_transport_limit_are_dropped_counted_return_their_credit_and_fail_the_run()
 {
    // Messages of 64 MiB of payload, which encode to a few bytes more than the transport
    // carries, on a cut `block` edge of capacity 2: if a dropped message kept its credit, the
    // source would block for good after two. (A file may not ask for such a payload any more:
    // the plan is changed after validation, as a stage sending an unexpectedly large message
    // would.)
    let mut p = plan(&two_nodes(
        r#"
[[stage]]
name = "source"
kind = "probe_source"
node = "a"
params = { payload_bytes = 1000, count = 5 }
[[stage]]
name = "sink"
kind = "probe_sink"
node = "b"
[[edge]]
from = "source"
to = "sink"
capacity = 2
policy = "block"
"#,
    ));
    let source = p
        .topology
        .stages
        .iter_mut()
        .find(|s| s.name == "source")
        .unwrap();
    source
        .params
        .insert("payload_bytes".into(), toml::Value::Integer(64 << 20));
    // It ends by itself: no credit was kept.
    let report = run(&p, None).await;
    // Every message was dropped: a run that carried nothing across its cut has failed.
    let Err(RunError::NetworkFailed { error, report }) = report else {
        panic!("a run that delivered nothing succeeded: {report:?}");
    };
    assert!(
        error.contains("cut edge `source.out -> sink.in` delivered none of its 5 messages (5 over"),
        "{error}"
    );
    assert_eq!(report.end, EndReason::Finished, "it ended by itself");
    let edge = report
        .metrics
        .edges
        .iter()
        .find(|e| e.name == "source.out -> sink.in")
        .unwrap();
    assert_eq!(edge.dropped, 5, "{edge:?}");
    assert_eq!(edge.wire.as_ref().unwrap().oversize, 5);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_panicking_transport_thread_fails_the_run_by_name() {
    let p = plan(&two_nodes(
        r#"
[[stage]]
name = "source"
kind = "probe_source"
node = "a"
params = { rate_hz = 100.0 }
[[stage]]
name = "sink"
kind = "probe_sink"
node = "b"
[[edge]]
from = "source"
to = "sink"
"#,
    ));
    let registry = cloudlight::actors::registry();
    let options = RunOptions {
        duration: Some(Duration::from_secs(30)),
        ..RunOptions::default()
    };
    let cluster = Cluster::start(&p, &registry, options).await.unwrap();
    assert!(cluster.inject_transport_panic("b"));
    let started = Instant::now();
    let r = tokio::time::timeout(Duration::from_secs(20), cluster.run(std::future::pending()))
        .await
        .expect("the run ends by itself");
    match r {
        Err(RunError::NetworkFailed { error, report }) => {
            assert!(
                error.contains("node `b`") && error.contains("panicked"),
                "{error}"
            );
            assert_eq!(report.metrics.failure.as_deref(), Some(error.as_str()));
        }
        other => panic!("expected a network failure, got {:?}", other.map(|r| r.end)),
    }
    assert!(started.elapsed() < Duration::from_secs(5));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_edge_holds_no_more_bytes_than_its_bound_whatever_its_capacity() {
    // 100 kB messages into a relay that takes 100 ms each, across a cut edge of capacity
    // 100,000 but 1 MiB: the source may run ahead of the relay by about ten messages, not by
    // 100,000 (which would be 10 GB).
    let p = plan(&two_nodes(
        r#"
[[stage]]
name = "source"
kind = "probe_source"
node = "a"
params = { payload_bytes = 100000 }
[[stage]]
name = "relay"
kind = "probe_relay"
node = "b"
params = { work_ms = 100.0 }
[[stage]]
name = "sink"
kind = "probe_sink"
node = "b"
[[edge]]
from = "source"
to = "relay"
capacity = 100000
max_bytes = 1048576
[[edge]]
from = "relay"
to = "sink"
"#,
    ));
    assert!(
        p.warnings
            .iter()
            .any(|w| w.message.contains("it holds 10 at a time")),
        "{:?}",
        p.warnings
    );
    let report = run(&p, Some(Duration::from_secs(2)))
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    let stage = |name: &str| {
        report
            .metrics
            .stages
            .iter()
            .find(|s| s.name == name)
            .unwrap()
            .clone()
    };
    let sent = stage("source").report.unwrap()["sent"].as_u64().unwrap();
    let relayed = stage("relay").handled;
    assert!(relayed >= 5, "{relayed}");
    assert!(
        sent <= relayed + 12,
        "the source ran {sent} messages ahead of a relay that handled {relayed}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_link_paced_too_slowly_stalls_the_run_and_every_message_is_counted() {
    // 1 bit/s: after the first burst, nothing moves; the stall fails the run, and what the
    // source sent is received, given up (`lost`) or still queued, never nowhere.
    let p = plan(
        &two_nodes(
            r#"
[[stage]]
name = "source"
kind = "probe_source"
node = "a"
params = { rate_hz = 100.0, payload_bytes = 20000 }
[[stage]]
name = "sink"
kind = "probe_sink"
node = "b"
[[edge]]
from = "source"
to = "sink"
"#,
        )
        .replace(
            "peer_timeout_ms = 500",
            "peer_timeout_ms = 500\npacing_mbps = 1e-6\nstall_timeout_s = 1.0",
        ),
    );
    let started = Instant::now();
    let result = run(&p, Some(Duration::from_secs(20))).await;
    let Err(RunError::NetworkFailed { error, report }) = result else {
        panic!("a link that carries nothing did not fail the run: {result:?}");
    };
    assert!(error.contains("stalled"), "{error}");
    assert!(
        started.elapsed() < Duration::from_secs(15),
        "the stall fired late"
    );
    let edge = |name: &str| {
        report
            .metrics
            .edges
            .iter()
            .find(|e| e.name == name)
            .unwrap()
            .clone()
    };
    let (tx, rx) = (
        edge("source.out -> sink.in"),
        edge("source.out -> sink.in (rx)"),
    );
    let lost = tx.wire.as_ref().unwrap().lost;
    assert!(lost > 0, "{tx:?}");
    assert_eq!(
        tx.messages,
        rx.messages + lost + tx.depth as u64,
        "sent {tx:?}\nreceived {rx:?}"
    );
}
