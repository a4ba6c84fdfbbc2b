//! Test-only stages shared by the integration tests: a counting producer, a recording
//! consumer/relay with a backpressure invariant check and fault injection, and helpers.
#![allow(dead_code)]

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use cloudlight::runtime::{
    EdgeSettings, Input, NextTick, Plan, Policy, Port, RunError, RunOptions, RunReport, Stage,
    StageCtx, StageKind, StageRegistry,
};
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Num(pub u64);

/// What a consumer saw: (producer instance, value, address of the shared message).
pub type Seen = Vec<(String, u64, usize)>;

#[derive(Default)]
pub struct Shared {
    pub emitted: AtomicU64,
    pub stopped: AtomicU64,
    /// Consumer instance -> what it saw.
    pub received: Mutex<HashMap<String, Seen>>,
    /// Times a consumer saw more messages emitted than `handled + capacity` allows.
    pub violations: AtomicU64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ProducerParams {
    count: Option<u64>,
}

struct Producer {
    count: Option<u64>,
    next: u64,
    shared: Arc<Shared>,
}

#[async_trait::async_trait]
impl Stage for Producer {
    async fn on_tick(&mut self, ctx: &mut StageCtx) -> anyhow::Result<NextTick> {
        if self.count.is_some_and(|c| self.next >= c) {
            return Ok(NextTick::Never);
        }
        let t = ctx.scene_time_s();
        ctx.send(NUM_OUT, t, Num(self.next)).await?;
        self.next += 1;
        self.shared.emitted.fetch_add(1, Ordering::SeqCst);
        Ok(NextTick::Now)
    }
    async fn on_stop(&mut self, _: &mut StageCtx) -> anyhow::Result<()> {
        self.shared.stopped.fetch_add(1, Ordering::SeqCst);
        Ok(())
    }
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct ConsumerParams {
    #[serde(default)]
    work_ms: u64,
    /// Capacity of the input edge, for the backpressure invariant (block edges only).
    check_capacity: Option<u64>,
    fail_at: Option<u64>,
    panic_at: Option<u64>,
}

struct Consumer {
    p: ConsumerParams,
    handled: u64,
    shared: Arc<Shared>,
    forward: bool,
}

#[async_trait::async_trait]
impl Stage for Consumer {
    async fn on_input(&mut self, ctx: &mut StageCtx, input: Input) -> anyhow::Result<()> {
        let msg = input.on(NUM_IN)?;
        if self.p.fail_at == Some(msg.body.0) {
            anyhow::bail!("cannot handle message {}", msg.body.0);
        }
        if self.p.panic_at == Some(msg.body.0) {
            panic!("stage blew up on message {}", msg.body.0);
        }
        self.shared
            .received
            .lock()
            .unwrap()
            .entry(ctx.name().to_string())
            .or_default()
            .push((
                input.from().to_string(),
                msg.body.0,
                Arc::as_ptr(&msg) as usize,
            ));
        if self.p.work_ms > 0 {
            tokio::time::sleep(Duration::from_millis(self.p.work_ms)).await;
        }
        // Still handling this message (its permit is held): at most `cap` messages may be
        // queued or in hand, so at most `handled + cap` can have been emitted.
        if let Some(cap) = self.p.check_capacity
            && self.shared.emitted.load(Ordering::SeqCst) > self.handled + cap
        {
            self.shared.violations.fetch_add(1, Ordering::SeqCst);
        }
        if self.forward {
            ctx.send(NUM_OUT, msg.scene_time_s, msg.body.clone())
                .await?;
        }
        self.handled += 1;
        Ok(())
    }
    async fn on_stop(&mut self, _: &mut StageCtx) -> anyhow::Result<()> {
        self.shared.stopped.fetch_add(1, Ordering::SeqCst);
        Ok(())
    }
}

struct FailsToStart;

#[async_trait::async_trait]
impl Stage for FailsToStart {
    async fn on_start(&mut self, _: &mut StageCtx) -> anyhow::Result<()> {
        anyhow::bail!("no device available")
    }
}

pub const NUM_IN: Port<Num> = Port::new("in");
pub const NUM_OUT: Port<Num> = Port::new("out");

const DEFAULT_IN: EdgeSettings = EdgeSettings {
    capacity: 4,
    policy: Policy::Block,
};

pub fn registry(shared: &Arc<Shared>) -> StageRegistry {
    let mut r = StageRegistry::new();
    let s = shared.clone();
    r.register(
        StageKind::new("producer", "test", "emits 0, 1, 2, ...", move |setup| {
            let p: ProducerParams = setup.params()?;
            Ok(Box::new(Producer {
                count: p.count,
                next: 0,
                shared: s.clone(),
            }))
        })
        .output(NUM_OUT)
        .params::<ProducerParams>(),
    );
    for (name, forward) in [("consumer", false), ("relay", true)] {
        let s = shared.clone();
        let mut kind = StageKind::new(name, "test", "records what it receives", move |setup| {
            Ok(Box::new(Consumer {
                p: setup.params()?,
                handled: 0,
                shared: s.clone(),
                forward,
            }))
        })
        .input(NUM_IN, DEFAULT_IN)
        .params::<ConsumerParams>();
        if forward {
            kind = kind.output(NUM_OUT);
        }
        r.register(kind);
    }
    r.register(StageKind::new(
        "broken",
        "test",
        "fails in on_start",
        |_| Ok(Box::new(FailsToStart)),
    ));
    r
}

pub fn plan(toml: &str, registry: &StageRegistry) -> Plan {
    let text = format!(
        "techniques = [\"test\"]\n[[node]]\nname = \"n\"\naddress = \"127.0.0.1:0\"\n{toml}"
    );
    Plan::from_str("test.toml", &text, registry).unwrap_or_else(|e| panic!("{e}"))
}

pub async fn run_plan(
    plan: &Plan,
    registry: &StageRegistry,
    options: RunOptions,
) -> Result<RunReport, RunError> {
    tokio::time::timeout(
        Duration::from_secs(60),
        cloudlight::runtime::run(plan, registry, options, std::future::pending()),
    )
    .await
    .expect("the run must end by itself")
}

pub fn values(shared: &Shared, consumer: &str) -> Vec<u64> {
    shared.received.lock().unwrap()[consumer]
        .iter()
        .map(|r| r.1)
        .collect()
}

/// A plan from a full topology text (with its own nodes).
pub fn plan_text(text: &str, registry: &StageRegistry) -> Plan {
    Plan::from_str("test.toml", text, registry).unwrap_or_else(|e| panic!("{e}"))
}

/// Runs a full topology text with the project's stages and the test stage `unit_gate`
/// (which drops a window of access units: outages, late joins); it must end by itself.
pub async fn run_gated(text: &str) -> RunReport {
    let mut registry = cloudlight::actors::registry();
    register_unit_gate(&mut registry);
    run_plan(
        &plan_text(text, &registry),
        &registry,
        RunOptions::default(),
    )
    .await
    .unwrap_or_else(|e| panic!("{e}"))
}

/// The report `stage` published in a run's metrics.
pub fn report<'a>(
    m: &'a cloudlight::runtime::MetricsSnapshot,
    stage: &str,
) -> &'a serde_json::Value {
    m.stages
        .iter()
        .find(|s| s.name == stage)
        .and_then(|s| s.report.as_ref())
        .unwrap_or_else(|| panic!("no report from {stage}"))
}

/// A number of a report.
pub fn f(v: &serde_json::Value, key: &str) -> f64 {
    v[key]
        .as_f64()
        .unwrap_or_else(|| panic!("{key} missing in {v}"))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct GateParams {
    /// First unit index dropped.
    #[serde(default)]
    drop_from: u64,
    /// First unit index passed on again.
    drop_until: u64,
}

/// Drops the access units of indices `drop_from..drop_until` and passes the others on: a
/// client joining a running stream late (`drop_from = 0`) or an outage in the middle.
struct UnitGate {
    p: GateParams,
}

const UNITS_IN: Port<cloudlight::actors::wire::VideoMsg> = Port::new("in");
const UNITS_OUT: Port<cloudlight::actors::wire::VideoMsg> = Port::new("out");

#[async_trait::async_trait]
impl Stage for UnitGate {
    async fn on_input(&mut self, ctx: &mut StageCtx, input: Input) -> anyhow::Result<()> {
        let msg = input.on(UNITS_IN)?;
        if !(self.p.drop_from..self.p.drop_until).contains(&msg.body.index) {
            ctx.send(UNITS_OUT, msg.scene_time_s, msg.body.clone())
                .await?;
        }
        Ok(())
    }
}

/// Registers `unit_gate` (technique `test`): see [`UnitGate`].
pub fn register_unit_gate(r: &mut StageRegistry) {
    r.register(
        StageKind::new("unit_gate", "test", "drops a window of access units", |s| {
            Ok(Box::new(UnitGate { p: s.params()? }))
        })
        .input(
            UNITS_IN,
            EdgeSettings {
                capacity: 16,
                policy: Policy::Block,
            },
        )
        .output(UNITS_OUT)
        .params::<GateParams>(),
    );
}
