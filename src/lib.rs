//! CloudLight-rs: indirect lighting computed on cloud nodes and streamed to clients.
//!
//! This library re-exports the workspace crates and holds the benchmark harness above them
//! ([`bench`](mod@bench), with its plots in [`plot`]); the `cloudlight` binary is the command-line face,
//! which only parses and prints. See the README for the commands and the topology format.

pub mod bench;
pub mod deploy;
pub mod experiment;
pub mod plot;

pub use cloudlight_actors as actors;
pub use cloudlight_render as render;
pub use cloudlight_runtime as runtime;
pub use cloudlight_scenes as scenes;
pub use cloudlight_transport as transport;

/// The built-in default topology, used by `cloudlight run` without a file: the photon
/// technique on the Cornell box (its light moving), traced on a cloud node and streamed to
/// two clients over emulated campus links, for four seconds.
pub const DEFAULT_TOPOLOGY: &str = include_str!("../examples/topologies/photons-cloud.toml");

/// File name under which diagnostics name the built-in default topology.
pub const DEFAULT_TOPOLOGY_NAME: &str =
    "<built-in default: examples/topologies/photons-cloud.toml>";
