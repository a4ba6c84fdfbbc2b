//! Node-to-node links for cut edges: framing, chunking below laminar's fragment limit,
//! reassembly with hard bounds, per-edge ordering, acknowledgement windows, pacing, credits
//! carried across the link, heartbeats and a seeded link emulator (latency, jitter,
//! bandwidth, loss, duplication, reordering).
//!
//! Nothing is implemented yet: this crate is filled by the transport issue. It must never
//! know about lighting; it moves opaque, already-encoded edge messages.
