//! The transport's packet format: every datagram the transport hands laminar is one of these.
//!
//! ```text
//! 0  magic "CL" | 2 version u8 | 3 kind u8 | 4 sender incarnation u64 | 12 body ... | crc32 u32
//! ```
//! All integers are little-endian. The CRC-32 covers every byte before it. Decoding borrows
//! from the datagram (no allocation), checks every length against the bytes present, and
//! never panics: any malformed input is a [`WireError`].

/// Protocol version carried by every packet.
pub const VERSION: u8 = 1;
const MAGIC: [u8; 2] = *b"CL";
/// Bytes of the common header (magic, version, kind, incarnation).
pub const HEADER_BYTES: usize = 12;
/// Bytes of the trailing checksum.
pub const CRC_BYTES: usize = 4;
/// Bytes a DATA packet spends besides its payload.
pub const DATA_OVERHEAD: usize = HEADER_BYTES + 8 + 4 + 8 + 4 + 4 + CRC_BYTES;
/// Most ranges one ACK carries.
pub const MAX_ACK_RANGES: usize = 64;
/// Bytes of the hello authentication tag.
pub const MAC_BYTES: usize = 16;

/// Why a datagram is not a valid packet.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WireError {
    /// Too short for the header, a field, or the checksum.
    #[error("truncated packet")]
    Truncated,
    /// Not a CloudLight packet.
    #[error("bad magic")]
    Magic,
    /// Another protocol version.
    #[error("protocol version {0}, expected {VERSION}")]
    Version(u8),
    /// Checksum mismatch.
    #[error("checksum mismatch")]
    Checksum,
    /// Unknown packet kind.
    #[error("unknown packet kind {0}")]
    Kind(u8),
    /// A field is out of range (e.g. a name that is not UTF-8, too many ranges).
    #[error("malformed field: {0}")]
    Field(&'static str),
}

/// One decoded packet, borrowing from the datagram.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Packet<'a> {
    /// Incarnation (random per process start) of the sending node.
    pub incarnation: u64,
    /// What the packet carries.
    pub body: Body<'a>,
}

/// Packet bodies.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Body<'a> {
    /// Handshake: who I am, which incarnation of you I have seen, and proof of the secret.
    Hello {
        /// Cluster id from the topology.
        cluster: &'a str,
        /// Sender's node name.
        from: &'a str,
        /// Receiver's node name.
        to: &'a str,
        /// Opaque value the sender shares with its peers (the runtime sends its clock epoch).
        epoch: u64,
        /// The receiver's incarnation as the sender knows it (0: none yet).
        seen: u64,
        /// Whether this hello answers one (answers are not answered).
        reply: bool,
        /// Truncated HMAC-SHA256 over the fields above.
        mac: [u8; MAC_BYTES],
    },
    /// One chunk of one message of one edge.
    Data {
        /// Packet number (per direction of a peer link, from 1).
        pn: u64,
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
    /// The sender is shutting down.
    Bye,
}

const K_HELLO: u8 = 1;
const K_DATA: u8 = 2;
const K_ACK: u8 = 3;
const K_CREDIT: u8 = 4;
const K_PING: u8 = 5;
const K_PONG: u8 = 6;
const K_BYE: u8 = 7;

fn header(out: &mut Vec<u8>, kind: u8, incarnation: u64) {
    out.extend_from_slice(&MAGIC);
    out.push(VERSION);
    out.push(kind);
    out.extend_from_slice(&incarnation.to_le_bytes());
}

fn seal(mut out: Vec<u8>) -> Vec<u8> {
    let crc = crc32fast::hash(&out);
    out.extend_from_slice(&crc.to_le_bytes());
    out
}

fn short_str(out: &mut Vec<u8>, s: &str) {
    let b = &s.as_bytes()[..s.len().min(255)];
    out.push(b.len() as u8);
    out.extend_from_slice(b);
}

impl Body<'_> {
    /// Encodes the packet.
    pub fn encode(&self, incarnation: u64) -> Vec<u8> {
        let mut out = Vec::with_capacity(64);
        match self {
            Body::Hello {
                cluster,
                from,
                to,
                epoch,
                seen,
                reply,
                mac,
            } => {
                header(&mut out, K_HELLO, incarnation);
                short_str(&mut out, cluster);
                short_str(&mut out, from);
                short_str(&mut out, to);
                out.extend_from_slice(&epoch.to_le_bytes());
                out.extend_from_slice(&seen.to_le_bytes());
                out.push(u8::from(*reply));
                out.extend_from_slice(mac);
            }
            Body::Data {
                pn,
                edge,
                seq,
                len,
                chunk,
                payload,
            } => {
                return encode_data(incarnation, *pn, *edge, *seq, *len, *chunk, payload);
            }
            Body::Ack { ranges } => {
                header(&mut out, K_ACK, incarnation);
                let n = ranges.len().min(MAX_ACK_RANGES);
                out.extend_from_slice(&(n as u16).to_le_bytes());
                for (lo, hi) in &ranges[..n] {
                    out.extend_from_slice(&lo.to_le_bytes());
                    out.extend_from_slice(&hi.to_le_bytes());
                }
            }
            Body::Credit { grants } => {
                header(&mut out, K_CREDIT, incarnation);
                let n = grants.len().min(u16::MAX as usize);
                out.extend_from_slice(&(n as u16).to_le_bytes());
                for (edge, granted) in &grants[..n] {
                    out.extend_from_slice(&edge.to_le_bytes());
                    out.extend_from_slice(&granted.to_le_bytes());
                }
            }
            Body::Ping { t_us } => {
                header(&mut out, K_PING, incarnation);
                out.extend_from_slice(&t_us.to_le_bytes());
            }
            Body::Pong { t_us } => {
                header(&mut out, K_PONG, incarnation);
                out.extend_from_slice(&t_us.to_le_bytes());
            }
            Body::Bye => header(&mut out, K_BYE, incarnation),
        }
        seal(out)
    }
}

/// Encodes a DATA packet without building a [`Body`] (the hot path).
pub fn encode_data(
    incarnation: u64,
    pn: u64,
    edge: u32,
    seq: u64,
    len: u32,
    chunk: u32,
    payload: &[u8],
) -> Vec<u8> {
    let mut out = Vec::with_capacity(DATA_OVERHEAD + payload.len());
    header(&mut out, K_DATA, incarnation);
    out.extend_from_slice(&pn.to_le_bytes());
    out.extend_from_slice(&edge.to_le_bytes());
    out.extend_from_slice(&seq.to_le_bytes());
    out.extend_from_slice(&len.to_le_bytes());
    out.extend_from_slice(&chunk.to_le_bytes());
    out.extend_from_slice(payload);
    seal(out)
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
    fn u8(&mut self) -> Result<u8, WireError> {
        Ok(self.take(1)?[0])
    }
    fn u16(&mut self) -> Result<u16, WireError> {
        Ok(u16::from_le_bytes(
            self.take(2)?.try_into().expect("2 bytes"),
        ))
    }
    fn u32(&mut self) -> Result<u32, WireError> {
        Ok(u32::from_le_bytes(
            self.take(4)?.try_into().expect("4 bytes"),
        ))
    }
    fn u64(&mut self) -> Result<u64, WireError> {
        Ok(u64::from_le_bytes(
            self.take(8)?.try_into().expect("8 bytes"),
        ))
    }
    fn short_str(&mut self) -> Result<&'a str, WireError> {
        let n = self.u8()? as usize;
        std::str::from_utf8(self.take(n)?).map_err(|_| WireError::Field("name is not UTF-8"))
    }
    fn end(&self) -> Result<(), WireError> {
        if self.b.is_empty() {
            Ok(())
        } else {
            Err(WireError::Field("trailing bytes"))
        }
    }
}

/// Decodes one datagram.
pub fn decode(datagram: &[u8]) -> Result<Packet<'_>, WireError> {
    if datagram.len() < HEADER_BYTES + CRC_BYTES {
        return Err(WireError::Truncated);
    }
    if datagram[..2] != MAGIC {
        return Err(WireError::Magic);
    }
    if datagram[2] != VERSION {
        return Err(WireError::Version(datagram[2]));
    }
    let (content, crc) = datagram.split_at(datagram.len() - CRC_BYTES);
    if crc32fast::hash(content) != u32::from_le_bytes(crc.try_into().expect("4 bytes")) {
        return Err(WireError::Checksum);
    }
    let mut r = Reader { b: &content[3..] };
    let kind = r.u8()?;
    let incarnation = r.u64()?;
    let body = match kind {
        K_HELLO => {
            let cluster = r.short_str()?;
            let from = r.short_str()?;
            let to = r.short_str()?;
            let epoch = r.u64()?;
            let seen = r.u64()?;
            let reply = match r.u8()? {
                0 => false,
                1 => true,
                _ => return Err(WireError::Field("reply flag")),
            };
            let mac = r.take(MAC_BYTES)?.try_into().expect("MAC_BYTES");
            r.end()?;
            Body::Hello {
                cluster,
                from,
                to,
                epoch,
                seen,
                reply,
                mac,
            }
        }
        K_DATA => {
            let pn = r.u64()?;
            let edge = r.u32()?;
            let seq = r.u64()?;
            let len = r.u32()?;
            let chunk = r.u32()?;
            Body::Data {
                pn,
                edge,
                seq,
                len,
                chunk,
                payload: r.b,
            }
        }
        K_ACK => {
            let n = r.u16()? as usize;
            if n > MAX_ACK_RANGES {
                return Err(WireError::Field("too many ack ranges"));
            }
            let mut ranges = Vec::with_capacity(n);
            for _ in 0..n {
                let (lo, hi) = (r.u64()?, r.u64()?);
                if lo > hi {
                    return Err(WireError::Field("empty ack range"));
                }
                ranges.push((lo, hi));
            }
            r.end()?;
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
        K_PING => {
            let t_us = r.u64()?;
            r.end()?;
            Body::Ping { t_us }
        }
        K_PONG => {
            let t_us = r.u64()?;
            r.end()?;
            Body::Pong { t_us }
        }
        K_BYE => {
            r.end()?;
            Body::Bye
        }
        k => return Err(WireError::Kind(k)),
    };
    Ok(Packet { incarnation, body })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn round_trip(body: Body<'_>) {
        let bytes = body.encode(42);
        let p = decode(&bytes).unwrap();
        assert_eq!(p.incarnation, 42);
        assert_eq!(p.body, body);
    }

    #[test]
    fn every_kind_round_trips() {
        round_trip(Body::Hello {
            cluster: "c",
            from: "cloud",
            to: "client",
            epoch: 9,
            seen: 3,
            reply: true,
            mac: [7; MAC_BYTES],
        });
        round_trip(Body::Data {
            pn: 1,
            edge: 2,
            seq: 3,
            len: 4,
            chunk: 0,
            payload: b"abcd",
        });
        round_trip(Body::Data {
            pn: 1,
            edge: 2,
            seq: 3,
            len: 0,
            chunk: 0,
            payload: b"",
        });
        round_trip(Body::Ack {
            ranges: vec![(10, 20), (1, 5)],
        });
        round_trip(Body::Credit {
            grants: vec![(0, 4), (7, 100)],
        });
        round_trip(Body::Ping { t_us: 5 });
        round_trip(Body::Pong { t_us: 5 });
        round_trip(Body::Bye);
        let d = encode_data(1, 2, 3, 4, 5, 6, &[1, 2, 3]);
        assert_eq!(d.len(), DATA_OVERHEAD + 3);
    }

    #[test]
    fn a_flipped_bit_is_caught_by_the_checksum() {
        let mut bytes = Body::Ping { t_us: 77 }.encode(1);
        bytes[14] ^= 0x10;
        assert_eq!(decode(&bytes), Err(WireError::Checksum));
    }

    proptest! {
        #[test]
        fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
            let _ = decode(&bytes);
        }

        #[test]
        fn random_bodies_with_a_valid_checksum_never_panic(kind in 0u8..10, body in proptest::collection::vec(any::<u8>(), 0..300)) {
            let mut out = Vec::new();
            header(&mut out, kind, 5);
            out.extend_from_slice(&body);
            let _ = decode(&seal(out));
        }
    }
}
