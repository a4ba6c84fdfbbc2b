//! The one place where edge messages become bytes and back.
//!
//! Every edge message is encoded as a 2-byte little-endian wire version followed by the
//! message's bincode 2 encoding (standard configuration: little-endian, varint lengths).
//! Decoding checks the version, refuses to allocate past [`MAX_MESSAGE_BYTES`] and rejects
//! trailing bytes, so a corrupt or forged message is an error, never a panic or a huge
//! allocation. Swapping the wire format (to measure another one) means changing this module
//! only. This module must not know about edges, actors or sockets.

use serde::Serialize;
use serde::de::DeserializeOwned;

/// Version of the edge wire format; bump it when the encoding of any edge message changes.
pub const WIRE_VERSION: u16 = 1;

/// Largest encoded message accepted by [`decode`], in bytes (64 MiB).
pub const MAX_MESSAGE_BYTES: usize = 64 << 20;

/// Why a message could not be encoded or decoded.
#[derive(Debug, thiserror::Error)]
pub enum CodecError {
    /// The bytes end before the 2-byte version header.
    #[error("message of {0} bytes is shorter than the 2-byte version header")]
    Truncated(usize),
    /// The message was written by another wire version.
    #[error("wire version {found} is not the supported version {WIRE_VERSION}")]
    Version {
        /// Version found in the header.
        found: u16,
    },
    /// bincode could not encode the value.
    #[error("encode: {0}")]
    Encode(#[from] bincode::error::EncodeError),
    /// bincode could not decode the bytes (corrupt, wrong type or over the size bound).
    #[error("decode: {0}")]
    Decode(#[from] bincode::error::DecodeError),
    /// The message decoded but bytes were left over.
    #[error("{extra} trailing bytes after the message")]
    Trailing {
        /// Bytes left over after decoding.
        extra: usize,
    },
}

type Config = bincode::config::Configuration<
    bincode::config::LittleEndian,
    bincode::config::Varint,
    bincode::config::Limit<MAX_MESSAGE_BYTES>,
>;

fn config() -> Config {
    bincode::config::standard().with_limit::<MAX_MESSAGE_BYTES>()
}

/// Encodes `value` as version header + bincode.
pub fn encode<T: Serialize + ?Sized>(value: &T) -> Result<Vec<u8>, CodecError> {
    let mut out = Vec::with_capacity(2 + encoded_len(value)?);
    out.extend_from_slice(&WIRE_VERSION.to_le_bytes());
    let body = bincode::serde::encode_to_vec(value, config())?;
    out.extend_from_slice(&body);
    Ok(out)
}

/// Decodes bytes written by [`encode`].
pub fn decode<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, CodecError> {
    let Some((header, body)) = bytes.split_first_chunk::<2>() else {
        return Err(CodecError::Truncated(bytes.len()));
    };
    let found = u16::from_le_bytes(*header);
    if found != WIRE_VERSION {
        return Err(CodecError::Version { found });
    }
    let (value, used) = bincode::serde::decode_from_slice(body, config())?;
    if used != body.len() {
        return Err(CodecError::Trailing {
            extra: body.len() - used,
        });
    }
    Ok(value)
}

/// Size in bytes that [`encode`] would produce, computed without allocating the buffer.
pub fn encoded_len<T: Serialize + ?Sized>(value: &T) -> Result<usize, CodecError> {
    struct Counter<'a>(&'a mut usize);
    impl bincode::enc::write::Writer for Counter<'_> {
        fn write(&mut self, bytes: &[u8]) -> Result<(), bincode::error::EncodeError> {
            *self.0 += bytes.len();
            Ok(())
        }
    }
    let mut n = 2;
    bincode::serde::encode_into_writer(value, Counter(&mut n), config())?;
    Ok(n)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn length_matches_encoding() {
        let v = (1u32, "hello".to_string(), vec![1.5f32; 100]);
        assert_eq!(encode(&v).unwrap().len(), encoded_len(&v).unwrap());
    }

    #[test]
    fn rejects_wrong_version_truncation_and_trailing_bytes() {
        let mut bytes = encode(&7u64).unwrap();
        assert!(matches!(
            decode::<u64>(&bytes[..1]),
            Err(CodecError::Truncated(1))
        ));
        bytes.push(0);
        assert!(matches!(
            decode::<u64>(&bytes),
            Err(CodecError::Trailing { extra: 1 })
        ));
        bytes[0] ^= 0xff;
        assert!(matches!(
            decode::<u64>(&bytes),
            Err(CodecError::Version { .. })
        ));
    }

    #[test]
    fn forged_length_does_not_allocate_past_the_bound() {
        // A Vec<u8> claiming u64::MAX elements: varint tag 253 then 8 bytes.
        let mut bytes = WIRE_VERSION.to_le_bytes().to_vec();
        bytes.push(253);
        bytes.extend_from_slice(&u64::MAX.to_le_bytes());
        assert!(decode::<Vec<u8>>(&bytes).is_err());
    }

    proptest! {
        #[test]
        fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..256)) {
            let _ = decode::<(u64, String, Vec<f32>)>(&bytes);
        }

        #[test]
        fn round_trip(a in any::<u64>(), s in ".*", v in proptest::collection::vec(any::<f32>(), 0..64)) {
            let value = (a, s, v);
            let back: (u64, String, Vec<f32>) = decode(&encode(&value).unwrap()).unwrap();
            prop_assert_eq!(back.0, value.0);
            prop_assert_eq!(&back.1, &value.1);
            prop_assert_eq!(back.2.len(), value.2.len());
            for (x, y) in back.2.iter().zip(&value.2) {
                prop_assert_eq!(x.to_bits(), y.to_bits());
            }
        }
    }
}
