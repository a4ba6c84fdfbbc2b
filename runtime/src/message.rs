//! Edge messages: the [`Stamped`] envelope every message travels in, and the type-erased
//! [`MessageType`] descriptor that lets the runtime move, measure and (when an edge is cut)
//! encode a message without knowing its type.
//!
//! Stages see typed values; the runtime sees `Arc<dyn Any>` plus a `MessageType`. Fan-out
//! clones the `Arc`, so a message computed once is shared by every consumer, never copied.

use std::any::{Any, TypeId};
use std::sync::Arc;

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

use crate::codec::{self, CodecError};

/// What a value needs to travel on an edge: serializable (any edge may be cut) and shareable
/// between threads.
pub trait Message: Serialize + DeserializeOwned + Send + Sync + 'static {}
impl<T: Serialize + DeserializeOwned + Send + Sync + 'static> Message for T {}

/// The envelope of every edge message.
///
/// `scene_time_s` is the scene time the content was computed for (so a consumer can measure
/// the age of the lighting it shows); `produced_unix_ns` is the wall-clock time the producer
/// sent it; `seq` counts messages per output port of the producing instance, from 0.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Stamped<T> {
    /// Scene time (seconds) the body was computed for.
    pub scene_time_s: f64,
    /// Wall-clock send time, nanoseconds since the Unix epoch.
    pub produced_unix_ns: u64,
    /// Per-port sequence number of the producer, from 0.
    pub seq: u64,
    /// The payload.
    pub body: T,
}

/// A message as the runtime holds it: a shared, type-erased `Stamped<T>`.
pub type AnyMessage = Arc<dyn Any + Send + Sync>;

/// Type descriptor of the messages on a port: identity for wiring checks, and the functions
/// that measure, encode and decode a type-erased [`Stamped`] value of that type.
#[derive(Clone, Copy)]
pub struct MessageType {
    type_id: TypeId,
    name: &'static str,
    wire_len: fn(&AnyMessage) -> Result<usize, CodecError>,
    encode: fn(&AnyMessage) -> Result<Vec<u8>, CodecError>,
    decode: fn(&[u8]) -> Result<AnyMessage, CodecError>,
}

impl std::fmt::Debug for MessageType {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name)
    }
}

impl PartialEq for MessageType {
    fn eq(&self, other: &Self) -> bool {
        self.type_id == other.type_id
    }
}

impl Eq for MessageType {}

impl MessageType {
    /// The descriptor of `Stamped<T>` messages.
    pub fn of<T: Message>() -> Self {
        fn downcast<T: Message>(m: &AnyMessage) -> &Stamped<T> {
            m.downcast_ref::<Stamped<T>>()
                .expect("the runtime checks port types when it wires edges")
        }
        MessageType {
            type_id: TypeId::of::<Stamped<T>>(),
            name: std::any::type_name::<T>(),
            wire_len: |m| codec::encoded_len(downcast::<T>(m)),
            encode: |m| codec::encode(downcast::<T>(m)),
            decode: |b| Ok(Arc::new(codec::decode::<Stamped<T>>(b)?) as AnyMessage),
        }
    }

    /// Rust name of the payload type (for diagnostics).
    pub fn name(&self) -> &'static str {
        self.name
    }

    /// Whether `msg` is a `Stamped` value of this type.
    pub fn matches(&self, msg: &AnyMessage) -> bool {
        (**msg).type_id() == self.type_id
    }

    /// Encoded size of `msg` in bytes (what it costs on a cut edge).
    pub fn wire_len(&self, msg: &AnyMessage) -> Result<usize, CodecError> {
        (self.wire_len)(msg)
    }

    /// Encodes `msg` with the [`codec`].
    pub fn encode(&self, msg: &AnyMessage) -> Result<Vec<u8>, CodecError> {
        (self.encode)(msg)
    }

    /// Decodes bytes written by [`MessageType::encode`] for this type.
    pub fn decode(&self, bytes: &[u8]) -> Result<AnyMessage, CodecError> {
        (self.decode)(bytes)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn type_erased_round_trip() {
        let ty = MessageType::of::<Vec<u16>>();
        let msg: AnyMessage = Arc::new(Stamped {
            scene_time_s: 1.25,
            produced_unix_ns: 42,
            seq: 7,
            body: vec![1u16, 2, 3],
        });
        assert!(ty.matches(&msg));
        assert!(!MessageType::of::<Vec<u32>>().matches(&msg));
        let bytes = ty.encode(&msg).unwrap();
        assert_eq!(bytes.len(), ty.wire_len(&msg).unwrap());
        let back = ty.decode(&bytes).unwrap();
        let back = back.downcast_ref::<Stamped<Vec<u16>>>().unwrap();
        assert_eq!(back, msg.downcast_ref::<Stamped<Vec<u16>>>().unwrap());
    }
}
