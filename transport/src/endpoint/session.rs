//! Session packets: find the session, refuse replays, check the tag, check the address
//! (an authentic packet from a new address only earns that address a path challenge), then
//! obey the packet.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use rand::RngExt;

use super::{Control, Endpoint, Event, PathProbe, recv, send};
use crate::wire::{self, Body, Frame, SESSION_HEADER_BYTES, frames};

impl Endpoint {
    /// A session packet: find its session, refuse replays, check its tag, then obey it.
    pub(super) fn handle_session(
        &mut self,
        now: Instant,
        from: SocketAddr,
        packet: &wire::SessionPacket<'_>,
        size: usize,
    ) {
        let Some(&p) = self.sessions.get(&packet.session) else {
            self.stats.unknown_session += 1;
            self.noise.note(now, "packet of no current session", || {
                format!("from {from}")
            });
            return;
        };
        let mut scratch = std::mem::take(&mut self.scratch);
        let peer = &mut self.peers[p];
        let session = peer.session.as_mut().expect("indexed sessions exist");
        // A seen number is still authenticated: a bit flipped in a copy of a seen packet is
        // a forgery, not a replay, and counts as one.
        let seen = !session.replay.is_new(packet.pn);
        let body = session
            .secrets
            .recv
            .open(
                packet.pn,
                packet.sealed,
                SESSION_HEADER_BYTES,
                packet.tag,
                &mut scratch,
            )
            .map(|plain| wire::Body::decode(packet.kind, plain));
        let body = match body {
            None => {
                peer.stats.forged += 1;
                let name = peer.name.clone();
                self.noise.note(now, "packet failed authentication", || {
                    format!("claiming peer {name}'s session, from {from}")
                });
                self.scratch = scratch;
                return;
            }
            Some(_) if seen => {
                peer.stats.replayed += 1;
                self.scratch = scratch;
                return;
            }
            Some(Err(e)) => {
                // Authentic but undecodable: a peer speaking another dialect.
                session.replay.mark(packet.pn);
                self.stats.malformed += 1;
                self.noise
                    .note(now, "malformed body", || format!("from {from}: {e}"));
                self.scratch = scratch;
                return;
            }
            Some(Ok(body)) => body,
        };
        session.replay.mark(packet.pn);
        if from != peer.addr && !self.path_check(now, p, from, &body) {
            self.scratch = scratch;
            return;
        }
        self.obey(now, p, packet.pn, body, size);
        self.scratch = scratch;
    }

    /// An authentic packet from an address other than the peer's: only a path response
    /// moves the link; anything else is dropped and the new address challenged. Returns
    /// whether to obey the packet.
    fn path_check(&mut self, now: Instant, p: usize, from: SocketAddr, body: &Body<'_>) -> bool {
        let peer = &mut self.peers[p];
        match body {
            Body::PathChallenge { token } => {
                // Answer where it came from; that proves nothing about us moving.
                let reply = Body::PathResponse { token: *token };
                self.control.push_back(Control::Body(p, Some(from), reply));
                false
            }
            Body::PathResponse { token }
                if peer
                    .path
                    .as_ref()
                    .is_some_and(|probe| probe.addr == from && probe.token == *token) =>
            {
                tracing::info!(peer = %peer.name, old = %peer.addr, new = %from, "peer moved");
                peer.addr = from;
                peer.path = None;
                peer.stats.moves += 1;
                false
            }
            _ => {
                peer.stats.misaddressed += 1;
                let due = peer.path.as_ref().is_none_or(|probe| {
                    probe.addr != from || now >= probe.sent + self.config.hello_interval
                });
                if due {
                    let token = self.rng.random();
                    peer.path = Some(PathProbe {
                        addr: from,
                        token,
                        sent: now,
                    });
                    let probe = Body::PathChallenge { token };
                    self.control.push_back(Control::Body(p, Some(from), probe));
                }
                false
            }
        }
    }

    /// Acts on an authentic, fresh packet of peer `p`'s session.
    fn obey(&mut self, now: Instant, p: usize, pn: u64, body: Body<'_>, size: usize) {
        let peer = &mut self.peers[p];
        peer.last_heard = now;
        if let Some(s) = peer.session.as_mut()
            && !s.confirmed
        {
            s.confirmed = true;
        }
        if peer.gone {
            // It said goodbye: stragglers are ignored; a new handshake revives it.
            return;
        }
        peer.stats.packets_received += 1;
        peer.stats.wire_bytes_received += size as u64;
        if !peer.up && !matches!(body, Body::Bye { .. }) {
            peer.up = true;
            peer.ever_up = true;
            peer.recv.credit_dirty = true;
            let ev = Event::PeerUp {
                peer: peer.name.clone(),
                epoch: peer.remote_epoch,
            };
            self.events.push_back(ev);
        }
        match body {
            Body::Data {
                edge,
                seq,
                len,
                chunk,
                payload,
            } => {
                let frame = Frame {
                    edge,
                    seq,
                    len,
                    chunk,
                    payload,
                };
                recv::on_data(self, p, now, pn, [frame])
            }
            // Checked by `Body::decode`: every frame is well formed.
            Body::Frames { raw } => recv::on_data(self, p, now, pn, frames(raw).flatten()),
            other => {
                self.peers[p].recv.record(pn);
                self.obey_control(now, p, other);
            }
        }
    }

    fn obey_control(&mut self, now: Instant, p: usize, body: Body<'_>) {
        match body {
            Body::Ack { ranges } => send::on_ack(self, p, now, &ranges),
            Body::Credit { grants } => {
                for (edge, granted) in grants {
                    if let Some(e) = self.send_edges.get_mut(&edge)
                        && e.peer == p
                        && granted > e.granted
                    {
                        e.granted = granted;
                        self.events.push_back(Event::Credit { edge, granted });
                    }
                }
            }
            Body::Ping { t_us } => {
                self.control
                    .push_back(Control::Body(p, None, Body::Pong { t_us }));
            }
            Body::Pong { t_us } => {
                let rtt = Duration::from_micros(self.now_us(now).saturating_sub(t_us));
                let peer = &mut self.peers[p];
                peer.send.rtt_sample(rtt, &self.config);
                peer.stats.srtt_s = peer.send.srtt().as_secs_f64();
            }
            Body::Bye { failed } => {
                let peer = &mut self.peers[p];
                peer.gone = true;
                peer.up = false;
                self.events.push_back(Event::PeerLeft {
                    peer: peer.name.clone(),
                    failed,
                });
            }
            Body::PathChallenge { token } => {
                let reply = Body::PathResponse { token };
                self.control.push_back(Control::Body(p, None, reply));
            }
            Body::PathResponse { .. } | Body::Data { .. } | Body::Frames { .. } => {}
        }
    }
}
