//! Pipeline stages, one module per stage kind, and the wire message types of every edge.
//!
//! A stage is a thin shell over a kernel of `cloudlight-render`: receive → compute → send.
//! Stages never open sockets or look at placement; the runtime moves their messages.
//! Lighting stages arrive with their techniques; for now this crate holds the probe
//! technique used to qualify topologies and links.

pub mod probe;
pub mod wire;

use cloudlight_runtime::StageRegistry;

/// Every stage kind this build knows, for topology files to name.
pub fn registry() -> StageRegistry {
    let mut r = StageRegistry::new();
    probe::register(&mut r);
    r
}
