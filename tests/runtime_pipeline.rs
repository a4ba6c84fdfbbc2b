//! The runtime proven on a small synthetic pipeline (test-only stages): backpressure,
//! `latest` drops, per-edge order, fan-out/fan-in, draining shutdown and failure reporting.

mod common;

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use cloudlight::runtime::{EndReason, Plan, RunError, RunOptions, RunStatus, StageRegistry};
use common::{Shared, plan, registry, run_plan, values};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn block_bounds_depth_and_slows_the_producer() {
    let shared = Arc::new(Shared::default());
    let reg = registry(&shared);
    let p = plan(
        r#"
[[stage]]
name = "p"
kind = "producer"
node = "n"
params = { count = 60 }
[[stage]]
name = "c"
kind = "consumer"
node = "n"
params = { work_ms = 2, check_capacity = 3 }
[[edge]]
from = "p"
to = "c"
capacity = 3
policy = "block"
"#,
        &reg,
    );
    let report = run_plan(&p, &reg, RunOptions::default()).await.unwrap();
    assert_eq!(report.end, EndReason::Finished);
    assert_eq!(values(&shared, "c"), (0..60).collect::<Vec<_>>());
    assert_eq!(
        shared.violations.load(Ordering::SeqCst),
        0,
        "emitted > handled + capacity"
    );
    let edge = &report.metrics.edges[0];
    assert!(edge.max_depth <= 3, "max depth {}", edge.max_depth);
    assert_eq!(edge.dropped, 0);
    assert_eq!(edge.messages, 60);
    let producer = report
        .metrics
        .stages
        .iter()
        .find(|s| s.name == "p")
        .unwrap();
    assert!(producer.blocked_s > 0.0, "the producer never waited");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn latest_bounds_depth_and_counts_every_drop() {
    let shared = Arc::new(Shared::default());
    let reg = registry(&shared);
    let p = plan(
        r#"
[[stage]]
name = "p"
kind = "producer"
node = "n"
params = { count = 400 }
[[stage]]
name = "c"
kind = "consumer"
node = "n"
params = { work_ms = 1 }
[[edge]]
from = "p.out"
to = "c.in"
capacity = 4
policy = "latest"
"#,
        &reg,
    );
    let report = run_plan(&p, &reg, RunOptions::default()).await.unwrap();
    let got = values(&shared, "c");
    let edge = &report.metrics.edges[0];
    assert!(edge.max_depth <= 4);
    assert_eq!(edge.messages, 400);
    assert_eq!(
        got.len() as u64 + edge.dropped,
        400,
        "every message is delivered or counted as dropped"
    );
    assert!(
        edge.dropped > 0,
        "a 1 ms consumer cannot keep up with an unthrottled producer"
    );
    assert!(
        got.windows(2).all(|w| w[0] < w[1]),
        "survivors keep their order"
    );
    assert_eq!(
        *got.last().unwrap(),
        399,
        "the newest message is never dropped"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn order_is_preserved_along_a_chain() {
    let shared = Arc::new(Shared::default());
    let reg = registry(&shared);
    let p = plan(
        r#"
[defaults]
capacity = 2
[[stage]]
name = "p"
kind = "producer"
node = "n"
params = { count = 2000 }
[[stage]]
name = "r"
kind = "relay"
node = "n"
[[stage]]
name = "c"
kind = "consumer"
node = "n"
[[edge]]
from = "p"
to = "r"
[[edge]]
from = "r"
to = "c"
"#,
        &reg,
    );
    let report = run_plan(&p, &reg, RunOptions::default()).await.unwrap();
    assert_eq!(report.end, EndReason::Finished);
    assert_eq!(values(&shared, "c"), (0..2000).collect::<Vec<_>>());
    assert!(report.metrics.edges.iter().all(|e| e.max_depth <= 2));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fan_out_delivers_each_message_once_to_every_replica_without_copies() {
    let shared = Arc::new(Shared::default());
    let reg = registry(&shared);
    let p = plan(
        r#"
[[stage]]
name = "p"
kind = "producer"
node = "n"
params = { count = 300 }
[[stage]]
name = "c"
kind = "consumer"
node = "n"
replicas = 3
[[edge]]
from = "p"
to = "c"
"#,
        &reg,
    );
    let report = run_plan(&p, &reg, RunOptions::default()).await.unwrap();
    assert_eq!(shared.emitted.load(Ordering::SeqCst), 300, "computed once");
    let received = shared.received.lock().unwrap();
    for r in 0..3 {
        let got: Vec<u64> = received[&format!("c[{r}]")].iter().map(|x| x.1).collect();
        assert_eq!(got, (0..300).collect::<Vec<_>>(), "replica {r}");
    }
    for i in 0..300 {
        let addrs: Vec<usize> = (0..3).map(|r| received[&format!("c[{r}]")][i].2).collect();
        assert!(
            addrs.iter().all(|&a| a == addrs[0]),
            "message {i} was copied per replica"
        );
    }
    assert_eq!(report.metrics.edges.len(), 3);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fan_in_and_one_to_one_replica_wiring() {
    let shared = Arc::new(Shared::default());
    let reg = registry(&shared);
    let p = plan(
        r#"
[[stage]]
name = "p"
kind = "producer"
node = "n"
replicas = 2
params = { count = 50 }
[[stage]]
name = "r"
kind = "relay"
node = "n"
replicas = 2
[[stage]]
name = "c"
kind = "consumer"
node = "n"
[[edge]]
from = "p"
to = "r"
[[edge]]
from = "r"
to = "c"
"#,
        &reg,
    );
    run_plan(&p, &reg, RunOptions::default()).await.unwrap();
    let received = shared.received.lock().unwrap();
    for r in 0..2 {
        let from_p: Vec<u64> = received[&format!("r[{r}]")].iter().map(|x| x.1).collect();
        assert_eq!(
            from_p,
            (0..50).collect::<Vec<_>>(),
            "one-to-one p[{r}] -> r[{r}]"
        );
        assert!(
            received[&format!("r[{r}]")]
                .iter()
                .all(|x| x.0 == format!("p[{r}]"))
        );
        let at_sink: Vec<u64> = received["c"]
            .iter()
            .filter(|x| x.0 == format!("r[{r}]"))
            .map(|x| x.1)
            .collect();
        assert_eq!(
            at_sink,
            (0..50).collect::<Vec<_>>(),
            "fan-in keeps per-edge order from r[{r}]"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_drains_and_stops_every_actor() {
    let shared = Arc::new(Shared::default());
    let reg = registry(&shared);
    let p = plan(
        r#"
[[stage]]
name = "p"
kind = "producer"
node = "n"
[[stage]]
name = "r"
kind = "relay"
node = "n"
params = { work_ms = 1 }
[[stage]]
name = "c"
kind = "consumer"
node = "n"
replicas = 2
[[edge]]
from = "p"
to = "r"
capacity = 8
[[edge]]
from = "r"
to = "c"
capacity = 8
"#,
        &reg,
    );
    let dir = tempfile::tempdir().unwrap();
    let options = RunOptions {
        duration: Some(Duration::from_millis(400)),
        out_dir: Some(dir.path().to_path_buf()),
        metrics_interval: Duration::from_millis(100),
        ..RunOptions::default()
    };
    let report = run_plan(&p, &reg, options).await.unwrap();
    assert_eq!(report.end, EndReason::Duration);
    assert_eq!(
        report.undrained, 0,
        "queued messages were handled before stopping"
    );
    assert_eq!(report.started, 4);
    assert_eq!(
        report.stopped.len(),
        4,
        "every actor terminated: {:?}",
        report.stopped
    );
    assert_eq!(
        shared.stopped.load(Ordering::SeqCst),
        4,
        "every stage got on_stop"
    );
    let emitted = shared.emitted.load(Ordering::SeqCst);
    assert!(emitted > 0);
    for c in ["c[0]", "c[1]"] {
        assert_eq!(
            values(&shared, c),
            (0..emitted).collect::<Vec<_>>(),
            "{c}: nothing lost on shutdown"
        );
    }
    let json: cloudlight::runtime::MetricsSnapshot =
        serde_json::from_slice(&std::fs::read(dir.path().join("metrics.json")).unwrap()).unwrap();
    assert_eq!(json.status, RunStatus::Finished);
    assert_eq!(json.stages.len(), 4);
    assert_eq!(json.edges.iter().map(|e| e.depth).sum::<usize>(), 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stop_request_ends_the_run_cleanly() {
    let shared = Arc::new(Shared::default());
    let reg = registry(&shared);
    let p = plan(
        "[[stage]]\nname = \"p\"\nkind = \"producer\"\nnode = \"n\"\n[[stage]]\nname = \"c\"\nkind = \"consumer\"\nnode = \"n\"\n[[edge]]\nfrom = \"p\"\nto = \"c\"\n",
        &reg,
    );
    let stop = tokio::time::sleep(Duration::from_millis(150));
    let report = tokio::time::timeout(
        Duration::from_secs(30),
        cloudlight::runtime::run(&p, &reg, RunOptions::default(), stop),
    )
    .await
    .unwrap()
    .unwrap();
    assert_eq!(report.end, EndReason::Stopped);
    assert_eq!(report.undrained, 0);
    assert_eq!(
        values(&shared, "c").len() as u64,
        shared.emitted.load(Ordering::SeqCst)
    );
}

fn failing_plan(reg: &StageRegistry, consumer_params: &str) -> Plan {
    plan(
        &format!(
            r#"
[[stage]]
name = "p"
kind = "producer"
node = "n"
[[stage]]
name = "r"
kind = "relay"
node = "n"
[[stage]]
name = "bad"
kind = "consumer"
node = "n"
params = {consumer_params}
[[edge]]
from = "p"
to = "r"
capacity = 1
[[edge]]
from = "r"
to = "bad"
capacity = 1
"#
        ),
        reg,
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_failing_stage_is_reported_by_name_and_stops_the_run() {
    let shared = Arc::new(Shared::default());
    let reg = registry(&shared);
    let p = failing_plan(&reg, "{ fail_at = 5 }");
    let dir = tempfile::tempdir().unwrap();
    let options = RunOptions {
        out_dir: Some(dir.path().to_path_buf()),
        ..RunOptions::default()
    };
    match run_plan(&p, &reg, options).await {
        Err(RunError::StageFailed {
            stage,
            error,
            report,
        }) => {
            assert_eq!(stage, "bad");
            assert!(error.contains("cannot handle message 5"), "{error}");
            assert_eq!(report.end, EndReason::Failed);
            assert_eq!(report.metrics.status, RunStatus::Failed);
            for name in ["p", "r"] {
                assert!(
                    report.stopped.iter().any(|s| s == name),
                    "{name} was not stopped"
                );
            }
            let json: cloudlight::runtime::MetricsSnapshot =
                serde_json::from_slice(&std::fs::read(dir.path().join("metrics.json")).unwrap())
                    .unwrap();
            assert_eq!(json.status, RunStatus::Failed);
            assert!(json.failure.unwrap().contains("`bad`"));
        }
        other => panic!("expected a stage failure, got {other:?}"),
    }
    assert_eq!(values(&shared, "bad"), (0..5).collect::<Vec<_>>());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_panicking_stage_is_reported_by_name() {
    let shared = Arc::new(Shared::default());
    let reg = registry(&shared);
    let p = failing_plan(&reg, "{ panic_at = 3 }");
    match run_plan(&p, &reg, RunOptions::default()).await {
        Err(RunError::StageFailed { stage, error, .. }) => {
            assert_eq!(stage, "bad");
            assert!(error.contains("blew up on message 3"), "{error}");
        }
        other => panic!("expected a stage failure, got {other:?}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stage_that_cannot_start_is_reported_and_nothing_runs() {
    let shared = Arc::new(Shared::default());
    let reg = registry(&shared);
    let p = plan(
        "[[stage]]\nname = \"p\"\nkind = \"producer\"\nnode = \"n\"\n[[stage]]\nname = \"gpu\"\nkind = \"broken\"\nnode = \"n\"\n",
        &reg,
    );
    match run_plan(&p, &reg, RunOptions::default()).await {
        Err(RunError::Start { stage, error }) => {
            assert_eq!(stage, "gpu");
            assert!(error.contains("no device available"), "{error}");
        }
        other => panic!("expected a start failure, got {other:?}"),
    }
    assert_eq!(
        shared.emitted.load(Ordering::SeqCst),
        0,
        "no stage ticked before all were ready"
    );
}
