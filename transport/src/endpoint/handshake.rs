//! The handshake: HELLO packets with the cluster id, both names, incarnations and a
//! truncated HMAC-SHA256 under the shared secret; peer restarts are detected here.

use std::net::SocketAddr;
use std::time::Instant;

use hmac::{KeyInit, Mac};

use super::{Endpoint, Event, RecvState};
use crate::wire::{Body, MAC_BYTES};

type HmacSha256 = hmac::Hmac<sha2::Sha256>;

impl Endpoint {
    #[allow(clippy::too_many_arguments)]
    fn mac_state(
        &self,
        cluster: &str,
        from: &str,
        to: &str,
        incarnation: u64,
        epoch: u64,
        seen: u64,
        reply: bool,
    ) -> HmacSha256 {
        let mut m =
            HmacSha256::new_from_slice(&self.config.secret).expect("HMAC takes keys of any length");
        m.update(b"cloudlight-hello-v1");
        for part in [cluster, from, to] {
            m.update(&[part.len() as u8]);
            m.update(part.as_bytes());
        }
        m.update(&incarnation.to_le_bytes());
        m.update(&epoch.to_le_bytes());
        m.update(&seen.to_le_bytes());
        m.update(&[u8::from(reply)]);
        m
    }

    pub(super) fn hello(&self, p: usize, reply: bool) -> Vec<u8> {
        let peer = &self.peers[p];
        let c = &self.config;
        let full = self
            .mac_state(
                &c.cluster,
                &c.node,
                &peer.name,
                c.incarnation,
                c.epoch,
                peer.remote_incarnation,
                reply,
            )
            .finalize()
            .into_bytes();
        let mac: [u8; MAC_BYTES] = full[..MAC_BYTES]
            .try_into()
            .expect("HMAC-SHA256 has 32 bytes");
        Body::Hello {
            cluster: &c.cluster,
            from: &c.node,
            to: &peer.name,
            epoch: c.epoch,
            seen: peer.remote_incarnation,
            reply,
            mac,
        }
        .encode(c.incarnation)
    }

    #[allow(clippy::too_many_arguments)]
    pub(super) fn handle_hello(
        &mut self,
        now: Instant,
        from: SocketAddr,
        incarnation: u64,
        cluster: &str,
        name: &str,
        to: &str,
        epoch: u64,
        seen: u64,
        reply: bool,
        mac: &[u8; MAC_BYTES],
    ) {
        let proven = self
            .mac_state(cluster, name, to, incarnation, epoch, seen, reply)
            .verify_truncated_left(mac)
            .is_ok();
        let Some(p) = self.peer_index(name) else {
            self.strangers += 1;
            return;
        };
        if cluster != self.config.cluster || to != self.config.node || incarnation == 0 || !proven {
            self.strangers += 1;
            tracing::debug!(%from, name, "hello refused (cluster, name or proof)");
            return;
        }
        if self.peers[p].addr != from {
            self.by_addr.remove(&self.peers[p].addr);
            self.peers[p].addr = from;
            self.by_addr.insert(from, p);
        }
        let old = self.peers[p].remote_incarnation;
        if old != incarnation {
            if old != 0 {
                let lost = self.peers[p].send.outstanding();
                self.events.push_back(Event::PeerRestarted {
                    peer: name.to_string(),
                    lost_messages: lost,
                });
                self.reset_peer(p, now);
            }
            self.peers[p].remote_incarnation = incarnation;
        }
        let my = self.config.incarnation;
        let peer = &mut self.peers[p];
        peer.remote_epoch = epoch;
        peer.last_heard = now;
        peer.gone = false;
        if !reply || seen != my {
            peer.reply_hello = true;
        }
        if seen == my && !peer.up {
            peer.up = true;
            peer.ever_up = true;
            peer.ping_due = now;
            peer.recv.credit_dirty = true;
            self.events.push_back(Event::PeerUp {
                peer: name.to_string(),
                epoch,
            });
        }
    }

    /// Forgets the streams of a restarted peer.
    fn reset_peer(&mut self, p: usize, now: Instant) {
        let peer = &mut self.peers[p];
        peer.send.reset(&self.config, now);
        peer.recv = RecvState::default();
        peer.up = false;
        for (&edge, e) in self.send_edges.iter_mut().filter(|(_, e)| e.peer == p) {
            e.reset();
            self.events.push_back(Event::Credit {
                edge,
                granted: e.granted,
            });
        }
        for e in self.recv_edges.values_mut().filter(|e| e.peer == p) {
            e.reset();
        }
    }
}
