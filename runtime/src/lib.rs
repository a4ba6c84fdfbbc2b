//! The CloudLight runtime: pipeline stages as ractor actors joined by bounded edges, placed on
//! nodes by a topology file, with a run-wide scene clock, a lifecycle and metrics.
//!
//! This crate knows nothing about lighting (stages live in `cloudlight-actors`) nor about
//! sockets (cut edges travel over `cloudlight-transport`). Delivery semantics are written
//! down in `runtime/README.md`, included below.
#![doc = include_str!("../README.md")]

mod actor;
pub mod clock;
pub mod cluster;
pub mod codec;
pub mod control;
pub mod edge;
pub mod message;
pub mod metrics;
mod net;
pub mod observe;
pub mod stage;
pub mod toolkit;
pub mod topology;

pub use actor::RunEvent;
pub use clock::SceneClock;
pub use cluster::{Cluster, EndReason, RunError, RunOptions, RunReport, run};
pub use edge::{EdgeSettings, Policy};
pub use message::{Message, MessageType, Stamped};
pub use metrics::{MetricsSnapshot, PeerLinkSnapshot, RunStatus, TransportSnapshot};
pub use stage::{
    AnyScene, CheckParams, Input, InstanceInfo, NextTick, SendError, Stage, StageCtx, StageKind,
    StageRegistry, StageSetup, check_range, parse_params,
};
pub use toolkit::{Cadence, Latency, Port, lock};
pub use topology::{Diagnostic, Plan, Topology, TopologyErrors, TopologySpec};
