//! The probe technique: a source, a relay and a sink that carry pattern-filled messages
//! through a topology and measure it — throughput, per-hop latency, age of scene time at
//! the sink, order and integrity — the way iperf qualifies a link. Users run it to qualify
//! a placement or a link profile before running a lighting technique on it, and the
//! runtime's and transport's tests use it as their synthetic pipeline.

use std::collections::HashMap;
use std::time::Duration;

use cloudlight_runtime::clock::now_unix_ns;
use cloudlight_runtime::{
    Cadence, CheckParams, EdgeSettings, Input, Latency, NextTick, Policy, Port, Stage, StageCtx,
    StageKind, StageRegistry, StageSetup, check_range,
};
use serde::Deserialize;

use crate::wire::ProbeMsg;

/// Technique name of the probe stages.
pub const TECHNIQUE: &str = "probe";

/// Probe messages into a relay or a sink.
pub const IN: Port<ProbeMsg> = Port::new("in");

/// Probe messages out of a source or a relay.
pub const OUT: Port<ProbeMsg> = Port::new("out");

/// Parameters of `probe_source`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SourceParams {
    /// Messages per second; absent: as fast as the edges accept them.
    pub rate_hz: Option<f64>,
    /// Payload bytes per message.
    #[serde(default = "default_payload")]
    pub payload_bytes: usize,
    /// Stop after this many messages; absent: until the run stops.
    pub count: Option<u64>,
}

fn default_payload() -> usize {
    64
}

/// Emits `ProbeMsg`s on `out`, at a fixed rate or as fast as backpressure allows.
pub struct ProbeSource {
    params: SourceParams,
    sent: u64,
    /// At `rate_hz`, keeping the average rate after a stall.
    cadence: Option<Cadence>,
}

#[async_trait::async_trait]
impl Stage for ProbeSource {
    async fn on_tick(&mut self, ctx: &mut StageCtx) -> anyhow::Result<NextTick> {
        if self.params.count.is_some_and(|c| self.sent >= c) || ctx.is_stopping() {
            return Ok(NextTick::Never);
        }
        if let Some(c) = &mut self.cadence {
            c.begin();
        }
        let msg = ProbeMsg::new(ctx.seed(), self.sent, self.params.payload_bytes);
        let t = ctx.scene_time_s();
        ctx.send(OUT, t, msg).await?;
        self.sent += 1;
        let overruns = self.cadence.as_ref().map_or(0, Cadence::overruns);
        ctx.report(serde_json::json!({ "sent": self.sent, "overruns": overruns }));
        if self.params.count.is_some_and(|c| self.sent >= c) {
            return Ok(NextTick::Never);
        }
        Ok(self
            .cadence
            .as_mut()
            .map_or(NextTick::Now, Cadence::end_tick))
    }
}

/// Parameters of `probe_relay`.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RelayParams {
    /// Service time to emulate per message, milliseconds.
    #[serde(default)]
    pub work_ms: f64,
    /// Fail (return an error) on the message after this many: fault injection for failure
    /// handling experiments.
    pub fail_after: Option<u64>,
}

/// Forwards each message from `in` to `out`, keeping its scene time.
pub struct ProbeRelay {
    params: RelayParams,
    handled: u64,
}

#[async_trait::async_trait]
impl Stage for ProbeRelay {
    async fn on_input(&mut self, ctx: &mut StageCtx, input: Input) -> anyhow::Result<()> {
        if self.params.fail_after.is_some_and(|n| self.handled >= n) {
            anyhow::bail!(
                "injected failure after {} messages (fail_after)",
                self.handled
            );
        }
        let msg = input.on(IN)?;
        if self.params.work_ms > 0.0 {
            tokio::time::sleep(Duration::from_secs_f64(self.params.work_ms / 1000.0)).await;
        }
        ctx.send(OUT, msg.scene_time_s, msg.body.clone()).await?;
        self.handled += 1;
        Ok(())
    }
}

/// Parameters of `probe_sink`.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SinkParams {
    /// Service time to emulate per message, milliseconds.
    #[serde(default)]
    pub work_ms: f64,
}

/// Receives messages and reports count, order, integrity, hop latency and scene-time age,
/// and which of its source's messages never arrived.
pub struct ProbeSink {
    params: SinkParams,
    received: u64,
    bytes: u64,
    out_of_order: u64,
    corrupt: u64,
    /// Messages skipped in the source's sequence (gaps in `index` per upstream instance):
    /// dropped by a `latest` edge, lost with a restarted peer, or lost inside a node that
    /// crashed — wherever on the path, so that every message sent is counted somewhere.
    missing: u64,
    last_index: HashMap<String, u64>,
    hop_latency: Latency,
    age: Latency,
}

impl ProbeSink {
    fn report(&self) -> serde_json::Value {
        serde_json::json!({
            "received": self.received,
            "bytes": self.bytes,
            "out_of_order": self.out_of_order,
            "corrupt": self.corrupt,
            "missing": self.missing,
            "last_index": self.last_index.values().max(),
            "hop_latency_ms_p50": self.hop_latency.p50_ms(),
            "hop_latency_ms_p99": self.hop_latency.p99_ms(),
            "age_ms_p50": self.age.p50_ms(),
            "age_ms_p99": self.age.p99_ms(),
        })
    }
}

#[async_trait::async_trait]
impl Stage for ProbeSink {
    async fn on_input(&mut self, ctx: &mut StageCtx, input: Input) -> anyhow::Result<()> {
        let msg = input.on(IN)?;
        let now = now_unix_ns();
        self.received += 1;
        self.bytes += msg.body.payload.len() as u64;
        let last = self.last_index.get(input.from()).copied();
        match last {
            Some(last) if msg.body.index <= last => self.out_of_order += 1,
            // The first message from this upstream is index 0 unless some went missing.
            _ => self.missing += msg.body.index - last.map_or(0, |l| l + 1),
        }
        if last.is_none_or(|l| msg.body.index > l) {
            self.last_index
                .insert(input.from().to_string(), msg.body.index);
        }
        if !msg.body.is_intact(ctx.seed()) {
            self.corrupt += 1;
            tracing::warn!(
                stage = ctx.name(),
                index = msg.body.index,
                "corrupt probe payload"
            );
        }
        self.hop_latency.record(Duration::from_nanos(
            now.saturating_sub(msg.produced_unix_ns),
        ));
        let age_s = (ctx.clock().scene_time_at_s(now) - msg.scene_time_s).max(0.0);
        self.age.record_s(age_s);
        if self.params.work_ms > 0.0 {
            tokio::time::sleep(Duration::from_secs_f64(self.params.work_ms / 1000.0)).await;
        }
        if self.received % 64 == 1 {
            ctx.report(self.report());
        }
        Ok(())
    }

    async fn on_stop(&mut self, ctx: &mut StageCtx) -> anyhow::Result<()> {
        ctx.report(self.report());
        Ok(())
    }
}

/// Default settings of probe inputs: block, 8 deep (nothing lost, so counts can be checked).
pub const PROBE_EDGE: EdgeSettings = EdgeSettings {
    capacity: 8,
    policy: Policy::Block,
};

/// Largest probe payload: the codec's and the transport's message limit less room for the
/// message's envelope (sequence, send time, checksum, framing), so that the largest payload
/// the file may ask for still crosses a cut edge (64 MiB exactly did not: 26 bytes over).
const MAX_PAYLOAD_BYTES: usize = cloudlight_runtime::codec::MAX_MESSAGE_BYTES - 1024;
/// Longest emulated service time per message, milliseconds.
const MAX_WORK_MS: f64 = 60_000.0;

impl CheckParams for SourceParams {
    fn check(&self) -> Result<(), String> {
        if let Some(r) = self.rate_hz {
            check_range("rate_hz", r, 0.001, 1e6, "Hz")?;
        }
        if self.payload_bytes > MAX_PAYLOAD_BYTES {
            return Err(format!(
                "`payload_bytes` = {} is out of range: must be in [0, {MAX_PAYLOAD_BYTES}] bytes",
                self.payload_bytes
            ));
        }
        Ok(())
    }
}

impl CheckParams for RelayParams {
    fn check(&self) -> Result<(), String> {
        check_range("work_ms", self.work_ms, 0.0, MAX_WORK_MS, "ms")
    }
}

impl CheckParams for SinkParams {
    fn check(&self) -> Result<(), String> {
        check_range("work_ms", self.work_ms, 0.0, MAX_WORK_MS, "ms")
    }
}

/// Registers `probe_source`, `probe_relay` and `probe_sink`.
pub fn register(registry: &mut StageRegistry) {
    registry.register(
        StageKind::new(
            "probe_source",
            TECHNIQUE,
            "emits pattern-filled messages at `rate_hz` (or as fast as edges allow)",
            |s: &StageSetup| {
                let params: SourceParams = s.params()?;
                let cadence = params.rate_hz.map(|hz| Cadence::hz(hz).catching_up());
                Ok(Box::new(ProbeSource {
                    params,
                    sent: 0,
                    cadence,
                }))
            },
        )
        .output(OUT)
        .checked_params::<SourceParams>()
        .message_bytes(|t| {
            // The payload and the message's envelope (index, send time, scene time, framing).
            let payload = match t.get("payload_bytes") {
                Some(v) => u64::try_from(v.as_integer()?).ok()?,
                None => default_payload() as u64,
            };
            Some(payload + 64)
        }),
    );
    registry.register(
        StageKind::new(
            "probe_relay",
            TECHNIQUE,
            "forwards messages, optionally after `work_ms`",
            |s| {
                Ok(Box::new(ProbeRelay {
                    params: s.params()?,
                    handled: 0,
                }))
            },
        )
        .input(IN, PROBE_EDGE)
        .output(OUT)
        .checked_params::<RelayParams>(),
    );
    registry.register(
        StageKind::new(
            "probe_sink",
            TECHNIQUE,
            "counts, checks and times received messages",
            |s| {
                Ok(Box::new(ProbeSink {
                    params: s.params()?,
                    received: 0,
                    bytes: 0,
                    out_of_order: 0,
                    corrupt: 0,
                    missing: 0,
                    last_index: HashMap::new(),
                    hop_latency: Latency::new(),
                    age: Latency::new(),
                }))
            },
        )
        .input(IN, PROBE_EDGE)
        .checked_params::<SinkParams>(),
    );
}
