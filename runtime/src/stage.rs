//! What a stage is: the [`Stage`] behaviour a pipeline stage implements, the [`StageCtx`] it
//! sends through, the [`StageKind`] that declares its typed ports and builds it, and the
//! [`StageRegistry`] of kinds a topology may name.
//!
//! A stage is a thin shell: receive → call a kernel → send downstream. It never knows whether
//! its edges are in-process or cut, or on which node its neighbours run.

use std::collections::BTreeMap;
use std::fmt;
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::de::DeserializeOwned;

use crate::clock::{SceneClock, now_unix_ns};
use crate::codec::CodecError;
use crate::control::RunControl;
use crate::edge::{Delivery, Edge, EdgeClosed, EdgeSettings};
use crate::message::{AnyMessage, Message, MessageType, Stamped};
use crate::metrics::StageMetrics;
use crate::toolkit::Port;

/// When a stage wants its next [`Stage::on_tick`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NextTick {
    /// As soon as the stage's other messages allow.
    Now,
    /// After this long.
    After(Duration),
    /// Never again: the stage only reacts to inputs from now on.
    Never,
}

/// The behaviour of a pipeline stage. One value per stage instance; the runtime calls it from
/// one actor, one call at a time.
///
/// Every stage gets one tick when the run starts; sources keep ticking by returning
/// [`NextTick::Now`] or [`NextTick::After`]. Returning an error fails the stage, which stops
/// the run (see the crate documentation).
#[async_trait::async_trait]
pub trait Stage: Send + 'static {
    /// Called once before any message or tick.
    async fn on_start(&mut self, _ctx: &mut StageCtx) -> anyhow::Result<()> {
        Ok(())
    }

    /// Called at start and then as the previous call asked.
    async fn on_tick(&mut self, _ctx: &mut StageCtx) -> anyhow::Result<NextTick> {
        Ok(NextTick::Never)
    }

    /// Called for each message taken from one of the stage's input edges.
    async fn on_input(&mut self, _ctx: &mut StageCtx, input: Input) -> anyhow::Result<()> {
        anyhow::bail!(
            "stage has no inputs but got a message on `{}`",
            input.port()
        )
    }

    /// Called once when the stage stops after a drained run.
    async fn on_stop(&mut self, _ctx: &mut StageCtx) -> anyhow::Result<()> {
        Ok(())
    }
}

/// A message delivered to a stage on one input port.
pub struct Input {
    port: Arc<str>,
    from: Arc<str>,
    delivery: Delivery,
}

impl Input {
    pub(crate) fn new(port: Arc<str>, from: Arc<str>, delivery: Delivery) -> Self {
        Input {
            port,
            from,
            delivery,
        }
    }

    /// Input port the message arrived on.
    pub fn port(&self) -> &str {
        &self.port
    }

    /// Instance that produced it.
    pub fn from(&self) -> &str {
        &self.from
    }

    /// Time the message waited in the edge's queue.
    pub fn waited(&self) -> Duration {
        self.delivery.waited()
    }

    /// The message on `port`; errors if it arrived on another port.
    pub fn on<T: Message>(&self, port: Port<T>) -> anyhow::Result<Arc<Stamped<T>>> {
        if &*self.port != port.name() {
            anyhow::bail!(
                "a message on input `{}`, where only `{}` was expected",
                self.port,
                port.name()
            );
        }
        self.get()
    }

    /// Whether the message arrived on `port`.
    pub fn is_on<T>(&self, port: Port<T>) -> bool {
        &*self.port == port.name()
    }

    /// The message as a `Stamped<T>`; errors if the port carries another type.
    pub fn get<T: Message>(&self) -> anyhow::Result<Arc<Stamped<T>>> {
        let any: AnyMessage = self.delivery.message().clone();
        any.downcast::<Stamped<T>>().map_err(|_| {
            anyhow::anyhow!(
                "input `{}` does not carry {}",
                self.port,
                std::any::type_name::<T>()
            )
        })
    }
}

/// Why a send failed.
#[derive(Debug, thiserror::Error)]
pub enum SendError {
    /// The stage's kind declares no such output.
    #[error("no output port `{0}`")]
    UnknownPort(String),
    /// The value is not of the port's declared type.
    #[error("output `{port}` carries {expected}, not {got}")]
    WrongType {
        /// Port name.
        port: String,
        /// Declared type.
        expected: &'static str,
        /// Type sent.
        got: &'static str,
    },
    /// A consumer stopped.
    #[error(transparent)]
    Closed(#[from] EdgeClosed),
    /// The message could not be measured/encoded.
    #[error(transparent)]
    Codec(#[from] CodecError),
}

pub(crate) struct OutputPort {
    pub(crate) name: &'static str,
    pub(crate) ty: MessageType,
    pub(crate) edges: Vec<Arc<Edge>>,
    pub(crate) next_seq: u64,
}

/// Identity of a stage instance in a run.
#[derive(Clone, Debug)]
pub struct InstanceInfo {
    /// Instance name: the stage's name, or `stage[i]` for replica `i`.
    pub name: Arc<str>,
    /// Name of the stage declaration.
    pub stage: String,
    /// Stage kind.
    pub kind: String,
    /// Node it runs on.
    pub node: String,
    /// Replica index, 0 for unreplicated stages.
    pub replica: usize,
    /// Replica count of its stage.
    pub replicas: usize,
}

/// What a stage uses while it runs: its identity, the clock, and its outputs.
pub struct StageCtx {
    pub(crate) info: InstanceInfo,
    pub(crate) seed: u64,
    pub(crate) clock: SceneClock,
    pub(crate) control: Arc<RunControl>,
    pub(crate) outputs: Vec<OutputPort>,
    pub(crate) metrics: Arc<StageMetrics>,
    pub(crate) blocked: Duration,
}

impl StageCtx {
    /// Identity of this instance.
    pub fn info(&self) -> &InstanceInfo {
        &self.info
    }

    /// Instance name.
    pub fn name(&self) -> &str {
        &self.info.name
    }

    /// The run's seed, mixed with nothing: combine it with the replica index yourself.
    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// The run-wide scene clock.
    pub fn clock(&self) -> &SceneClock {
        &self.clock
    }

    /// Scene time now, seconds.
    pub fn scene_time_s(&self) -> f64 {
        self.clock.scene_time_s()
    }

    /// True once the run is draining: sources should stop producing.
    pub fn is_stopping(&self) -> bool {
        self.control.is_stopping()
    }

    /// Publishes this stage's own figures into the run's metrics (replaces the last report).
    pub fn report(&self, value: serde_json::Value) {
        self.metrics.set_report(value);
    }

    /// Whether output `port` has any consumer (a stage may skip work nobody receives).
    pub fn has_consumers<T>(&self, port: Port<T>) -> bool {
        self.outputs
            .iter()
            .any(|p| p.name == port.name() && !p.edges.is_empty())
    }

    /// Sends `body`, computed for `scene_time_s`, to every consumer of output `port`. Under
    /// `block` this waits for room; the wait is not counted as busy time.
    pub async fn send<T: Message>(
        &mut self,
        port: Port<T>,
        scene_time_s: f64,
        body: T,
    ) -> Result<(), SendError> {
        let port = port.name();
        let out = self
            .outputs
            .iter_mut()
            .find(|p| p.name == port)
            .ok_or_else(|| SendError::UnknownPort(port.to_string()))?;
        if out.ty != MessageType::of::<T>() {
            return Err(SendError::WrongType {
                port: port.to_string(),
                expected: out.ty.name(),
                got: std::any::type_name::<T>(),
            });
        }
        let msg: AnyMessage = Arc::new(Stamped {
            scene_time_s,
            produced_unix_ns: now_unix_ns(),
            seq: out.next_seq,
            body,
        });
        out.next_seq += 1;
        if out.edges.is_empty() {
            return Ok(());
        }
        let bytes = out.ty.wire_len(&msg)?;
        let start = Instant::now();
        for edge in &out.edges {
            edge.push(msg.clone(), bytes).await?;
        }
        self.blocked += start.elapsed();
        Ok(())
    }
}

/// A port of a stage kind.
#[derive(Clone, Debug)]
pub struct PortSpec {
    /// Port name, unique among the kind's inputs (or outputs).
    pub name: &'static str,
    /// Message type carried.
    pub ty: MessageType,
    /// Default capacity and policy of edges into this port (inputs only).
    pub default: Option<EdgeSettings>,
    /// An input the stage works without (no warning when no edge feeds it).
    pub optional: bool,
}

/// Everything a stage kind's constructor gets.
#[derive(Clone, Debug)]
pub struct StageSetup {
    /// Identity of the instance being built.
    pub info: InstanceInfo,
    /// Scene named by the topology.
    pub scene: String,
    /// Run seed.
    pub seed: u64,
    /// The stage's `params` table from the topology.
    pub params: toml::Table,
    /// The run's output folder, where stages may write files (frames, dumps); `None` when
    /// the run writes nothing.
    pub out_dir: Option<std::path::PathBuf>,
}

impl StageSetup {
    /// Parses the `params` table into the kind's parameter type.
    pub fn params<P: DeserializeOwned>(&self) -> anyhow::Result<P> {
        parse_params(&self.params).map_err(|e| anyhow::anyhow!("{}: params: {e}", self.info.name))
    }
}

/// Parameters whose values need more checking than their types give: finite numbers,
/// ranges, sizes a machine can hold.
pub trait CheckParams {
    /// Why the values cannot run, naming the parameter, its value and its range.
    fn check(&self) -> Result<(), String>;
}

/// Checks that `value` of parameter `name` is finite and in `[low, high]` (`unit` for the
/// message).
pub fn check_range(name: &str, value: f64, low: f64, high: f64, unit: &str) -> Result<(), String> {
    if value.is_finite() && (low..=high).contains(&value) {
        Ok(())
    } else {
        Err(format!(
            "`{name}` = {} is out of range: must be in [{}, {}] {unit}",
            show_number(value),
            show_number(low),
            show_number(high)
        ))
    }
}

/// A number as a person would write it: plain when moderate, scientific when extreme.
pub fn show_number(v: f64) -> String {
    if v != 0.0 && v.is_finite() && !(1e-3..1e7).contains(&v.abs()) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

/// A `params` table as `P`, the error as `toml` words it.
pub fn parse_params<P: DeserializeOwned>(table: &toml::Table) -> Result<P, String> {
    toml::Value::Table(table.clone())
        .try_into()
        .map_err(|e: toml::de::Error| e.message().to_string())
}

/// The loaded scene as the runtime sees it: opaque (a stage kind downcasts it to the scene
/// type it knows; the runtime never depends on the scene model).
pub type AnyScene = dyn std::any::Any + Send + Sync;

type SceneCheck = Arc<dyn Fn(&toml::Table, &AnyScene) -> Result<(), String> + Send + Sync>;
type Builder = Arc<dyn Fn(&StageSetup) -> anyhow::Result<Box<dyn Stage>> + Send + Sync>;
type ParamCheck = Arc<dyn Fn(&toml::Table) -> Result<(), String> + Send + Sync>;

type SizeEstimate = Arc<dyn Fn(&toml::Table) -> Option<u64> + Send + Sync>;

/// A kind of stage: its name, the technique it belongs to, its typed ports, how its
/// parameters are checked and how an instance is built.
#[derive(Clone)]
pub struct StageKind {
    /// Name used by `kind = "..."` in topology files.
    pub name: String,
    /// Technique it belongs to (`photons`, `voxels`, `irradiance`, `probe`, ...).
    pub technique: String,
    /// One line for `--help` style listings.
    pub summary: String,
    /// Input ports.
    pub inputs: Vec<PortSpec>,
    /// Output ports.
    pub outputs: Vec<PortSpec>,
    check: ParamCheck,
    scene_check: Option<SceneCheck>,
    message_bytes: Option<SizeEstimate>,
    build: Builder,
}

impl fmt::Debug for StageKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("StageKind")
            .field("name", &self.name)
            .field("inputs", &self.inputs)
            .field("outputs", &self.outputs)
            .finish()
    }
}

impl StageKind {
    /// A kind without ports or parameters; add them with the builder methods.
    pub fn new(
        name: &str,
        technique: &str,
        summary: &str,
        build: impl Fn(&StageSetup) -> anyhow::Result<Box<dyn Stage>> + Send + Sync + 'static,
    ) -> Self {
        StageKind {
            name: name.to_string(),
            technique: technique.to_string(),
            summary: summary.to_string(),
            inputs: Vec::new(),
            outputs: Vec::new(),
            check: Arc::new(|t| match t.keys().next() {
                None => Ok(()),
                Some(k) => Err(format!("unknown parameter `{k}` (this kind takes none)")),
            }),
            scene_check: None,
            message_bytes: None,
            build: Arc::new(build),
        }
    }

    /// Declares how large (encoded) the messages this kind sends are, from its parameters,
    /// when that is known before it runs: validation then checks capacity × size against each
    /// output edge's byte bound and reports what a node's queues may hold.
    pub fn message_bytes(
        mut self,
        estimate: impl Fn(&toml::Table) -> Option<u64> + Send + Sync + 'static,
    ) -> Self {
        self.message_bytes = Some(Arc::new(estimate));
        self
    }

    /// The size of the messages it sends with `params`, if declared and known.
    pub fn estimated_message_bytes(&self, params: &toml::Table) -> Option<u64> {
        self.message_bytes.as_ref().and_then(|f| f(params))
    }

    /// Declares an input port carrying `T`, with the default settings of edges into it.
    pub fn input<T: Message>(mut self, port: Port<T>, default: EdgeSettings) -> Self {
        self.inputs.push(PortSpec {
            name: port.name(),
            ty: MessageType::of::<T>(),
            default: Some(default),
            optional: false,
        });
        self
    }

    /// Declares an input port the stage works without: [`Self::input`], but a topology
    /// that feeds it nothing gets no warning (e.g. clients' views, which only refine what
    /// the stage does).
    pub fn optional_input<T: Message>(mut self, port: Port<T>, default: EdgeSettings) -> Self {
        self = self.input(port, default);
        if let Some(p) = self.inputs.last_mut() {
            p.optional = true;
        }
        self
    }

    /// Declares an output port carrying `T`.
    pub fn output<T: Message>(mut self, port: Port<T>) -> Self {
        self.outputs.push(PortSpec {
            name: port.name(),
            ty: MessageType::of::<T>(),
            default: None,
            optional: false,
        });
        self
    }

    /// Declares the parameter type: `params` tables are checked by deserializing into `P`
    /// (use `#[serde(deny_unknown_fields)]` so that misspelt keys are errors).
    pub fn params<P: DeserializeOwned>(mut self) -> Self {
        self.check = Arc::new(|t| parse_params::<P>(t).map(|_| ()));
        self
    }

    /// Like [`StageKind::params`], then [`CheckParams::check`]: values out of their ranges are
    /// validation errors, found before anything runs.
    pub fn checked_params<P: DeserializeOwned + CheckParams>(mut self) -> Self {
        self.check = Arc::new(|t| parse_params::<P>(t).and_then(|p| p.check()));
        self
    }

    /// Declares a check of the parameters against the loaded scene (e.g. a camera index the
    /// scene must have, a photon budget the scene's lights derive), run by `validate`.
    pub fn scene_check(
        mut self,
        check: impl Fn(&toml::Table, &AnyScene) -> Result<(), String> + Send + Sync + 'static,
    ) -> Self {
        self.scene_check = Some(Arc::new(check));
        self
    }

    /// Checks a `params` table.
    pub fn check_params(&self, params: &toml::Table) -> Result<(), String> {
        (self.check)(params)
    }

    /// Checks a `params` table against the scene (nothing when the kind declares no check).
    pub fn check_scene(&self, params: &toml::Table, scene: &AnyScene) -> Result<(), String> {
        self.scene_check
            .as_ref()
            .map_or(Ok(()), |c| c(params, scene))
    }

    /// Builds an instance.
    pub fn build(&self, setup: &StageSetup) -> anyhow::Result<Box<dyn Stage>> {
        (self.build)(setup)
    }

    /// Input port by name, or the only input when `name` is `None`.
    pub fn find_input(&self, name: Option<&str>) -> Result<&PortSpec, String> {
        find_port(&self.inputs, name, "input")
    }

    /// Output port by name, or the only output when `name` is `None`.
    pub fn find_output(&self, name: Option<&str>) -> Result<&PortSpec, String> {
        find_port(&self.outputs, name, "output")
    }
}

fn find_port<'a>(
    ports: &'a [PortSpec],
    name: Option<&str>,
    what: &str,
) -> Result<&'a PortSpec, String> {
    let names = || {
        let v: Vec<_> = ports.iter().map(|p| p.name).collect();
        if v.is_empty() {
            "none".to_string()
        } else {
            v.join(", ")
        }
    };
    match name {
        Some(n) => ports
            .iter()
            .find(|p| p.name == n)
            .ok_or_else(|| format!("no {what} port `{n}` (it has: {})", names())),
        None if ports.len() == 1 => Ok(&ports[0]),
        None => Err(format!(
            "name the {what} port as `stage.port` (it has: {})",
            names()
        )),
    }
}

/// The stage kinds a topology may name.
#[derive(Clone, Debug, Default)]
pub struct StageRegistry {
    kinds: BTreeMap<String, StageKind>,
}

impl StageRegistry {
    /// An empty registry.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a kind; a later kind of the same name replaces the earlier one.
    pub fn register(&mut self, kind: StageKind) -> &mut Self {
        self.kinds.insert(kind.name.clone(), kind);
        self
    }

    /// Kind by name.
    pub fn get(&self, name: &str) -> Option<&StageKind> {
        self.kinds.get(name)
    }

    /// Every kind, by name.
    pub fn kinds(&self) -> impl Iterator<Item = &StageKind> {
        self.kinds.values()
    }
}
