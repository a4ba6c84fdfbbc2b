//! The handshake: HELLO → CHALLENGE → CONFIRM, each tagged with an HMAC under the shared
//! secret; sessions are installed here, and a new session replacing a live one is a restart.
//!
//! Who initiates: a node without a session sends HELLOs (a fresh nonce per attempt) to the
//! peer's address every `hello_interval`. A HELLO is answered by a CHALLENGE to the address
//! it came from (at most `challenges_per_s` to addresses other than the peer's own), except
//! that when both sides are initiating, only the one with the greater name answers, so that
//! one handshake completes. The initiator installs the session on a CHALLENGE that echoes its
//! current nonce (the responder proved itself *now*) and sends CONFIRM until it hears an
//! authentic packet of the session, starting over if none comes within twice the peer
//! timeout; the responder installs on a CONFIRM that echoes a challenge it issued and still holds (each
//! challenge completes at most once). Recorded packets from this or an earlier run therefore
//! install nothing: their nonces are not current.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use rand::RngExt;

use super::{Control, Endpoint, Event, Peer, RecvState, Session};
use crate::crypto::{
    ReplayWindow, Role, SessionInputs, SessionSecrets, handshake_tag, handshake_tag_ok,
};
use crate::wire::{Handshake, Ids, NONCE_BYTES, TAG_BYTES};

/// Challenges a responder holds per peer, at most (the oldest is forgotten first).
const MAX_PENDING: usize = 4;
/// How long an issued challenge may be confirmed.
const CHALLENGE_TTL: Duration = Duration::from_secs(10);
/// How long an initiator waits for its session to be confirmed before starting over: twice
/// the peer timeout (at least two seconds), so that a slow link confirms before it expires.
fn confirm_timeout(peer_timeout: Duration) -> Duration {
    (peer_timeout * 2).max(Duration::from_secs(2))
}

/// A HELLO this node sent and awaits an answer to.
pub(crate) struct Initiation {
    nonce_i: [u8; NONCE_BYTES],
    /// When its first HELLO left: the CHALLENGE gives a first round-trip sample (an
    /// overestimate when HELLOs were lost: the first sample of data replaces it).
    since: Instant,
}

/// A CHALLENGE this node issued.
pub(crate) struct PendingChallenge {
    addr: SocketAddr,
    nonce_i: [u8; NONCE_BYTES],
    nonce_r: [u8; NONCE_BYTES],
    at: Instant,
}

impl Endpoint {
    fn ids<'a>(&'a self, peer: &'a Peer) -> Ids<'a> {
        Ids {
            cluster: &self.config.cluster,
            from: &self.config.node,
            to: &peer.name,
            digest: self.config.topology_digest,
            epoch: self.config.epoch,
        }
    }

    fn tagged(&self, message: &Handshake<'_>) -> Vec<u8> {
        let mut bytes = message.encode_untagged();
        let tag = handshake_tag(&self.config.secret, &bytes);
        bytes.extend_from_slice(&tag);
        bytes
    }

    /// A handshake packet for peer `p` when one is due: HELLO while it has no session,
    /// CONFIRM again while its session is unconfirmed.
    pub(super) fn poll_handshake(
        &mut self,
        p: usize,
        now: Instant,
    ) -> Option<(SocketAddr, Vec<u8>)> {
        let interval = self.config.hello_interval;
        let peer = &self.peers[p];
        let bytes = match &peer.session {
            None if now >= peer.hello_due => {
                let (nonce_i, since) = match &peer.initiation {
                    Some(i) => (i.nonce_i, i.since),
                    None => (self.rng.random(), now),
                };
                let hello = Handshake::Hello {
                    ids: self.ids(peer),
                    nonce_i,
                };
                let bytes = self.tagged(&hello);
                let peer = &mut self.peers[p];
                peer.initiation = Some(Initiation { nonce_i, since });
                peer.hello_due = now + interval;
                bytes
            }
            Some(s) if !s.confirmed && now >= s.confirm_due => {
                let (nonce_i, nonce_r) = s.nonces;
                let confirm = Handshake::Confirm {
                    ids: self.ids(peer),
                    nonce_i,
                    nonce_r,
                };
                let bytes = self.tagged(&confirm);
                let s = self.peers[p].session.as_mut().expect("matched above");
                s.confirm_due = now + interval;
                bytes
            }
            _ => return None,
        };
        let to = self.peers[p].addr;
        self.account(p, to, bytes.len());
        Some((to, bytes))
    }

    /// Forgets expired challenges and unconfirmed sessions of peer `p`.
    pub(super) fn expire_handshakes(&mut self, p: usize, now: Instant) {
        let peer = &mut self.peers[p];
        peer.pending
            .retain(|c| now.saturating_duration_since(c.at) < CHALLENGE_TTL);
        if let Some(s) = &peer.session
            && !s.confirmed
            && now.saturating_duration_since(s.established)
                > confirm_timeout(self.config.peer_timeout)
        {
            tracing::debug!(peer = %peer.name, "session not confirmed; starting over");
            self.sessions.remove(&s.secrets.id);
            peer.session = None;
            peer.hello_due = now;
        }
    }

    /// One handshake packet: who it claims to be from, its proof, then its step.
    pub(super) fn handle_handshake(
        &mut self,
        now: Instant,
        from: SocketAddr,
        message: &Handshake<'_>,
        tagged: &[u8],
        tag: &[u8; TAG_BYTES],
    ) {
        let ids = message.ids();
        let known = ids.cluster == self.config.cluster && ids.to == self.config.node;
        let p = self.peer_index(ids.from).filter(|_| known);
        let Some(p) = p.filter(|_| handshake_tag_ok(&self.config.secret, tagged, tag)) else {
            self.stats.strangers += 1;
            let name = ids.from.to_string();
            self.noise.note(
                now,
                "handshake refused (unknown cluster, name or proof)",
                || format!("from {from} claiming `{name}`"),
            );
            return;
        };
        match *message {
            Handshake::Hello { nonce_i, .. } => self.on_hello(now, p, from, nonce_i),
            Handshake::Challenge {
                ref ids,
                nonce_i,
                nonce_r,
            } => self.on_challenge(now, p, from, ids, nonce_i, nonce_r),
            Handshake::Confirm {
                ref ids,
                nonce_i,
                nonce_r,
            } => self.on_confirm(now, p, from, ids, nonce_i, nonce_r),
        }
    }

    fn on_hello(&mut self, now: Instant, p: usize, from: SocketAddr, nonce_i: [u8; NONCE_BYTES]) {
        let peer = &self.peers[p];
        let known_addr = from == peer.addr;
        if peer.session.is_none()
            && peer.initiation.is_some()
            && self.config.node < peer.name
            && known_addr
        {
            // Both initiating: the peer answers ours. Not when its HELLO comes from another
            // address than the one ours go to (a peer behind NAT, whose advertised address
            // ours may never reach): that one is answered.
            return;
        }
        let reuse = peer
            .pending
            .iter()
            .find(|c| c.addr == from && c.nonce_i == nonce_i)
            .map(|c| c.nonce_r);
        if reuse.is_none() && !known_addr && !self.take_challenge_token(now) {
            self.stats.rate_limited += 1;
            return;
        }
        let nonce_r = reuse.unwrap_or_else(|| self.rng.random());
        let challenge = Handshake::Challenge {
            ids: self.ids(&self.peers[p]),
            nonce_i,
            nonce_r,
        };
        let bytes = self.tagged(&challenge);
        let peer = &mut self.peers[p];
        if reuse.is_none() {
            if peer.pending.len() >= MAX_PENDING {
                // Forget the oldest, but never the one for the peer's own address.
                let own = peer.addr;
                let victim = (0..peer.pending.len())
                    .filter(|&i| peer.pending[i].addr != own)
                    .min_by_key(|&i| peer.pending[i].at)
                    .unwrap_or(0);
                peer.pending.remove(victim);
            }
            peer.pending.push(PendingChallenge {
                addr: from,
                nonce_i,
                nonce_r,
                at: now,
            });
        }
        self.control.push_back(Control::Raw(from, bytes));
    }

    fn take_challenge_token(&mut self, now: Instant) -> bool {
        let rate = self.config.challenges_per_s.max(1.0);
        let dt = now
            .saturating_duration_since(self.challenge_refill)
            .as_secs_f64();
        self.challenge_refill = now;
        self.challenge_tokens = (self.challenge_tokens + dt * rate).min(rate);
        if self.challenge_tokens >= 1.0 {
            self.challenge_tokens -= 1.0;
            true
        } else {
            false
        }
    }

    fn on_challenge(
        &mut self,
        now: Instant,
        p: usize,
        from: SocketAddr,
        ids: &Ids<'_>,
        nonce_i: [u8; NONCE_BYTES],
        nonce_r: [u8; NONCE_BYTES],
    ) {
        let current = self.peers[p]
            .initiation
            .as_ref()
            .is_some_and(|i| i.nonce_i == nonce_i);
        if !current || self.peers[p].session.is_some() {
            self.stats.stale_handshakes += 1;
            return;
        }
        // Answer even on a mismatch, so that the responder learns of it too.
        let confirm = Handshake::Confirm {
            ids: self.ids(&self.peers[p]),
            nonce_i,
            nonce_r,
        };
        let bytes = self.tagged(&confirm);
        self.control.push_back(Control::Raw(from, bytes));
        if self.refuse_mismatch(now, p, from, ids) {
            return;
        }
        let since = self.peers[p].initiation.take().map(|i| i.since);
        let secrets = self.derive(p, Role::Initiator, &nonce_i, &nonce_r);
        self.install(
            now,
            p,
            from,
            ids.epoch,
            Role::Initiator,
            secrets,
            (nonce_i, nonce_r),
        );
        if let Some(since) = since {
            self.handshake_rtt(p, now.saturating_duration_since(since));
        }
    }

    /// A first round-trip sample from the handshake (HELLO to CHALLENGE, CHALLENGE to
    /// CONFIRM), as QUIC takes one: without it a path of seconds sends its first data with
    /// the initial 200 ms timeout and retransmits spuriously.
    fn handshake_rtt(&mut self, p: usize, rtt: Duration) {
        let peer = &mut self.peers[p];
        if peer.send.srtt_known() {
            return;
        }
        peer.send.provisional_rtt_sample(rtt, &self.config);
        peer.stats.srtt_s = peer.send.srtt().as_secs_f64();
    }

    fn on_confirm(
        &mut self,
        now: Instant,
        p: usize,
        from: SocketAddr,
        ids: &Ids<'_>,
        nonce_i: [u8; NONCE_BYTES],
        nonce_r: [u8; NONCE_BYTES],
    ) {
        let peer = &mut self.peers[p];
        let Some(i) = peer
            .pending
            .iter()
            .position(|c| c.addr == from && c.nonce_i == nonce_i && c.nonce_r == nonce_r)
        else {
            // A CONFIRM resent for the session we already hold is harmless; any other is stale.
            let resent = peer
                .session
                .as_ref()
                .is_some_and(|s| s.nonces == (nonce_i, nonce_r));
            if !resent {
                self.stats.stale_handshakes += 1;
            }
            return;
        };
        let challenge = peer.pending.remove(i);
        // A challenge issued before the session this node holds now belongs to a handshake
        // that session superseded (both sides initiated; a CONFIRM resent before the other
        // side switched sessions): installing it would leave each side up in a session the
        // other no longer has. A restarted peer's new HELLO earns a newer challenge.
        if peer
            .session
            .as_ref()
            .is_some_and(|s| challenge.at < s.established)
        {
            self.stats.stale_handshakes += 1;
            return;
        }
        if self.refuse_mismatch(now, p, from, ids) {
            return;
        }
        let secrets = self.derive(p, Role::Responder, &nonce_i, &nonce_r);
        self.install(
            now,
            p,
            from,
            ids.epoch,
            Role::Responder,
            secrets,
            (nonce_i, nonce_r),
        );
        self.handshake_rtt(p, now.saturating_duration_since(challenge.at));
    }

    /// Reports (once) and refuses a proven peer whose topology differs. While the peer has a
    /// live session, the newcomer (another deployment using the same secret and name) is
    /// refused and counted, and the live session stays: it does not fail this node.
    fn refuse_mismatch(&mut self, now: Instant, p: usize, from: SocketAddr, ids: &Ids<'_>) -> bool {
        if ids.digest == self.config.topology_digest {
            return false;
        }
        let peer = &mut self.peers[p];
        if peer.up && !peer.gone && peer.session.is_some() {
            peer.stats.mismatched += 1;
            let (name, live) = (peer.name.clone(), peer.addr);
            self.noise.note(
                now,
                "refused a node of another topology under a live peer's name",
                || format!("`{name}` from {from}; its live session (at {live}) stays"),
            );
            return true;
        }
        if !peer.mismatch {
            peer.mismatch = true;
            tracing::error!(peer = %peer.name, "peer runs a different topology; refusing it");
            self.events.push_back(Event::TopologyMismatch {
                peer: peer.name.clone(),
            });
        }
        true
    }

    fn derive(
        &self,
        p: usize,
        role: Role,
        nonce_i: &[u8; NONCE_BYTES],
        nonce_r: &[u8; NONCE_BYTES],
    ) -> SessionSecrets {
        let (me, them) = (self.config.node.as_str(), self.peers[p].name.as_str());
        let (initiator, responder) = match role {
            Role::Initiator => (me, them),
            Role::Responder => (them, me),
        };
        let inputs = SessionInputs {
            secret: &self.config.secret,
            cluster: &self.config.cluster,
            initiator,
            responder,
            digest: &self.config.topology_digest,
            nonce_i,
            nonce_r,
        };
        SessionSecrets::derive(
            &inputs,
            role,
            self.config.confidential,
            self.config.key_update_packets,
        )
    }

    /// Installs a new session with peer `p`, bound to `addr`; one that replaces a session
    /// the peer was ever up in is a restart, and both sides' streams start afresh.
    #[allow(clippy::too_many_arguments)]
    fn install(
        &mut self,
        now: Instant,
        p: usize,
        addr: SocketAddr,
        epoch: u64,
        role: Role,
        secrets: SessionSecrets,
        nonces: ([u8; NONCE_BYTES], [u8; NONCE_BYTES]),
    ) {
        if let Some(old) = self.peers[p].session.take() {
            self.sessions.remove(&old.secrets.id);
        }
        if self.peers[p].ever_up {
            let peer = &mut self.peers[p];
            let lost = peer.send.outstanding();
            peer.stats.restarts += 1;
            peer.stats.lost_messages += lost;
            tracing::warn!(peer = %peer.name, lost, "peer restarted: streams reset");
            self.events.push_back(Event::PeerRestarted {
                peer: peer.name.clone(),
                lost_messages: lost,
            });
            self.reset_peer(p, now);
        }
        self.sessions.insert(secrets.id, p);
        let confirmed = role == Role::Responder;
        let peer = &mut self.peers[p];
        peer.session = Some(Session {
            secrets,
            replay: ReplayWindow::default(),
            confirmed,
            nonces,
            established: now,
            confirm_due: now + self.config.hello_interval,
        });
        peer.send.restart_numbers();
        peer.stats.handshakes += 1;
        peer.addr = addr;
        peer.path = None;
        peer.remote_epoch = epoch;
        peer.last_heard = now;
        peer.gone = false;
        peer.initiation = None;
        peer.ping_due = now;
        if confirmed {
            peer.up = true;
            peer.ever_up = true;
            peer.recv.credit_dirty = true;
            self.events.push_back(Event::PeerUp {
                peer: peer.name.clone(),
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
        peer.stall_reported = false;
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
