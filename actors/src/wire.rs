//! The wire message types of every edge. Each is serde-serializable because any edge may be
//! cut; the runtime wraps each in `Stamped<T>` and encodes it with `cloudlight_runtime::codec`.
//! Techniques add their batch, delta and frame types here as they arrive.

pub use cloudlight_render::HdrMap;
use serde::{Deserialize, Serialize};

/// A probe message: a payload whose bytes follow [`ProbeMsg::pattern`], so a receiver can
/// check that nothing was corrupted on the way.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ProbeMsg {
    /// Index of the message at its source, from 0.
    pub index: u64,
    /// `payload[k] == pattern(seed, index, k)`.
    #[serde(with = "serde_bytes")]
    pub payload: Vec<u8>,
}

impl ProbeMsg {
    /// Byte `k` of message `index` from a source seeded with `seed`.
    pub fn pattern(seed: u64, index: u64, k: usize) -> u8 {
        let x = seed
            .wrapping_mul(0x9E37_79B9_7F4A_7C15)
            .wrapping_add(index.wrapping_mul(31))
            .wrapping_add(k as u64);
        (x ^ (x >> 29)) as u8
    }

    /// A message of `len` pattern bytes.
    pub fn new(seed: u64, index: u64, len: usize) -> Self {
        ProbeMsg {
            index,
            payload: (0..len).map(|k| Self::pattern(seed, index, k)).collect(),
        }
    }

    /// Whether the payload still follows the pattern.
    pub fn is_intact(&self, seed: u64) -> bool {
        self.payload
            .iter()
            .enumerate()
            .all(|(k, &b)| b == Self::pattern(seed, self.index, k))
    }
}

/// A picture for a `video_encoder`: a client's SDR frame or an HDR light map.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum FrameMsg {
    /// sRGB-encoded RGB8, row-major from the top (3 bytes per pixel).
    Sdr {
        /// Width, pixels (even).
        width: u32,
        /// Height, pixels (even).
        height: u32,
        /// The pixels.
        #[serde(with = "serde_bytes")]
        rgb: Vec<u8>,
        /// Scene time of the indirect light the frame shows, when the renderer knows it (a
        /// client rendering in the cloud); the frame's own stamp is its render time.
        light_s: Option<f64>,
    },
    /// An HDR light map (f16 texels and coverage bits: the same bits in process and on the
    /// wire; check it with [`HdrMap::check`] before use).
    Hdr {
        /// The map.
        map: HdrMap,
        /// The scene is static and the map has converged: it stays valid until a newer map
        /// supersedes it (a client holding it shows current light, whatever its stamp).
        steady: bool,
    },
}

/// One H.264 access unit from a `video_encoder` (the runtime's stamp carries the scene time
/// of the picture it encodes).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct VideoMsg {
    /// Pictures the encoder was given before this one.
    pub index: u64,
    /// An IDR: a decoder (a client joining late) can start here.
    pub key: bool,
    /// Stream time, milliseconds (strictly increasing).
    pub timestamp_ms: i64,
    /// Picture width, pixels.
    pub width: u32,
    /// Picture height, pixels.
    pub height: u32,
    /// For an HDR map: the luminance range to unpack it with.
    pub hdr: Option<cloudlight_render::video::HdrRange>,
    /// Scene time of the indirect light the picture shows, when its producer said
    /// ([`FrameMsg::Sdr::light_s`]); a light map is its own light (the stamp).
    pub light_s: Option<f64>,
    /// A light map that stays valid until superseded ([`FrameMsg::Hdr::steady`]).
    pub steady: bool,
    /// Annex-B NAL units.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// The voxel technique's edges inside the GI node (CloudLight §4.1).
pub mod voxel {
    use std::sync::Arc;

    pub use cloudlight_render::voxel::VoxelDelta;
    use cloudlight_render::voxel::{Octree, VoxelRadiance};
    use cloudlight_scenes::glam::Vec3;
    use serde::{Deserialize, Serialize};

    /// `light_injector` → `octree_filter`: the leaves' light of one update. The octree
    /// travels with it (shared in process; on a cut edge its bytes are what cutting the GI
    /// node there costs).
    #[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
    pub struct InjectedMsg {
        /// Update number.
        pub update: u64,
        /// The octree lit.
        pub octree: Arc<Octree>,
        /// Per leaf, its anisotropic radiance and opacity.
        pub leaves: Vec<VoxelRadiance>,
    }

    /// `octree_filter` → `cone_tracer`: every level's voxels of one update.
    #[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
    pub struct FilteredMsg {
        /// Update number.
        pub update: u64,
        /// The octree lit.
        pub octree: Arc<Octree>,
        /// Root first, per voxel.
        pub levels: Vec<Vec<VoxelRadiance>>,
    }

    /// `cone_tracer` → `light_injector`: the gathered irradiance on the leaves' two sides,
    /// reflected by the next injection (one more bounce per update).
    #[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
    pub struct BounceMsg {
        /// Update it was gathered in.
        pub update: u64,
        /// Checksum of the octree's structure it belongs to.
        pub structure: u32,
        /// Per leaf.
        pub leaves: Vec<[Vec3; 2]>,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use cloudlight_runtime::{MessageType, Stamped, codec};
    use proptest::prelude::*;

    /// Every edge message type, encoded and decoded through the runtime's codec.
    fn round_trip<T: cloudlight_runtime::Message + Clone + PartialEq + std::fmt::Debug>(body: T) {
        let msg = Stamped {
            scene_time_s: 3.5,
            produced_unix_ns: 1_700_000_000_000_000_000,
            seq: 12,
            body,
        };
        let bytes = codec::encode(&msg).unwrap();
        assert_eq!(bytes.len(), codec::encoded_len(&msg).unwrap());
        let back: Stamped<T> = codec::decode(&bytes).unwrap();
        assert_eq!(back, msg);
        // The same through the type-erased descriptor used by cut edges.
        let ty = MessageType::of::<T>();
        let any: std::sync::Arc<dyn std::any::Any + Send + Sync> = std::sync::Arc::new(msg.clone());
        let erased = ty.decode(&ty.encode(&any).unwrap()).unwrap();
        assert_eq!(erased.downcast_ref::<Stamped<T>>().unwrap(), &msg);
    }

    #[test]
    fn every_edge_message_type_round_trips() {
        round_trip(ProbeMsg::new(7, 3, 1000));
        round_trip(ProbeMsg::new(0, 0, 0));
        round_trip(FrameMsg::Sdr {
            width: 2,
            height: 2,
            rgb: vec![9; 12],
            light_s: Some(3.25),
        });
        let map = HdrMap::new(
            2,
            2,
            &[cloudlight_scenes::glam::Vec3::new(1.0, 2.0, 3.0); 4],
            &[true, false, true, true],
        )
        .unwrap();
        // 6 bytes a texel and one coverage byte, beside a few bytes of framing.
        let len = codec::encoded_len(&FrameMsg::Hdr {
            map: map.clone(),
            steady: true,
        })
        .unwrap();
        assert!(len <= 4 * 6 + 1 + 24, "{len} bytes for a 2×2 map");
        round_trip(FrameMsg::Hdr { map, steady: false });
        round_trip(VideoMsg {
            index: 4,
            key: true,
            timestamp_ms: 133,
            width: 640,
            height: 360,
            hdr: Some(cloudlight_render::video::HdrRange {
                log2_min: -3.0,
                log2_max: 5.0,
            }),
            light_s: None,
            steady: true,
            data: vec![0, 0, 0, 1, 0x65, 7],
        });
    }

    #[test]
    fn voxel_edge_messages_round_trip() {
        use cloudlight_render::voxel::{
            DeltaEncoder, Gathered, VoxelRadiance, VoxelSettings, Voxelizer, transfer,
        };
        use cloudlight_scenes::glam::Vec3;
        let scene = cloudlight_scenes::builtin("cornell").unwrap();
        let settings = VoxelSettings {
            max_depth: 2,
            ..Default::default()
        };
        let octree = std::sync::Arc::new(Voxelizer::new(&scene, &settings).octree_at(&scene, 0.0));
        let n = octree.leaves().len();
        let leaf = VoxelRadiance {
            radiance: [Vec3::new(1.0, 2.0, 3.0); 6],
            opacity: [0.5; 6],
        };
        round_trip(voxel::InjectedMsg {
            update: 3,
            octree: octree.clone(),
            leaves: vec![leaf; n],
        });
        round_trip(voxel::FilteredMsg {
            update: 3,
            octree: octree.clone(),
            levels: octree.levels.iter().map(|l| vec![leaf; l.len()]).collect(),
        });
        round_trip(voxel::BounceMsg {
            update: 3,
            structure: transfer::structure_of(&octree),
            leaves: vec![[Vec3::ONE, Vec3::ZERO]; n],
        });
        let gathered = Gathered {
            levels: octree
                .levels
                .iter()
                .map(|l| vec![[Vec3::splat(0.25), Vec3::ONE]; l.len()])
                .collect(),
            ..Default::default()
        };
        let update = DeltaEncoder::new(Default::default()).encode(&octree, &gathered, 1.5);
        for delta in update.deltas {
            // The payload costs about its bytes, beside a small header.
            let len = codec::encoded_len(&delta).unwrap() as u64;
            assert!(
                len <= delta.wire_bytes() + 16,
                "{len} bytes for {}",
                delta.wire_bytes()
            );
            round_trip(delta);
        }
    }

    #[test]
    fn probe_payload_costs_one_byte_per_byte() {
        let m = Stamped {
            scene_time_s: 0.0,
            produced_unix_ns: 0,
            seq: 0,
            body: ProbeMsg::new(1, 1, 10_000),
        };
        let len = codec::encoded_len(&m).unwrap();
        assert!(len < 10_000 + 32, "{len} bytes for a 10 kB payload");
    }

    proptest! {
        #[test]
        fn probe_round_trips(seed in any::<u64>(), index in any::<u64>(), len in 0usize..4096) {
            let m = ProbeMsg::new(seed, index, len);
            prop_assert!(m.is_intact(seed));
            round_trip(m);
        }

        #[test]
        fn corrupted_probe_is_detected(seed in any::<u64>(), len in 1usize..512, at in any::<prop::sample::Index>()) {
            let mut m = ProbeMsg::new(seed, 5, len);
            let k = at.index(len);
            m.payload[k] ^= 1;
            prop_assert!(!m.is_intact(seed));
        }
    }
}

/// What the photon batcher sends each client: packed batches as they complete, and after
/// each iteration a manifest of the complete set (see `cloudlight_render::photon::store`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum PhotonMsg {
    /// One light's batch for one slot.
    Batch(cloudlight_render::photon::PackedBatch),
    /// The generations and batch counts of every light as of a scene time.
    Manifest(cloudlight_render::photon::Manifest),
}
