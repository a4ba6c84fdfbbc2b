//! The transport's cryptography, from well-kept RustCrypto crates: handshake tags
//! (HMAC-SHA256 under the cluster's shared secret, truncated to 16 bytes), session keys
//! (HKDF-SHA256 from the secret and both sides' fresh nonces), packet protection
//! (AES-256-GCM keyed per direction, nonce = packet number, a new key every
//! [`KEY_UPDATE_PACKETS`] packet numbers) and the replay window.
//!
//! AES-256-GCM rather than ChaCha20-Poly1305: on this project's machines (x86-64 with AES-NI
//! and carry-less multiply, which `aes-gcm` detects at run time) it seals a 1,200-byte packet
//! in about 1.1 µs against 3.6 µs (`cargo run --release -p cloudlight-transport --example
//! aead_speed`); on a CPU without AES instructions it falls back to a slower constant-time
//! implementation.
//!
//! What it protects against, and what not, is written in the crate's README.

use aes_gcm::Aes256Gcm;
use aes_gcm::aead::{AeadInOut, KeyInit};
use aes_gcm::aead::{Key, Nonce, Tag};
use hmac::Mac;

use crate::wire::{DIGEST_BYTES, NONCE_BYTES, TAG_BYTES};

type HmacSha256 = hmac::Hmac<sha2::Sha256>;

/// Packet numbers one key protects. AES-GCM may protect at most 2^23 packets under one key
/// (its confidentiality limit, RFC 9001 §6.6); a direction changes keys every 2^22 packet
/// numbers, half of it. Packet numbers are in clear and never reused in a session, so both
/// sides know which key a number uses: the stream never pauses for a key update.
pub const KEY_UPDATE_PACKETS: u64 = 1 << 22;

/// The tag of a handshake packet: HMAC-SHA256 over `bytes` under `secret`, truncated.
pub fn handshake_tag(secret: &[u8], bytes: &[u8]) -> [u8; TAG_BYTES] {
    let mut m = HmacSha256::new_from_slice(secret).expect("HMAC takes keys of any length");
    m.update(b"cloudlight-handshake-v2");
    m.update(bytes);
    let full = m.finalize().into_bytes();
    full[..TAG_BYTES].try_into().expect("32 bytes")
}

/// Whether `tag` is the handshake tag of `bytes` (constant time).
pub fn handshake_tag_ok(secret: &[u8], bytes: &[u8], tag: &[u8; TAG_BYTES]) -> bool {
    let mut m = HmacSha256::new_from_slice(secret).expect("HMAC takes keys of any length");
    m.update(b"cloudlight-handshake-v2");
    m.update(bytes);
    m.verify_truncated_left(tag).is_ok()
}

/// A short digest (SHA-256, truncated) of a canonical description, e.g. of a topology.
pub fn digest(bytes: &[u8]) -> [u8; DIGEST_BYTES] {
    use sha2::Digest;
    let full = sha2::Sha256::digest(bytes);
    full[..DIGEST_BYTES].try_into().expect("32 bytes")
}

/// A fresh random secret (32 hex digits) from the operating system's randomness.
pub fn random_secret() -> String {
    let bytes: [u8; 16] = rand::random();
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Which side of a handshake this node played.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Role {
    /// Sent the HELLO.
    Initiator,
    /// Answered it.
    Responder,
}

/// Everything both sides derive alike from one handshake.
pub struct SessionSecrets {
    /// Session id carried by every packet of the session.
    pub id: u64,
    /// Protects what this node sends.
    pub send: PacketKey,
    /// Opens what the peer sends.
    pub recv: PacketKey,
}

/// What a session is derived from.
pub struct SessionInputs<'a> {
    /// The cluster's shared secret.
    pub secret: &'a [u8],
    /// Cluster id.
    pub cluster: &'a str,
    /// Initiator's node name.
    pub initiator: &'a str,
    /// Responder's node name.
    pub responder: &'a str,
    /// Both sides' (equal) topology digest.
    pub digest: &'a [u8; DIGEST_BYTES],
    /// Initiator's nonce.
    pub nonce_i: &'a [u8; NONCE_BYTES],
    /// Responder's nonce.
    pub nonce_r: &'a [u8; NONCE_BYTES],
}

impl SessionSecrets {
    /// HKDF-SHA256: salt = both nonces, input key = the secret, info = names and digest.
    /// Keys change every `key_span` packet numbers ([`KEY_UPDATE_PACKETS`]; less in tests).
    pub fn derive(
        inputs: &SessionInputs<'_>,
        role: Role,
        confidential: bool,
        key_span: u64,
    ) -> SessionSecrets {
        let mut salt = [0u8; 2 * NONCE_BYTES];
        salt[..NONCE_BYTES].copy_from_slice(inputs.nonce_i);
        salt[NONCE_BYTES..].copy_from_slice(inputs.nonce_r);
        let hk = hkdf::Hkdf::<sha2::Sha256>::new(Some(&salt), inputs.secret);
        let mut info = b"cloudlight-session-v2".to_vec();
        for part in [inputs.cluster, inputs.initiator, inputs.responder] {
            info.extend_from_slice(&(part.len() as u32).to_le_bytes());
            info.extend_from_slice(part.as_bytes());
        }
        info.extend_from_slice(inputs.digest);
        let mut okm = [0u8; 72];
        hk.expand(&info, &mut okm)
            .expect("72 bytes is within HKDF's output limit");
        let key =
            |b: &[u8]| PacketKey::new(b.try_into().expect("32 bytes"), confidential, key_span);
        let (i2r, r2i) = (key(&okm[..32]), key(&okm[32..64]));
        let id = u64::from_le_bytes(okm[64..].try_into().expect("8 bytes"));
        let (send, recv) = match role {
            Role::Initiator => (i2r, r2i),
            Role::Responder => (r2i, i2r),
        };
        SessionSecrets { id, send, recv }
    }
}

/// One direction's packet protection: key `k` protects packet numbers from `k · span` on,
/// key 0 being the session's and key `k` derived from it by HKDF with `k`.
pub struct PacketKey {
    base: [u8; 32],
    confidential: bool,
    span: u64,
    /// Ciphers of the newest key epochs used (at most [`PacketKey::KEPT`]).
    ciphers: std::cell::RefCell<Vec<(u64, Aes256Gcm)>>,
    /// The newest epoch that sealed or opened a packet.
    newest: std::cell::Cell<u64>,
}

fn nonce(pn: u64) -> Nonce<Aes256Gcm> {
    let mut n = [0u8; 12];
    n[4..].copy_from_slice(&pn.to_le_bytes());
    n.into()
}

impl PacketKey {
    /// Epochs whose keys are kept: the newest and the one before (for packets reordered
    /// across a key update); packets of older epochs are refused.
    const KEPT: usize = 2;

    fn new(key: [u8; 32], confidential: bool, span: u64) -> Self {
        PacketKey {
            base: key,
            confidential,
            span: span.max(1),
            ciphers: std::cell::RefCell::new(Vec::new()),
            newest: std::cell::Cell::new(0),
        }
    }

    /// The key epoch of packet number `pn`.
    pub fn epoch(&self, pn: u64) -> u64 {
        pn / self.span
    }

    /// Runs `f` with the cipher of `epoch`, derived when first needed.
    fn with_cipher<R>(&self, epoch: u64, f: impl FnOnce(&Aes256Gcm) -> R) -> R {
        let mut ciphers = self.ciphers.borrow_mut();
        if let Some((_, c)) = ciphers.iter().find(|(e, _)| *e == epoch) {
            return f(c);
        }
        let key = if epoch == 0 {
            self.base
        } else {
            let hk = hkdf::Hkdf::<sha2::Sha256>::new(None, &self.base);
            let mut info = b"cloudlight-key-update".to_vec();
            info.extend_from_slice(&epoch.to_le_bytes());
            let mut okm = [0u8; 32];
            hk.expand(&info, &mut okm)
                .expect("32 bytes is within HKDF's output limit");
            okm
        };
        let cipher = Aes256Gcm::new(&Key::<Aes256Gcm>::from(key));
        let out = f(&cipher);
        ciphers.push((epoch, cipher));
        ciphers.sort_unstable_by_key(|(e, _)| std::cmp::Reverse(*e));
        ciphers.truncate(Self::KEPT);
        out
    }

    /// Whether a packet of `epoch` may be opened: the newest epoch seen, the one before, or
    /// the next (a key update); anything else is refused without deriving a key, so forged
    /// far-away numbers cost no key derivation.
    fn acceptable(&self, epoch: u64) -> bool {
        let newest = self.newest.get();
        epoch + 1 >= newest && epoch <= newest + 1
    }

    /// Seals a session packet in place: `packet` holds the header (`header_len` bytes) and
    /// the body; the body is encrypted when the link is confidential, and the tag appended.
    pub fn seal(&self, pn: u64, mut packet: Vec<u8>, header_len: usize) -> Vec<u8> {
        self.seal_in(pn, &mut packet, 0, header_len);
        packet
    }

    /// Seals the session packet that `out` holds from `start` on (its header is
    /// `header_len` bytes), in place, and appends the tag: a packet encoded straight into an
    /// outgoing batch is sealed there, never copied.
    pub fn seal_in(&self, pn: u64, out: &mut Vec<u8>, start: usize, header_len: usize) {
        let epoch = self.epoch(pn);
        self.newest.set(self.newest.get().max(epoch));
        let packet = &mut out[start..];
        let tag = self
            .with_cipher(epoch, |cipher| {
                if self.confidential {
                    let (header, body) = packet.split_at_mut(header_len);
                    cipher.encrypt_inout_detached(&nonce(pn), header, body.into())
                } else {
                    cipher.encrypt_inout_detached(&nonce(pn), packet, (&mut [][..]).into())
                }
            })
            .expect("packets are far below AES-GCM's length limit");
        out.extend_from_slice(&tag);
    }

    /// Checks a session packet's tag and returns its plain body (decrypted into `scratch`
    /// on a confidential link); `None` when the packet is not authentic. `sealed` is the
    /// packet without its tag: `header_len` bytes of header, then the body.
    pub fn open<'a>(
        &self,
        pn: u64,
        sealed: &'a [u8],
        header_len: usize,
        tag: &[u8; TAG_BYTES],
        scratch: &'a mut Vec<u8>,
    ) -> Option<&'a [u8]> {
        let tag = Tag::<Aes256Gcm>::from(*tag);
        let epoch = self.epoch(pn);
        if !self.acceptable(epoch) {
            return None;
        }
        let (header, body) = sealed.split_at(header_len.min(sealed.len()));
        let plain = if self.confidential {
            scratch.clear();
            scratch.extend_from_slice(body);
            self.with_cipher(epoch, |cipher| {
                cipher.decrypt_inout_detached(
                    &nonce(pn),
                    header,
                    scratch.as_mut_slice().into(),
                    &tag,
                )
            })
            .ok()?;
            &scratch[..]
        } else {
            // Integrity only: header and body together are the associated data.
            self.with_cipher(epoch, |cipher| {
                cipher.decrypt_inout_detached(&nonce(pn), sealed, (&mut [][..]).into(), &tag)
            })
            .ok()?;
            body
        };
        // Authentic: its epoch is current from now on.
        self.newest.set(self.newest.get().max(epoch));
        Some(plain)
    }
}

/// Packet numbers already accepted in a session, to refuse replays: everything above the
/// highest seen is new; within [`ReplayWindow::WIDTH`] below it, a bit per number; older
/// numbers are refused.
pub struct ReplayWindow {
    highest: u64,
    bits: Box<[u64; Self::WORDS]>,
}

impl Default for ReplayWindow {
    fn default() -> Self {
        ReplayWindow {
            highest: 0,
            bits: Box::new([0; Self::WORDS]),
        }
    }
}

impl ReplayWindow {
    const WORDS: usize = 256;
    /// Packet numbers tracked below the highest one.
    pub const WIDTH: u64 = 64 * Self::WORDS as u64;

    fn slot(pn: u64) -> (usize, u64) {
        let i = pn % Self::WIDTH;
        ((i / 64) as usize, 1 << (i % 64))
    }

    /// Whether `pn` would be new (packet number 0 is never used).
    pub fn is_new(&self, pn: u64) -> bool {
        if pn == 0 {
            return false;
        }
        if pn > self.highest {
            return true;
        }
        if self.highest - pn >= Self::WIDTH {
            return false;
        }
        let (w, bit) = Self::slot(pn);
        self.bits[w] & bit == 0
    }

    /// Marks `pn` as seen; call only after the packet proved authentic and [`Self::is_new`].
    pub fn mark(&mut self, pn: u64) {
        if pn > self.highest {
            let gap = pn - self.highest;
            if gap >= Self::WIDTH {
                self.bits.fill(0);
            } else {
                for x in self.highest + 1..pn {
                    let (w, bit) = Self::slot(x);
                    self.bits[w] &= !bit;
                }
            }
            self.highest = pn;
        }
        let (w, bit) = Self::slot(pn);
        self.bits[w] |= bit;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::collections::BTreeSet;

    fn inputs<'a>(secret: &'a [u8], digest: &'a [u8; DIGEST_BYTES]) -> SessionInputs<'a> {
        SessionInputs {
            secret,
            cluster: "c",
            initiator: "a",
            responder: "b",
            digest,
            nonce_i: &[1; NONCE_BYTES],
            nonce_r: &[2; NONCE_BYTES],
        }
    }

    #[test]
    fn both_sides_derive_matching_keys_and_tampering_is_caught() {
        for confidential in [false, true] {
            let d = [0; DIGEST_BYTES];
            let a = SessionSecrets::derive(&inputs(b"s", &d), Role::Initiator, confidential, 8);
            let b = SessionSecrets::derive(&inputs(b"s", &d), Role::Responder, confidential, 8);
            assert_eq!(a.id, b.id);
            let packet = a.send.seal(5, b"headerBODY".to_vec(), 6);
            assert_eq!(&packet[..6], b"header");
            assert_eq!(confidential, &packet[6..10] != b"BODY");
            let (sealed, tag) = packet.split_at(10);
            let tag: &[u8; 16] = tag.try_into().unwrap();
            let mut scratch = Vec::new();
            let open = |key: &PacketKey, pn: u64, bytes: &[u8], scratch: &mut Vec<u8>| {
                key.open(pn, bytes, 6, tag, scratch).map(|b| b.to_vec())
            };
            assert_eq!(
                open(&b.recv, 5, sealed, &mut scratch).as_deref(),
                Some(&b"BODY"[..])
            );
            assert!(
                open(&b.recv, 6, sealed, &mut scratch).is_none(),
                "pn is bound"
            );
            assert!(
                open(&a.recv, 5, sealed, &mut scratch).is_none(),
                "direction is bound"
            );
            for i in [1, 7] {
                let mut flipped = sealed.to_vec();
                flipped[i] ^= 1;
                assert!(
                    open(&b.recv, 5, &flipped, &mut scratch).is_none(),
                    "byte {i} is bound"
                );
            }
            let other = SessionSecrets::derive(&inputs(b"t", &d), Role::Responder, confidential, 8);
            assert!(
                open(&other.recv, 5, sealed, &mut scratch).is_none(),
                "secret is bound"
            );
        }
    }

    #[test]
    fn keys_change_every_span_of_packet_numbers_and_stale_or_far_epochs_are_refused() {
        let d = [0; DIGEST_BYTES];
        let a = SessionSecrets::derive(&inputs(b"s", &d), Role::Initiator, true, 8);
        let b = SessionSecrets::derive(&inputs(b"s", &d), Role::Responder, true, 8);
        let mut scratch = Vec::new();
        let open = |pn: u64, packet: &[u8], scratch: &mut Vec<u8>| {
            let (sealed, tag) = packet.split_at(packet.len() - TAG_BYTES);
            b.recv
                .open(pn, sealed, 4, tag.try_into().unwrap(), scratch)
                .map(|x| x.to_vec())
        };
        // Each epoch seals under its own key: the same body at pn 3 and pn 11 (epochs 0 and
        // 1) differ beyond the nonce, and both open across the update.
        let p3 = a.send.seal(3, b"headBODY".to_vec(), 4);
        let p11 = a.send.seal(11, b"headBODY".to_vec(), 4);
        assert_eq!(open(3, &p3, &mut scratch).as_deref(), Some(&b"BODY"[..]));
        assert_eq!(open(11, &p11, &mut scratch).as_deref(), Some(&b"BODY"[..]));
        // Packet 11 sealed under the session's first key (no update yet with a span of
        // 1,000) differs from epoch 1's, and does not open where epoch 1 is expected.
        let first = SessionSecrets::derive(&inputs(b"s", &d), Role::Initiator, true, 1000);
        let wrong = first.send.seal(11, b"headBODY".to_vec(), 4);
        assert_ne!(wrong, p11);
        assert!(open(11, &wrong, &mut scratch).is_none());
        // Reordered across the update: epoch 0 still opens while epoch 1 is the newest.
        let p5 = a.send.seal(5, b"headBODY".to_vec(), 4);
        assert!(open(5, &p5, &mut scratch).is_some());
        // Two epochs on, epoch 0's key is gone: an old packet is refused.
        let p20 = a.send.seal(20, b"headBODY".to_vec(), 4);
        assert!(open(20, &p20, &mut scratch).is_some());
        assert!(open(3, &p3, &mut scratch).is_none(), "a stale epoch opens");
        // Far ahead of the newest epoch: refused without deriving anything.
        let far = a.send.seal(800, b"headBODY".to_vec(), 4);
        assert!(open(800, &far, &mut scratch).is_none());
        assert!(b.recv.ciphers.borrow().len() <= PacketKey::KEPT);
    }

    #[test]
    fn handshake_tags_depend_on_secret_and_bytes() {
        let t = handshake_tag(b"s", b"hello");
        assert!(handshake_tag_ok(b"s", b"hello", &t));
        assert!(!handshake_tag_ok(b"x", b"hello", &t));
        assert!(!handshake_tag_ok(b"s", b"hellp", &t));
    }

    proptest! {
        /// The window accepts each packet number at most once, and accepts every number
        /// that is new and within its width of the highest seen.
        #[test]
        fn replay_window_accepts_each_number_once(pns in proptest::collection::vec(1u64..40_000, 0..3000)) {
            let mut w = ReplayWindow::default();
            let mut seen = BTreeSet::new();
            let mut highest = 0;
            for pn in pns {
                let fresh = !seen.contains(&pn) && (pn > highest || highest - pn < ReplayWindow::WIDTH);
                prop_assert_eq!(w.is_new(pn), fresh);
                if fresh {
                    w.mark(pn);
                    seen.insert(pn);
                    highest = highest.max(pn);
                }
            }
        }
    }
}
