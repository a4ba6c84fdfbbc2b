//! Receiving side of a peer link: bounded reassembly, in-order delivery per edge,
//! acknowledgements and credit grants.

use std::collections::{BTreeMap, HashMap};
use std::time::Instant;

use rangemap::RangeInclusiveSet;

use super::{EdgeWireStats, Endpoint, Event};
use crate::wire::{Body, MAX_ACK_RANGES};

/// A receiving edge.
pub(crate) struct RecvEdge {
    pub(crate) peer: usize,
    capacity: u64,
    /// Next sequence number to deliver.
    pub(crate) next_seq: u64,
    /// Messages the local consumer finished (credit basis).
    pub(crate) released: u64,
    partial: HashMap<u64, Partial>,
    done: BTreeMap<u64, Vec<u8>>,
    pub(crate) stats: EdgeWireStats,
}

struct Partial {
    buf: Vec<u8>,
    got: Vec<bool>,
    remaining: u32,
}

impl RecvEdge {
    pub(crate) fn new(peer: usize, capacity: u64) -> Self {
        RecvEdge {
            peer,
            capacity,
            next_seq: 0,
            released: 0,
            partial: HashMap::new(),
            done: BTreeMap::new(),
            stats: EdgeWireStats::default(),
        }
    }

    pub(crate) fn reset(&mut self) {
        let (peer, capacity, stats) = (self.peer, self.capacity, self.stats);
        *self = RecvEdge::new(peer, capacity);
        self.stats = stats;
    }

    fn grant(&self) -> u64 {
        self.released + self.capacity
    }
}

/// Per-peer receiving state.
#[derive(Default)]
pub(crate) struct RecvState {
    received: RangeInclusiveSet<u64>,
    pub(crate) ack_due: Option<Instant>,
    unacked: u32,
    pub(crate) credit_dirty: bool,
    reassembly_bytes: usize,
}

impl RecvState {
    pub(crate) fn reassembly_bytes(&self) -> usize {
        self.reassembly_bytes
    }
}

/// A DATA packet from peer `p`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn on_data(
    ep: &mut Endpoint,
    p: usize,
    now: Instant,
    pn: u64,
    edge: u32,
    seq: u64,
    len: u32,
    chunk: u32,
    payload: &[u8],
) {
    let Endpoint {
        peers,
        recv_edges,
        config,
        events,
        ..
    } = ep;
    let peer = &mut peers[p];
    let state = &mut peer.recv;
    let result = (|| -> Result<(), &'static str> {
        let e = recv_edges
            .get_mut(&edge)
            .filter(|e| e.peer == p)
            .ok_or("unknown edge")?;
        let len = len as usize;
        if len > config.max_message_bytes {
            return Err("message over the size bound");
        }
        let cb = config.chunk_bytes();
        let chunks = len.div_ceil(cb).max(1);
        let chunk = chunk as usize;
        if chunk >= chunks {
            return Err("chunk index out of range");
        }
        let start = chunk * cb;
        let expect = len.saturating_sub(start).min(cb);
        if payload.len() != expect {
            return Err("chunk length mismatch");
        }
        if seq < e.next_seq || e.done.contains_key(&seq) {
            return Ok(()); // a duplicate of something delivered or complete
        }
        if seq >= e.grant() {
            return Err("sequence beyond the granted credit");
        }
        let part = match e.partial.entry(seq) {
            std::collections::hash_map::Entry::Occupied(o) => o.into_mut(),
            std::collections::hash_map::Entry::Vacant(v) => {
                if state.reassembly_bytes + len > config.max_reassembly_bytes {
                    return Err("reassembly bound reached");
                }
                state.reassembly_bytes += len;
                v.insert(Partial {
                    buf: vec![0; len],
                    got: vec![false; chunks],
                    remaining: chunks as u32,
                })
            }
        };
        if part.buf.len() != len {
            return Err("message length changed between chunks");
        }
        if !part.got[chunk] {
            part.got[chunk] = true;
            part.remaining -= 1;
            part.buf[start..start + expect].copy_from_slice(payload);
        }
        if part.remaining == 0 {
            let part = e.partial.remove(&seq).expect("present");
            state.reassembly_bytes -= len;
            e.done.insert(seq, part.buf);
            while let Some(bytes) = e.done.remove(&e.next_seq) {
                events.push_back(Event::Message {
                    edge,
                    seq: e.next_seq,
                    bytes,
                });
                e.next_seq += 1;
                e.stats.messages += 1;
            }
        }
        e.stats.wire_bytes += (payload.len() + crate::wire::DATA_OVERHEAD) as u64;
        Ok(())
    })();
    match result {
        Ok(()) => {
            state.received.insert(pn..=pn);
            state.unacked += 1;
            state.ack_due.get_or_insert(now + config.ack_delay);
        }
        Err(why) => {
            peer.stats.refused += 1;
            tracing::debug!(peer = %peer.name, edge, seq, why, "DATA refused");
        }
    }
}

/// An ACK for peer `p` when one is due.
pub(crate) fn poll_ack(ep: &mut Endpoint, p: usize, now: Instant) -> Option<Vec<u8>> {
    let config = &ep.config;
    let s = &mut ep.peers[p].recv;
    if s.unacked == 0 || (s.unacked < config.ack_every && s.ack_due.is_none_or(|d| now < d)) {
        return None;
    }
    s.unacked = 0;
    s.ack_due = None;
    let ranges: Vec<(u64, u64)> = s
        .received
        .iter()
        .rev()
        .take(MAX_ACK_RANGES)
        .map(|r| (*r.start(), *r.end()))
        .collect();
    // Keep the set small: old gaps will never be filled, merge everything below the ranges
    // we still report.
    if s.received.len() > 4 * MAX_ACK_RANGES
        && let Some(&(lo, _)) = ranges.last()
        && let Some(first) = s.received.iter().next().map(|r| *r.start())
    {
        s.received.insert(first..=lo);
    }
    Some(Body::Ack { ranges }.encode(config.incarnation))
}

/// A CREDIT packet for peer `p` when grants changed or are due again.
pub(crate) fn poll_credit(ep: &mut Endpoint, p: usize) -> Option<Vec<u8>> {
    if !ep.peers[p].recv.credit_dirty || !ep.peers[p].up {
        return None;
    }
    ep.peers[p].recv.credit_dirty = false;
    let mut grants: Vec<(u32, u64)> = ep
        .recv_edges
        .iter()
        .filter(|(_, e)| e.peer == p)
        .map(|(&id, e)| (id, e.grant()))
        .collect();
    if grants.is_empty() {
        return None;
    }
    grants.sort_unstable();
    Some(Body::Credit { grants }.encode(ep.config.incarnation))
}
