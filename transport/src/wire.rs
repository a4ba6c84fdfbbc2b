//! The transport's packet format: every datagram the transport hands laminar is one of these.
//!
//! ```text
//! handshake: 0 magic "CL" | 2 version u8 | 3 kind u8 | fields ...          | HMAC tag [16]
//! session:   0 magic "CL" | 2 version u8 | 3 kind u8 | 4 session id u64 | 12 packet number u64
//!            | 20 body ... (encrypted when the link is confidential)        | AEAD tag [16]
//! ```
//! All integers are little-endian. Handshake packets (HELLO, CHALLENGE, CONFIRM) carry a
//! truncated HMAC-SHA256 under the cluster's shared secret over every byte before it; session
//! packets carry an AES-256-GCM tag under the session's key (see [`crate::crypto`]).
//! Decoding borrows from the datagram (no allocation), checks every length against the bytes
//! present, and never panics: any malformed input is a [`WireError`]. Tags are checked by the
//! endpoint, which holds the keys.

/// Protocol version carried by every packet.
pub const VERSION: u8 = 4;
const MAGIC: [u8; 2] = *b"CL";
/// Bytes of the common header (magic, version, kind).
pub const HEADER_BYTES: usize = 4;
/// Bytes of a session packet's header (common header, session id, packet number).
pub const SESSION_HEADER_BYTES: usize = HEADER_BYTES + 8 + 8;
/// Bytes of every packet's trailing tag.
pub const TAG_BYTES: usize = 16;
/// Bytes of a handshake nonce.
pub const NONCE_BYTES: usize = 16;
/// Bytes of the topology digest carried in the handshake.
pub const DIGEST_BYTES: usize = 16;
/// Bytes a DATA packet spends besides its payload.
pub const DATA_OVERHEAD: usize = SESSION_HEADER_BYTES + 4 + 8 + 4 + 4 + TAG_BYTES;
/// Bytes each chunk of a coalesced DATA packet ([`Body::Frames`]) spends besides its
/// payload: edge, sequence, message length, chunk index and payload length.
pub const FRAME_HEADER_BYTES: usize = 4 + 8 + 4 + 4 + 2;
/// Most ranges one ACK carries. An ACK codes its ranges as QUIC's ACK frame does (RFC 9000
/// §19.3): the largest number, then lengths and gaps as variable-length integers, 2 to 4 bytes
/// a range at the losses a link sees; how many fit in one packet is [`ack_ranges_fitting`].
/// At 20% loss a 1,024-packet window holds about 200 gaps: every one must be reported, or
/// the sender takes packets that arrived for lost and sends them again.
pub const MAX_ACK_RANGES: usize = 1024;

/// Why a datagram is not a valid packet.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WireError {
    /// Too short for the header, a field, or the tag.
    #[error("truncated packet")]
    Truncated,
    /// Not a CloudLight packet.
    #[error("bad magic")]
    Magic,
    /// Another protocol version.
    #[error("protocol version {0}, expected {VERSION}")]
    Version(u8),
    /// Unknown packet kind.
    #[error("unknown packet kind {0}")]
    Kind(u8),
    /// A field is out of range (e.g. a name that is not UTF-8, too many ranges).
    #[error("malformed field: {0}")]
    Field(&'static str),
}

/// The three handshake messages (see [`crate::endpoint`] for the protocol).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Handshake<'a> {
    /// Initiator → responder: "I want a session; here is a fresh nonce".
    Hello {
        /// Cluster id, sender and receiver names, and the sender's topology digest.
        ids: Ids<'a>,
        /// The initiator's fresh nonce.
        nonce_i: [u8; NONCE_BYTES],
    },
    /// Responder → initiator: proves the responder (its tag covers the initiator's nonce).
    Challenge {
        /// Ids, the responder's side.
        ids: Ids<'a>,
        /// The initiator's nonce, echoed.
        nonce_i: [u8; NONCE_BYTES],
        /// The responder's fresh nonce.
        nonce_r: [u8; NONCE_BYTES],
    },
    /// Initiator → responder: proves the initiator (its tag covers the responder's nonce).
    Confirm {
        /// Ids, the initiator's side.
        ids: Ids<'a>,
        /// The initiator's nonce.
        nonce_i: [u8; NONCE_BYTES],
        /// The responder's nonce, echoed.
        nonce_r: [u8; NONCE_BYTES],
    },
}

/// Who a handshake packet is from and for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Ids<'a> {
    /// Cluster id from the topology.
    pub cluster: &'a str,
    /// Sender's node name.
    pub from: &'a str,
    /// Receiver's node name.
    pub to: &'a str,
    /// Digest of the sender's topology (nodes, stages, edges, ports, policies).
    pub digest: [u8; DIGEST_BYTES],
    /// Opaque value the sender shares with its peers (the runtime sends its clock epoch).
    pub epoch: u64,
}

impl Handshake<'_> {
    /// The sender's ids.
    pub fn ids(&self) -> &Ids<'_> {
        match self {
            Handshake::Hello { ids, .. }
            | Handshake::Challenge { ids, .. }
            | Handshake::Confirm { ids, .. } => ids,
        }
    }

    /// Encodes the packet without its tag; [`crate::crypto`] appends it.
    pub fn encode_untagged(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(128);
        let (kind, ids, nonces): (u8, _, &[&[u8; NONCE_BYTES]]) = match self {
            Handshake::Hello { ids, nonce_i } => (K_HELLO, ids, &[nonce_i]),
            Handshake::Challenge {
                ids,
                nonce_i,
                nonce_r,
            } => (K_CHALLENGE, ids, &[nonce_i, nonce_r]),
            Handshake::Confirm {
                ids,
                nonce_i,
                nonce_r,
            } => (K_CONFIRM, ids, &[nonce_i, nonce_r]),
        };
        header(&mut out, kind);
        for part in [ids.cluster, ids.from, ids.to] {
            short_str(&mut out, part);
        }
        out.extend_from_slice(&ids.digest);
        out.extend_from_slice(&ids.epoch.to_le_bytes());
        for n in nonces {
            out.extend_from_slice(*n);
        }
        out
    }
}

/// Bodies of session packets.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Body<'a> {
    /// One chunk of one message of one edge.
    Data {
        /// Edge id.
        edge: u32,
        /// Message sequence on the edge, from 0.
        seq: u64,
        /// Total message length in bytes.
        len: u32,
        /// Chunk index within the message.
        chunk: u32,
        /// Chunk bytes.
        payload: &'a [u8],
    },
    /// Several chunks (of one or more messages and edges) in one packet: small messages
    /// queued for a peer travel together. `raw` holds the frames as [`encode_frame`] writes
    /// them; [`Body::decode`] has checked their framing, [`frames`] reads them.
    Frames {
        /// The encoded frames.
        raw: &'a [u8],
    },
    /// Packet numbers received, as inclusive ranges, highest first.
    Ack {
        /// The ranges.
        ranges: Vec<(u64, u64)>,
    },
    /// Cumulative credit: the sender of this packet lets the receiver have sent up to
    /// `granted` messages in total on `edge`.
    Credit {
        /// (edge, granted) pairs.
        grants: Vec<(u32, u64)>,
    },
    /// Liveness probe; `t_us` is echoed back.
    Ping {
        /// Sender's clock, microseconds.
        t_us: u64,
    },
    /// Answer to a ping.
    Pong {
        /// The ping's `t_us`.
        t_us: u64,
    },
    /// The sender is shutting down; `failed` when its run failed (its downstream peers
    /// then know their input ended early, not at the end of the run).
    Bye {
        /// Whether the sender's run failed.
        failed: bool,
    },
    /// Sent to a new address an authenticated packet came from: answer to move the link.
    PathChallenge {
        /// Random token to echo.
        token: u64,
    },
    /// Answer to a path challenge, from the address being validated.
    PathResponse {
        /// The challenge's token.
        token: u64,
    },
}

const K_HELLO: u8 = 1;
const K_CHALLENGE: u8 = 2;
const K_CONFIRM: u8 = 3;
const K_DATA: u8 = 10;
const K_ACK: u8 = 11;
const K_CREDIT: u8 = 12;
const K_PING: u8 = 13;
const K_PONG: u8 = 14;
const K_BYE: u8 = 15;
const K_PATH_CHALLENGE: u8 = 16;
const K_PATH_RESPONSE: u8 = 17;
/// DATA with several chunks.
pub const K_FRAMES: u8 = 18;

fn header(out: &mut Vec<u8>, kind: u8) {
    out.extend_from_slice(&MAGIC);
    out.push(VERSION);
    out.push(kind);
}

fn short_str(out: &mut Vec<u8>, s: &str) {
    let mut n = s.len().min(255);
    while !s.is_char_boundary(n) {
        n -= 1;
    }
    out.push(n as u8);
    out.extend_from_slice(&s.as_bytes()[..n]);
}

/// Starts a session packet: header, session id and packet number; the caller appends the
/// body (e.g. with [`Body::encode_into`]) and seals it.
pub fn session_header(kind: u8, session: u64, pn: u64, body_bytes: usize) -> Vec<u8> {
    let mut out = Vec::with_capacity(SESSION_HEADER_BYTES + body_bytes + TAG_BYTES);
    session_header_into(&mut out, kind, session, pn);
    out
}

/// Appends a session packet's header to `out`.
pub fn session_header_into(out: &mut Vec<u8>, kind: u8, session: u64, pn: u64) {
    header(out, kind);
    out.extend_from_slice(&session.to_le_bytes());
    out.extend_from_slice(&pn.to_le_bytes());
}

impl Body<'_> {
    /// The packet kind of this body.
    pub fn kind(&self) -> u8 {
        match self {
            Body::Data { .. } => K_DATA,
            Body::Frames { .. } => K_FRAMES,
            Body::Ack { .. } => K_ACK,
            Body::Credit { .. } => K_CREDIT,
            Body::Ping { .. } => K_PING,
            Body::Pong { .. } => K_PONG,
            Body::Bye { .. } => K_BYE,
            Body::PathChallenge { .. } => K_PATH_CHALLENGE,
            Body::PathResponse { .. } => K_PATH_RESPONSE,
        }
    }

    /// Whether the receiver acknowledges packets of this kind.
    pub fn ack_eliciting(&self) -> bool {
        matches!(self, Body::Data { .. } | Body::Frames { .. })
    }

    /// An unsealed session packet holding this body.
    pub fn encode(&self, session: u64, pn: u64) -> Vec<u8> {
        let size = match self {
            Body::Data { payload, .. } => 20 + payload.len(),
            Body::Frames { raw } => raw.len(),
            Body::Ack { ranges } => ack_bytes(ranges),
            Body::Credit { grants } => 2 + 12 * grants.len(),
            _ => 8,
        };
        let mut out = session_header(self.kind(), session, pn, size);
        self.encode_into(&mut out);
        out
    }

    /// Appends the whole untagged packet (header, then body) to `out`.
    pub fn encode_onto(&self, out: &mut Vec<u8>, session: u64, pn: u64) {
        session_header_into(out, self.kind(), session, pn);
        self.encode_into(out);
    }

    /// Appends the body's bytes.
    pub fn encode_into(&self, out: &mut Vec<u8>) {
        match self {
            Body::Frames { raw } => out.extend_from_slice(raw),
            Body::Data {
                edge,
                seq,
                len,
                chunk,
                payload,
            } => {
                out.extend_from_slice(&edge.to_le_bytes());
                out.extend_from_slice(&seq.to_le_bytes());
                out.extend_from_slice(&len.to_le_bytes());
                out.extend_from_slice(&chunk.to_le_bytes());
                out.extend_from_slice(payload);
            }
            Body::Ack { ranges } => {
                // Count, largest, first length, then (gap, length) pairs, highest first:
                // gap = previous low − this high − 2 (ranges never touch), length = high − low.
                let n = ack_ranges_codable(ranges);
                put_varint(out, n as u64);
                if let Some(&(lo, hi)) = ranges.first().filter(|_| n > 0) {
                    out.extend_from_slice(&hi.to_le_bytes());
                    put_varint(out, hi - lo);
                    let mut prev_lo = lo;
                    for &(lo, hi) in &ranges[1..n] {
                        put_varint(out, prev_lo - hi - 2);
                        put_varint(out, hi - lo);
                        prev_lo = lo;
                    }
                }
            }
            Body::Credit { grants } => {
                let n = grants.len().min(u16::MAX as usize);
                out.extend_from_slice(&(n as u16).to_le_bytes());
                for (edge, granted) in &grants[..n] {
                    out.extend_from_slice(&edge.to_le_bytes());
                    out.extend_from_slice(&granted.to_le_bytes());
                }
            }
            Body::Ping { t_us } | Body::Pong { t_us } => out.extend_from_slice(&t_us.to_le_bytes()),
            Body::PathChallenge { token } | Body::PathResponse { token } => {
                out.extend_from_slice(&token.to_le_bytes())
            }
            Body::Bye { failed } => out.push(u8::from(*failed)),
        }
    }

    /// Decodes a body of `kind` from its (opened) bytes.
    pub fn decode(kind: u8, bytes: &[u8]) -> Result<Body<'_>, WireError> {
        let mut r = Reader { b: bytes };
        let body = match kind {
            K_DATA => {
                let edge = r.u32()?;
                let seq = r.u64()?;
                let len = r.u32()?;
                let chunk = r.u32()?;
                return Ok(Body::Data {
                    edge,
                    seq,
                    len,
                    chunk,
                    payload: r.b,
                });
            }
            K_FRAMES => {
                let mut n = 0;
                for f in frames(bytes) {
                    f?;
                    n += 1;
                }
                if n == 0 {
                    return Err(WireError::Field("no frames"));
                }
                return Ok(Body::Frames { raw: bytes });
            }
            K_ACK => {
                let n = r.varint()?;
                if n > MAX_ACK_RANGES as u64 {
                    return Err(WireError::Field("too many ack ranges"));
                }
                let mut ranges = Vec::with_capacity(n as usize);
                if n > 0 {
                    let hi = r.u64()?;
                    let lo = hi
                        .checked_sub(r.varint()?)
                        .ok_or(WireError::Field("ack range below zero"))?;
                    ranges.push((lo, hi));
                    let mut prev_lo = lo;
                    for _ in 1..n {
                        let hi = prev_lo
                            .checked_sub(r.varint()?)
                            .and_then(|x| x.checked_sub(2))
                            .ok_or(WireError::Field("ack gap below zero"))?;
                        let lo = hi
                            .checked_sub(r.varint()?)
                            .ok_or(WireError::Field("ack range below zero"))?;
                        ranges.push((lo, hi));
                        prev_lo = lo;
                    }
                }
                Body::Ack { ranges }
            }
            K_CREDIT => {
                let n = r.u16()? as usize;
                if n * 12 != r.b.len() {
                    return Err(WireError::Field("credit count does not match length"));
                }
                let mut grants = Vec::with_capacity(n);
                for _ in 0..n {
                    grants.push((r.u32()?, r.u64()?));
                }
                Body::Credit { grants }
            }
            K_PING => Body::Ping { t_us: r.u64()? },
            K_PONG => Body::Pong { t_us: r.u64()? },
            K_BYE => Body::Bye {
                failed: r.u8()? != 0,
            },
            K_PATH_CHALLENGE => Body::PathChallenge { token: r.u64()? },
            K_PATH_RESPONSE => Body::PathResponse { token: r.u64()? },
            k => return Err(WireError::Kind(k)),
        };
        r.end()?;
        Ok(body)
    }
}

/// One decoded datagram, borrowing from it; tags are not yet checked.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Packet<'a> {
    /// A handshake packet.
    Handshake {
        /// Its fields.
        message: Handshake<'a>,
        /// The bytes its tag covers.
        tagged: &'a [u8],
        /// The tag.
        tag: &'a [u8; TAG_BYTES],
    },
    /// A session packet.
    Session(SessionPacket<'a>),
}

/// A session packet before its tag is checked.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SessionPacket<'a> {
    /// Packet kind (decode the opened body with [`Body::decode`]).
    pub kind: u8,
    /// Session id.
    pub session: u64,
    /// Packet number.
    pub pn: u64,
    /// Header and body: everything the tag covers ([`SESSION_HEADER_BYTES`] of header,
    /// never encrypted, then the body, encrypted on a confidential link).
    pub sealed: &'a [u8],
    /// The AEAD tag.
    pub tag: &'a [u8; TAG_BYTES],
}

/// Largest value a variable-length integer holds.
const MAX_VARINT: u64 = (1 << 62) - 1;

fn varint_len(v: u64) -> usize {
    match v {
        0..=63 => 1,
        64..=16_383 => 2,
        16_384..=1_073_741_823 => 4,
        _ => 8,
    }
}

/// Appends `v` (at most [`MAX_VARINT`]) as a QUIC variable-length integer.
fn put_varint(out: &mut Vec<u8>, v: u64) {
    debug_assert!(v <= MAX_VARINT);
    let len = varint_len(v);
    let tag = (len.trailing_zeros() as u64) << (8 * len - 2);
    out.extend_from_slice(&(v | tag).to_be_bytes()[8 - len..]);
}

/// How many of `ranges` (disjoint, non-adjacent, highest first) an ACK codes: all of them,
/// up to [`MAX_ACK_RANGES`] and the first that is not ordered or too far apart to code.
fn ack_ranges_codable(ranges: &[(u64, u64)]) -> usize {
    let mut n = 0;
    let mut prev_lo: Option<u64> = None;
    for &(lo, hi) in ranges.iter().take(MAX_ACK_RANGES) {
        let ok = lo <= hi
            && hi - lo <= MAX_VARINT
            && prev_lo.is_none_or(|p| p >= hi.saturating_add(2) && p - hi - 2 <= MAX_VARINT);
        if !ok {
            break;
        }
        prev_lo = Some(lo);
        n += 1;
    }
    n
}

/// Bytes of an ACK body with `ranges` (as [`Body::encode`] codes them).
fn ack_bytes(ranges: &[(u64, u64)]) -> usize {
    let n = ack_ranges_codable(ranges);
    let mut size = varint_len(n as u64);
    let mut prev_lo = None;
    for &(lo, hi) in &ranges[..n] {
        size += match prev_lo {
            None => 8,
            Some(p) => varint_len(p - hi - 2),
        } + varint_len(hi - lo);
        prev_lo = Some(lo);
    }
    size
}

/// How many of `ranges` (highest first) fit in an ACK body of at most `budget` bytes.
pub fn ack_ranges_fitting(ranges: &[(u64, u64)], budget: usize) -> usize {
    let n = ack_ranges_codable(ranges);
    let mut size = varint_len(n as u64).max(2);
    let mut prev_lo = None;
    for (k, &(lo, hi)) in ranges[..n].iter().enumerate() {
        size += match prev_lo {
            None => 8,
            Some(p) => varint_len(p - hi - 2),
        } + varint_len(hi - lo);
        if size > budget {
            return k;
        }
        prev_lo = Some(lo);
    }
    n
}

struct Reader<'a> {
    b: &'a [u8],
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], WireError> {
        if self.b.len() < n {
            return Err(WireError::Truncated);
        }
        let (head, rest) = self.b.split_at(n);
        self.b = rest;
        Ok(head)
    }
    fn array<const N: usize>(&mut self) -> Result<[u8; N], WireError> {
        Ok(self.take(N)?.try_into().expect("N bytes"))
    }
    fn u8(&mut self) -> Result<u8, WireError> {
        Ok(self.take(1)?[0])
    }
    fn u16(&mut self) -> Result<u16, WireError> {
        Ok(u16::from_le_bytes(self.array()?))
    }
    fn u32(&mut self) -> Result<u32, WireError> {
        Ok(u32::from_le_bytes(self.array()?))
    }
    fn u64(&mut self) -> Result<u64, WireError> {
        Ok(u64::from_le_bytes(self.array()?))
    }
    /// A QUIC variable-length integer (RFC 9000 §16): the top two bits of the first byte
    /// give its length, 1, 2, 4 or 8 bytes, big-endian.
    fn varint(&mut self) -> Result<u64, WireError> {
        let first = self.u8()?;
        let len = 1usize << (first >> 6);
        let mut v = u64::from(first & 0x3F);
        for &b in self.take(len - 1)? {
            v = (v << 8) | u64::from(b);
        }
        Ok(v)
    }
    fn short_str(&mut self) -> Result<&'a str, WireError> {
        let n = self.u8()? as usize;
        std::str::from_utf8(self.take(n)?).map_err(|_| WireError::Field("name is not UTF-8"))
    }
    fn ids(&mut self) -> Result<Ids<'a>, WireError> {
        Ok(Ids {
            cluster: self.short_str()?,
            from: self.short_str()?,
            to: self.short_str()?,
            digest: self.array()?,
            epoch: self.u64()?,
        })
    }
    fn end(&self) -> Result<(), WireError> {
        if self.b.is_empty() {
            Ok(())
        } else {
            Err(WireError::Field("trailing bytes"))
        }
    }
}

/// One chunk of a coalesced DATA packet.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Frame<'a> {
    /// Edge id.
    pub edge: u32,
    /// Message sequence on the edge.
    pub seq: u64,
    /// Total message length in bytes.
    pub len: u32,
    /// Chunk index within the message.
    pub chunk: u32,
    /// Chunk bytes.
    pub payload: &'a [u8],
}

/// Appends one frame of a [`Body::Frames`] packet; `payload` is at most 65,535 bytes (a
/// chunk is one packet's worth).
pub fn encode_frame(out: &mut Vec<u8>, f: &Frame<'_>) {
    let n = u16::try_from(f.payload.len()).expect("a chunk fits in one packet");
    out.extend_from_slice(&f.edge.to_le_bytes());
    out.extend_from_slice(&f.seq.to_le_bytes());
    out.extend_from_slice(&f.len.to_le_bytes());
    out.extend_from_slice(&f.chunk.to_le_bytes());
    out.extend_from_slice(&n.to_le_bytes());
    out.extend_from_slice(f.payload);
}

/// The frames of a [`Body::Frames`] packet, in order; a malformed one ends the walk with
/// an error.
pub fn frames(raw: &[u8]) -> impl Iterator<Item = Result<Frame<'_>, WireError>> + '_ {
    let mut r = Reader { b: raw };
    let mut failed = false;
    std::iter::from_fn(move || {
        if failed || r.b.is_empty() {
            return None;
        }
        let frame = (|| {
            let edge = r.u32()?;
            let seq = r.u64()?;
            let len = r.u32()?;
            let chunk = r.u32()?;
            let n = r.u16()? as usize;
            if r.b.len() < n {
                return Err(WireError::Truncated);
            }
            let (payload, rest) = r.b.split_at(n);
            r.b = rest;
            Ok(Frame {
                edge,
                seq,
                len,
                chunk,
                payload,
            })
        })();
        failed = frame.is_err();
        Some(frame)
    })
}

/// Decodes one datagram's framing (tags are checked by the endpoint).
pub fn decode(datagram: &[u8]) -> Result<Packet<'_>, WireError> {
    if datagram.len() < HEADER_BYTES + TAG_BYTES {
        return Err(WireError::Truncated);
    }
    if datagram[..2] != MAGIC {
        return Err(WireError::Magic);
    }
    if datagram[2] != VERSION {
        return Err(WireError::Version(datagram[2]));
    }
    let kind = datagram[3];
    let (content, tag) = datagram.split_at(datagram.len() - TAG_BYTES);
    let tag: &[u8; TAG_BYTES] = tag.try_into().expect("TAG_BYTES");
    let mut r = Reader {
        b: &content[HEADER_BYTES..],
    };
    let message = match kind {
        K_HELLO => Handshake::Hello {
            ids: r.ids()?,
            nonce_i: r.array()?,
        },
        K_CHALLENGE => Handshake::Challenge {
            ids: r.ids()?,
            nonce_i: r.array()?,
            nonce_r: r.array()?,
        },
        K_CONFIRM => Handshake::Confirm {
            ids: r.ids()?,
            nonce_i: r.array()?,
            nonce_r: r.array()?,
        },
        K_DATA..=K_FRAMES => {
            if content.len() < SESSION_HEADER_BYTES {
                return Err(WireError::Truncated);
            }
            let session = r.u64()?;
            let pn = r.u64()?;
            return Ok(Packet::Session(SessionPacket {
                kind,
                session,
                pn,
                sealed: content,
                tag,
            }));
        }
        k => return Err(WireError::Kind(k)),
    };
    r.end()?;
    Ok(Packet::Handshake {
        message,
        tagged: content,
        tag,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn body_round_trip(body: Body<'_>) {
        let mut bytes = body.encode(42, 7);
        bytes.extend_from_slice(&[0; TAG_BYTES]);
        let Packet::Session(p) = decode(&bytes).unwrap() else {
            panic!("a session packet")
        };
        assert_eq!((p.session, p.pn, p.kind), (42, 7, body.kind()));
        assert_eq!(
            Body::decode(p.kind, &p.sealed[SESSION_HEADER_BYTES..]).unwrap(),
            body
        );
    }

    fn ids() -> Ids<'static> {
        Ids {
            cluster: "c",
            from: "cloud",
            to: "client",
            digest: [3; DIGEST_BYTES],
            epoch: 9,
        }
    }

    #[test]
    fn coalesced_frames_round_trip_and_garbage_is_refused() {
        let payloads: [&[u8]; 3] = [b"", b"abc", &[7; 600]];
        let mut raw = Vec::new();
        let sent: Vec<Frame<'_>> = payloads
            .iter()
            .enumerate()
            .map(|(i, p)| Frame {
                edge: i as u32,
                seq: 10 + i as u64,
                len: 5000,
                chunk: i as u32 * 2,
                payload: p,
            })
            .collect();
        for f in &sent {
            encode_frame(&mut raw, f);
        }
        assert_eq!(raw.len(), 3 * FRAME_HEADER_BYTES + 603);
        body_round_trip(Body::Frames { raw: &raw });
        let got: Vec<Frame<'_>> = frames(&raw).map(Result::unwrap).collect();
        assert_eq!(got, sent);
        // Truncated anywhere, or empty: refused.
        for cut in [1, FRAME_HEADER_BYTES, raw.len() - 1] {
            assert!(
                Body::decode(K_FRAMES, &raw[..raw.len() - cut]).is_err(),
                "cut {cut}"
            );
        }
        assert!(Body::decode(K_FRAMES, &[]).is_err());
    }

    #[test]
    fn every_kind_round_trips() {
        for message in [
            Handshake::Hello {
                ids: ids(),
                nonce_i: [1; NONCE_BYTES],
            },
            Handshake::Challenge {
                ids: ids(),
                nonce_i: [1; NONCE_BYTES],
                nonce_r: [2; NONCE_BYTES],
            },
            Handshake::Confirm {
                ids: ids(),
                nonce_i: [1; NONCE_BYTES],
                nonce_r: [2; NONCE_BYTES],
            },
        ] {
            let mut bytes = message.encode_untagged();
            let n = bytes.len();
            bytes.extend_from_slice(&[5; TAG_BYTES]);
            let Packet::Handshake {
                message: m,
                tagged,
                tag,
            } = decode(&bytes).unwrap()
            else {
                panic!("a handshake packet")
            };
            assert_eq!(m, message);
            assert_eq!(tagged.len(), n);
            assert_eq!(tag, &[5; TAG_BYTES]);
        }
        body_round_trip(Body::Data {
            edge: 2,
            seq: 3,
            len: 4,
            chunk: 0,
            payload: b"abcd",
        });
        body_round_trip(Body::Data {
            edge: 2,
            seq: 3,
            len: 0,
            chunk: 0,
            payload: b"",
        });
        body_round_trip(Body::Ack {
            ranges: vec![(10, 20), (1, 5)],
        });
        body_round_trip(Body::Ack { ranges: vec![] });
        // Ranges too far apart for a variable-length integer: the ACK stops before them.
        let mut far = Body::Ack {
            ranges: vec![(u64::MAX - 3, u64::MAX), (0, 0)],
        }
        .encode(42, 7);
        far.extend_from_slice(&[0; TAG_BYTES]);
        let Packet::Session(p) = decode(&far).unwrap() else {
            panic!("a session packet")
        };
        assert_eq!(
            Body::decode(p.kind, &p.sealed[SESSION_HEADER_BYTES..]).unwrap(),
            Body::Ack {
                ranges: vec![(u64::MAX - 3, u64::MAX)]
            }
        );
        body_round_trip(Body::Credit {
            grants: vec![(0, 4), (7, 100)],
        });
        body_round_trip(Body::Ping { t_us: 5 });
        body_round_trip(Body::Pong { t_us: 5 });
        body_round_trip(Body::Bye { failed: false });
        body_round_trip(Body::Bye { failed: true });
        body_round_trip(Body::PathChallenge { token: 77 });
        body_round_trip(Body::PathResponse { token: 77 });
        let data = Body::Data {
            edge: 1,
            seq: 2,
            len: 3,
            chunk: 0,
            payload: &[1, 2, 3],
        };
        assert_eq!(data.encode(1, 1).len() + TAG_BYTES, DATA_OVERHEAD + 3);
    }

    #[test]
    fn long_names_are_cut_at_a_character_boundary() {
        let name = "é".repeat(200);
        let mut out = Vec::new();
        short_str(&mut out, &name);
        assert_eq!(out[0], 254);
        assert!(std::str::from_utf8(&out[1..]).is_ok());
    }

    proptest! {
        /// Any set of ranges (disjoint, non-adjacent, highest first, numbers up to 2^62)
        /// round-trips, and `ack_ranges_fitting` never lets an ACK outgrow its budget.
        #[test]
        fn ack_ranges_round_trip_and_fit_their_budget(
            top in 0u64..(1 << 40),
            steps in proptest::collection::vec((0u64..5_000, 0u64..300), 0..1_200),
            budget in 12usize..2_000,
        ) {
            let mut ranges = Vec::new();
            let mut hi = top + (1 << 41);
            for (gap, len) in steps {
                let Some(lo) = hi.checked_sub(len) else { break };
                ranges.push((lo, hi));
                let Some(next) = lo.checked_sub(gap + 2) else { break };
                hi = next;
            }
            let n = ranges.len().min(MAX_ACK_RANGES);
            let body = Body::Ack { ranges: ranges[..n].to_vec() };
            body_round_trip(body.clone());
            prop_assert_eq!(body.encode(1, 1).len() - SESSION_HEADER_BYTES, ack_bytes(&ranges[..n]));
            let k = ack_ranges_fitting(&ranges, budget);
            prop_assert!(ack_bytes(&ranges[..k]) <= budget, "{} ranges in {} bytes", k, budget);
        }

        #[test]
        fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
            if let Ok(Packet::Session(p)) = decode(&bytes) {
                let _ = Body::decode(p.kind, &p.sealed[SESSION_HEADER_BYTES..]);
            }
        }

        #[test]
        fn random_bodies_after_a_valid_header_never_panic(kind in 0u8..20, body in proptest::collection::vec(any::<u8>(), 0..300)) {
            let mut out = Vec::new();
            header(&mut out, kind);
            out.extend_from_slice(&body);
            if let Ok(Packet::Session(p)) = decode(&out) {
                let _ = Body::decode(p.kind, &p.sealed[SESSION_HEADER_BYTES..]);
            }
            let _ = Body::decode(kind, &body);
        }
    }
}
