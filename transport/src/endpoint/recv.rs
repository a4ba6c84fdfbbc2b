//! Receiving side of a peer link: bounded reassembly, in-order delivery per edge,
//! acknowledgements and credit grants.

use std::collections::BTreeMap;
use std::time::Instant;

use rangemap::RangeInclusiveSet;

use super::{EdgeWireStats, Endpoint, Event};
use crate::wire::{Body, Frame, MAX_ACK_RANGES};

/// A receiving edge.
pub(crate) struct RecvEdge {
    pub(crate) peer: usize,
    capacity: u64,
    /// Next sequence number to deliver.
    pub(crate) next_seq: u64,
    /// Messages the local consumer finished (credit basis).
    pub(crate) released: u64,
    partial: crate::FastMap<u64, Partial>,
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
            partial: Default::default(),
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

/// Packet numbers received from a peer, as the ranges an ACK reports.
///
/// An acknowledgement must never cover a packet that did not arrive: the sender forgets
/// what is acknowledged. So the set is bounded by *forgetting* its oldest ranges (those
/// packets are then never acknowledged and the sender sends their chunks again, which the
/// reassembly ignores as duplicates), never by merging ranges across a gap.
#[derive(Default)]
pub(crate) struct Received {
    ranges: RangeInclusiveSet<u64>,
}

/// Most ranges kept: twice what one ACK may carry.
pub(crate) const MAX_TRACKED_RANGES: usize = 2 * MAX_ACK_RANGES;

impl Received {
    /// Records that packet `pn` arrived.
    pub(crate) fn record(&mut self, pn: u64) {
        self.ranges.insert(pn..=pn);
        while self.ranges.len() > MAX_TRACKED_RANGES {
            let oldest = self.ranges.iter().next().cloned().expect("non-empty");
            self.ranges.remove(oldest);
        }
    }

    /// The largest packet number received.
    fn largest(&self) -> Option<u64> {
        self.ranges.iter().next_back().map(|r| *r.end())
    }

    /// The newest ranges, highest first, at most [`MAX_ACK_RANGES`], and only those that
    /// reach within `span` packet numbers of the largest received.
    ///
    /// Older ranges tell the sender nothing it can still use: once it has any ACK of a
    /// number `n`, everything it has in flight below `n − 3` is acknowledged or declared
    /// lost, and an ACK covers the last `span` numbers many times over before they leave
    /// it. Reporting them cost both ends as much as the data at 20% loss (hundreds of ranges
    /// in every ACK).
    pub(crate) fn ack_ranges(&self, span: u64) -> Vec<(u64, u64)> {
        let Some(largest) = self.largest() else {
            return Vec::new();
        };
        let floor = largest.saturating_sub(span);
        self.ranges
            .iter()
            .rev()
            .take(MAX_ACK_RANGES)
            .take_while(|r| *r.end() >= floor)
            .map(|r| (*r.start(), *r.end()))
            .collect()
    }
}

/// Per-peer receiving state.
#[derive(Default)]
pub(crate) struct RecvState {
    received: Received,
    pub(crate) ack_due: Option<Instant>,
    pub(crate) unacked: u32,
    pub(crate) credit_dirty: bool,
    reassembly_bytes: usize,
}

impl RecvState {
    /// Records an authentic packet that is not acknowledged for itself (not DATA).
    pub(crate) fn record(&mut self, pn: u64) {
        self.received.record(pn);
    }

    pub(crate) fn reassembly_bytes(&self) -> usize {
        self.reassembly_bytes
    }
}

/// Chunks of an authentic packet `pn` from peer `p` (one, or several coalesced): each is
/// stored; the packet is acknowledged when every chunk was taken (a refused one is sent
/// again, and those taken then count as duplicates).
pub(crate) fn on_data<'a>(
    ep: &mut Endpoint,
    p: usize,
    now: Instant,
    pn: u64,
    frames: impl IntoIterator<Item = Frame<'a>>,
) {
    let mut refused = false;
    for f in frames {
        if let Err(why) = take_chunk(ep, p, &f) {
            refused = true;
            let peer = &mut ep.peers[p];
            peer.stats.refused += 1;
            let name = peer.name.clone();
            let (edge, seq) = (f.edge, f.seq);
            ep.noise.note(now, "authentic DATA refused", || {
                format!("from peer {name}: {why} (edge {edge}, sequence {seq})")
            });
        }
    }
    if !refused {
        let state = &mut ep.peers[p].recv;
        state.received.record(pn);
        state.unacked += 1;
        state.ack_due.get_or_insert(now + ep.config.ack_delay);
    }
}

/// Stores one chunk; delivers the messages it completes, in order.
fn take_chunk(ep: &mut Endpoint, p: usize, f: &Frame<'_>) -> Result<(), &'static str> {
    let Endpoint {
        peers,
        recv_edges,
        config,
        events,
        ..
    } = ep;
    let state = &mut peers[p].recv;
    let Frame {
        edge,
        seq,
        len,
        chunk,
        payload,
    } = *f;
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
}

/// An ACK for peer `p` when one is due.
pub(crate) fn poll_ack(ep: &mut Endpoint, p: usize, now: Instant) -> Option<Body<'static>> {
    let config = &ep.config;
    let s = &mut ep.peers[p].recv;
    if s.unacked == 0 || (s.unacked < config.ack_every && s.ack_due.is_none_or(|d| now < d)) {
        return None;
    }
    s.unacked = 0;
    s.ack_due = None;
    // As many of the newest ranges as one packet holds.
    let mut ranges = s.received.ack_ranges(ack_span(config));
    let budget = config
        .max_packet_bytes
        .saturating_sub(crate::wire::SESSION_HEADER_BYTES + crate::wire::TAG_BYTES);
    ranges.truncate(crate::wire::ack_ranges_fitting(&ranges, budget).max(1));
    Some(Body::Ack { ranges })
}

/// How far below the largest packet number received an ACK reports ranges: twice the
/// send window (a sender's packets in flight span about one window of numbers).
pub(crate) fn ack_span(config: &super::EndpointConfig) -> u64 {
    2 * config.window_packets as u64
}

/// A CREDIT packet for peer `p` when grants changed or are due again.
pub(crate) fn poll_credit(ep: &mut Endpoint, p: usize) -> Option<Body<'static>> {
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
    Some(Body::Credit { grants })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::collections::BTreeSet;

    proptest! {
        /// Under any arrival pattern (loss, reordering, duplicates, forged far-away numbers,
        /// any number of ranges), every acknowledged packet number was received.
        #[test]
        fn acks_only_cover_received_packets(
            arrivals in proptest::collection::vec(
                prop_oneof![
                    8 => 0u64..5_000,
                    1 => any::<u64>(),
                ],
                0..3_000,
            ),
            ack_every in 1usize..64,
        ) {
            let mut r = Received::default();
            let mut got = BTreeSet::new();
            for (i, pn) in arrivals.into_iter().enumerate() {
                r.record(pn);
                got.insert(pn);
                if i % ack_every == 0 {
                    let ranges = r.ack_ranges(u64::MAX);
                    prop_assert!(ranges.len() <= MAX_ACK_RANGES);
                    for (lo, hi) in ranges {
                        prop_assert!(lo <= hi);
                        // Ranges are small here except around forged numbers; check each one.
                        let covered = got.range(lo..=hi).count() as u64;
                        prop_assert_eq!(covered, hi - lo + 1, "ack {}..={} covers a gap", lo, hi);
                    }
                }
            }
            prop_assert!(r.ranges.len() <= MAX_TRACKED_RANGES);
        }
    }

    #[test]
    fn the_newest_packets_are_acknowledged_after_many_gaps() {
        let mut r = Received::default();
        for pn in (0..10_000u64).step_by(2) {
            r.record(pn);
        }
        let ranges = r.ack_ranges(u64::MAX);
        assert_eq!(ranges.len(), MAX_ACK_RANGES);
        assert_eq!(ranges[0], (9_998, 9_998));
        assert!(ranges.iter().all(|&(lo, hi)| lo == hi && lo % 2 == 0));
        // Within a span: the ranges reaching 100 numbers below the largest, no older.
        let near = r.ack_ranges(100);
        assert_eq!(near.len(), 51);
        assert_eq!(near.last(), Some(&(9_898, 9_898)));
    }
}
