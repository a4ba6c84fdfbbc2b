//! Sending gathered voxel irradiance from the GI node to frame renderers (CloudLight §4.1):
//! "storing the difference from the parent level at each octree node … equivalent to a 3D
//! Haar transform. Because the deltas are lower-magnitude than the values, we can reduce
//! precision … we need only transfer data that changed … we update the final frame GPU's
//! data structures in breadth-first order from the octree root."
//!
//! - **Coefficients.** Each voxel's value (irradiance on its two sides, three channels) is
//!   sent as its difference from its parent's (the root: from zero), taken between the
//!   floats' bit patterns read as ordered integers (as lossless float coders do: FPC,
//!   Burtscher & Ratanaworabhan 2009). Integer differences add back exactly, so at full
//!   precision the receiver holds the sender's floats bit for bit, and no error accumulates
//!   down the levels; the ordered integers are nearly logarithmic, so a voxel as bright
//!   relative to its parent as before keeps its coefficient when the light dims or grows.
//! - **Reduced precision.** Values are rounded to `mantissa_bits` bits of mantissa before
//!   the differences, so each received value is within 2^−(mantissa_bits + 1) of the sent
//!   one, relative, and the coefficients lose their low zero bits.
//! - **Only what changed.** The sender keeps the coefficients the receivers hold; a voxel is
//!   sent only where one of its six changed (a key update: where one is not zero, so the
//!   voxels below the gathering ones, which take their parent's value, are never sent).
//!   Unchanged levels are a header.
//! - **Breadth-first.** One [`VoxelDelta`] per level, root first: after level ℓ arrives, the
//!   receiver holds the update's values down to ℓ and can render coarse light before the
//!   fine levels arrive ([`DeltaDecoder::complete_level`]).
//! - **Key updates.** Every `key_every` updates (and the first) every voxel is sent. A
//!   receiver that missed a delta (or joined late) ignores deltas until the next key update,
//!   and counts the gap.
//!
//! The receiver needs the octree the update was gathered on (it voxelizes the same scene at
//! the update's scene time); a checksum of its structure travels with each delta. Garbage
//! (a wrong checksum, lengths, structure or value) is an error and changes nothing.

use glam::Vec3;
use serde::{Deserialize, Serialize};

use super::cone::Gathered;
use super::octree::Octree;

/// Transfer settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TransferSettings {
    /// Mantissa bits kept (23: exact f32).
    pub mantissa_bits: u32,
    /// Every this many updates, every voxel is sent (0: only the first).
    pub key_every: u64,
}

impl Default for TransferSettings {
    fn default() -> Self {
        TransferSettings {
            mantissa_bits: 8,
            key_every: 30,
        }
    }
}

/// The mantissa bits of an f32.
pub const FULL_PRECISION: u32 = 23;

/// A voxel's value as ordered integers: two sides × three channels.
type Six = [[i64; 3]; 2];

/// One level of one update, as sent.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct VoxelDelta {
    /// Update number (increases by one per update).
    pub update: u64,
    /// Scene time the irradiance was gathered for, seconds.
    pub scene_time_s: f64,
    /// Whether the update sends every voxel (receivers start over from it).
    pub key: bool,
    /// Checksum of the octree's structure (every level's codes).
    pub structure: u32,
    /// This delta's level (0: the root) and the octree's levels.
    pub level: u32,
    /// Levels of the octree (depth + 1).
    pub levels: u32,
    /// Voxels at this level.
    pub voxels: u32,
    /// Mantissa bits of the values.
    pub mantissa_bits: u8,
    /// Which voxels follow: a bitmask over the level's voxels, or (when `sparse`) the gaps
    /// between their indices as varints.
    pub sparse: bool,
    /// The changed voxels, see `sparse`.
    #[serde(with = "serde_bytes")]
    pub changed: Vec<u8>,
    /// Per changed voxel, six zigzag varints: its coefficients (ordered-integer differences
    /// from the parent, shifted right by the dropped mantissa bits).
    #[serde(with = "serde_bytes")]
    pub coefficients: Vec<u8>,
    /// CRC-32 of everything above.
    pub checksum: u32,
}

/// Why a delta was not applied.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum DeltaError {
    /// The checksum does not match.
    #[error("voxel delta checksum mismatch (corrupt or forged)")]
    Checksum,
    /// The lengths, level or values do not fit the delta's header.
    #[error("malformed voxel delta: {0}")]
    Malformed(&'static str),
    /// The receiver's octree is not the one the update was gathered on.
    #[error("voxel delta for another octree structure ({got:#010x}, have {have:#010x})")]
    Structure {
        /// The delta's.
        got: u32,
        /// The receiver's.
        have: u32,
    },
    /// A delta was missed (or the receiver joined late): deltas are ignored until the next
    /// key update.
    #[error(
        "voxel delta out of sequence (update {update} level {level}); waiting for a key update"
    )]
    Gap {
        /// The delta's update.
        update: u64,
        /// The delta's level.
        level: u32,
    },
}

/// A float as an ordered integer: the order of the values, and differences that add back
/// exactly.
fn to_ord(x: f32) -> i64 {
    let bits = x.to_bits();
    if bits & 0x8000_0000 != 0 {
        -i64::from(bits & 0x7fff_ffff)
    } else {
        i64::from(bits)
    }
}

/// The float of an ordered integer, if it is a finite one.
fn from_ord(o: i64) -> Option<f32> {
    if o.unsigned_abs() > u64::from(f32::MAX.to_bits()) {
        return None;
    }
    Some(if o >= 0 {
        f32::from_bits(o as u32)
    } else {
        f32::from_bits((-o) as u32 | 0x8000_0000)
    })
}

/// `x` rounded to `bits` bits of mantissa (non-finite values become 0).
fn quantize(x: f32, bits: u32) -> f32 {
    if !x.is_finite() {
        return 0.0;
    }
    if bits >= FULL_PRECISION {
        return x;
    }
    let drop = FULL_PRECISION - bits;
    let b = x.to_bits();
    let rounded = (b + (1 << (drop - 1))) & !((1u32 << drop) - 1);
    let r = f32::from_bits(rounded);
    if r.is_finite() {
        r
    } else {
        f32::MAX.copysign(x)
    }
}

fn six_of(v: [Vec3; 2], bits: u32) -> Six {
    v.map(|side| side.to_array().map(|x| to_ord(quantize(x, bits))))
}

fn value_of(o: &Six) -> Option<[Vec3; 2]> {
    let side = |s: &[i64; 3]| Some(Vec3::new(from_ord(s[0])?, from_ord(s[1])?, from_ord(s[2])?));
    Some([side(&o[0])?, side(&o[1])?])
}

/// Applies `f` to each of the six pairs of `a` and `b`.
fn zip6(a: &Six, b: &Six, f: impl Fn(i64, i64) -> i64) -> Six {
    std::array::from_fn(|s| std::array::from_fn(|k| f(a[s][k], b[s][k])))
}

/// A checksum of the octree's structure: every level's codes.
pub fn structure_of(octree: &Octree) -> u32 {
    let mut h = crc32fast::Hasher::new();
    for level in &octree.levels {
        h.update(&(level.len() as u64).to_le_bytes());
        for code in &level.codes {
            h.update(&code.to_le_bytes());
        }
    }
    h.finalize()
}

fn put_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

fn get_varint(bytes: &[u8], at: &mut usize) -> Option<u64> {
    let mut v = 0u64;
    for shift in (0..64).step_by(7) {
        let b = *bytes.get(*at)?;
        *at += 1;
        v |= u64::from(b & 0x7f) << shift;
        if b & 0x80 == 0 {
            return Some(v);
        }
    }
    None
}

fn zigzag(v: i64) -> u64 {
    ((v << 1) ^ (v >> 63)) as u64
}

fn unzigzag(v: u64) -> i64 {
    (v >> 1) as i64 ^ -((v & 1) as i64)
}

impl VoxelDelta {
    fn compute_checksum(&self) -> u32 {
        let mut h = crc32fast::Hasher::new();
        h.update(&self.update.to_le_bytes());
        h.update(&self.scene_time_s.to_le_bytes());
        h.update(&[
            u8::from(self.key),
            self.mantissa_bits,
            u8::from(self.sparse),
        ]);
        for v in [self.structure, self.level, self.levels, self.voxels] {
            h.update(&v.to_le_bytes());
        }
        h.update(&(self.changed.len() as u64).to_le_bytes());
        h.update(&self.changed);
        h.update(&self.coefficients);
        h.finalize()
    }

    /// Bytes this delta takes on the wire (its payload and a fixed header).
    pub fn wire_bytes(&self) -> u64 {
        (self.changed.len() + self.coefficients.len()) as u64 + 48
    }

    /// The indices of the changed voxels.
    fn changed_indices(&self) -> Result<Vec<usize>, DeltaError> {
        let n = self.voxels as usize;
        if self.sparse {
            let mut out = Vec::new();
            let (mut at, mut next) = (0, 0usize);
            while at < self.changed.len() {
                let gap = get_varint(&self.changed, &mut at)
                    .ok_or(DeltaError::Malformed("truncated index"))?;
                let i = next
                    .checked_add(usize::try_from(gap).map_err(|_| DeltaError::Malformed("index"))?)
                    .filter(|&i| i < n)
                    .ok_or(DeltaError::Malformed("index beyond the level"))?;
                out.push(i);
                next = i + 1;
            }
            Ok(out)
        } else {
            if self.changed.len() != n.div_ceil(8) {
                return Err(DeltaError::Malformed("mask length"));
            }
            Ok((0..n)
                .filter(|&i| self.changed[i / 8] & (1 << (i % 8)) != 0)
                .collect())
        }
    }
}

/// `old` (aligned with `old_codes`) carried over to `new_codes`: values of codes that
/// remain, the default for new ones.
fn remap<T: Copy + Default>(old_codes: &[u64], old: &[T], new_codes: &[u64]) -> Vec<T> {
    let mut out = vec![T::default(); new_codes.len()];
    let mut j = 0;
    for (i, code) in new_codes.iter().enumerate() {
        while j < old_codes.len() && old_codes[j] < *code {
            j += 1;
        }
        if j < old_codes.len() && old_codes[j] == *code && j < old.len() {
            out[i] = old[j];
        }
    }
    out
}

/// Coefficients of every level, kept by both ends, and the structure they belong to.
#[derive(Clone, Debug, Default)]
struct Mirror {
    structure: u32,
    codes: Vec<Vec<u64>>,
    coefficients: Vec<Vec<Six>>,
}

impl Mirror {
    /// Whether the mirror already follows `structure`.
    fn follows(&self, octree: &Octree, structure: u32) -> bool {
        structure == self.structure && self.codes.len() == octree.levels.len()
    }

    /// Follows the octree's structure: voxels that remain keep their coefficients (found
    /// by code), new ones start at zero.
    fn follow(&mut self, octree: &Octree, structure: u32) {
        if self.follows(octree, structure) {
            return;
        }
        let empty = Vec::new();
        self.coefficients = octree
            .levels
            .iter()
            .enumerate()
            .map(|(l, level)| {
                let old_codes = self.codes.get(l).unwrap_or(&empty);
                let old = self.coefficients.get(l).map_or(&[][..], |c| c.as_slice());
                remap(old_codes, old, &level.codes)
            })
            .collect();
        self.codes = octree.levels.iter().map(|l| l.codes.clone()).collect();
        self.structure = structure;
    }

    fn reset(&mut self) {
        for level in &mut self.coefficients {
            level.fill([[0; 3]; 2]);
        }
    }
}

/// The sending end: turns each gather into the deltas of one update.
#[derive(Clone, Debug, Default)]
pub struct DeltaEncoder {
    settings: TransferSettings,
    mirror: Mirror,
    update: u64,
}

/// What one update sent.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct EncodedUpdate {
    /// One delta per level, root first (none when nothing changed and it is no key update).
    pub deltas: Vec<VoxelDelta>,
    /// Voxels sent.
    pub voxels_sent: u64,
    /// Voxels in the octree.
    pub voxels: u64,
    /// Bytes the deltas take on the wire.
    pub bytes: u64,
    /// Bytes every voxel's value would take raw (six f32).
    pub raw_bytes: u64,
}

impl DeltaEncoder {
    /// An encoder with no update sent.
    pub fn new(settings: TransferSettings) -> DeltaEncoder {
        DeltaEncoder {
            settings,
            ..Default::default()
        }
    }

    /// The deltas of `gathered` (on `octree`, for scene time `scene_time_s`).
    pub fn encode(
        &mut self,
        octree: &Octree,
        gathered: &Gathered,
        scene_time_s: f64,
    ) -> EncodedUpdate {
        let bits = self.settings.mantissa_bits.min(FULL_PRECISION);
        let drop = FULL_PRECISION - bits;
        let structure = structure_of(octree);
        self.mirror.follow(octree, structure);
        let update = self.update;
        let key = update == 0
            || (self.settings.key_every > 0 && update.is_multiple_of(self.settings.key_every));
        if key {
            self.mirror.reset();
        }
        let levels = octree.levels.len();
        let mut values: Vec<Vec<Six>> = Vec::with_capacity(levels);
        let mut deltas = Vec::with_capacity(levels);
        let mut voxels_sent = 0u64;
        for (l, level) in octree.levels.iter().enumerate() {
            let here: Vec<Six> = (0..level.len())
                .map(|i| {
                    let v = gathered
                        .levels
                        .get(l)
                        .and_then(|g| g.get(i))
                        .copied()
                        .unwrap_or_default();
                    six_of(v, bits)
                })
                .collect();
            // Each voxel's parent value, seen from it.
            let predicted: Vec<Six> = if l == 0 {
                vec![[[0; 3]; 2]; level.len()]
            } else {
                octree
                    .parent_links(l)
                    .iter()
                    .map(|link| link.onto(values[l - 1][link.parent as usize]))
                    .collect()
            };
            let mirror = &mut self.mirror.coefficients[l];
            let mut changed = Vec::new();
            let mut coefficients = Vec::new();
            for i in 0..level.len() {
                let c = zip6(&here[i], &predicted[i], |v, p| (v - p) >> drop);
                if c != mirror[i] {
                    changed.push(i);
                    for x in c.as_flattened() {
                        put_varint(&mut coefficients, zigzag(*x));
                    }
                    mirror[i] = c;
                }
            }
            voxels_sent += changed.len() as u64;
            values.push(here);
            let n = level.len();
            let mut mask = vec![0u8; n.div_ceil(8)];
            let mut gaps = Vec::new();
            let mut next = 0;
            for &i in &changed {
                mask[i / 8] |= 1 << (i % 8);
                put_varint(&mut gaps, (i - next) as u64);
                next = i + 1;
            }
            let sparse = gaps.len() < mask.len();
            let mut delta = VoxelDelta {
                update,
                scene_time_s,
                key,
                structure,
                level: l as u32,
                levels: levels as u32,
                voxels: n as u32,
                mantissa_bits: bits as u8,
                sparse,
                changed: if sparse { gaps } else { mask },
                coefficients,
                checksum: 0,
            };
            delta.checksum = delta.compute_checksum();
            deltas.push(delta);
        }
        if voxels_sent == 0 && !key {
            deltas.clear(); // the receivers hold this already: no update
        } else {
            self.update += 1;
        }
        let voxels: u64 = octree.levels.iter().map(|l| l.len() as u64).sum();
        EncodedUpdate {
            bytes: deltas.iter().map(VoxelDelta::wire_bytes).sum(),
            deltas,
            voxels_sent,
            voxels,
            raw_bytes: voxels * 24,
        }
    }
}

/// The receiving end: applies deltas, level by level, and holds the values.
#[derive(Clone, Debug, Default)]
pub struct DeltaDecoder {
    mirror: Mirror,
    /// Per level, per voxel, the values as ordered integers.
    ords: Vec<Vec<Six>>,
    /// Per level, per voxel, the irradiance on its two sides.
    values: Vec<Vec<[Vec3; 2]>>,
    /// The update being received and the next level expected of it.
    update: Option<u64>,
    next_level: u32,
    scene_time_s: f64,
    /// Whether a key update has started the stream (or restarted it after a gap).
    synced: bool,
}

impl DeltaDecoder {
    /// A receiver that has seen nothing.
    pub fn new() -> DeltaDecoder {
        DeltaDecoder::default()
    }

    /// Applies one delta, gathered on `octree` (the receiver's octree at the delta's scene
    /// time, the same for every level of an update). Deltas of an update come root first; after a missed one, deltas are refused
    /// until the next key update.
    pub fn apply(&mut self, octree: &Octree, delta: &VoxelDelta) -> Result<(), DeltaError> {
        if delta.compute_checksum() != delta.checksum {
            return Err(DeltaError::Checksum);
        }
        let levels = octree.levels.len();
        if delta.levels as usize != levels
            || delta.level as usize >= levels
            || u32::from(delta.mantissa_bits) > FULL_PRECISION
        {
            return Err(DeltaError::Malformed("levels"));
        }
        let level = &octree.levels[delta.level as usize];
        if delta.voxels as usize != level.len() {
            return Err(DeltaError::Malformed("voxels per level"));
        }
        // In sequence: the next level of the current update, or level 0 of the next one
        // once the current one is whole; a key update's root starts over.
        let starts_over = delta.key && delta.level == 0;
        let follows = self.synced
            && match self.update {
                Some(u) if u == delta.update => delta.level == self.next_level,
                Some(u) => delta.update == u + 1 && delta.level == 0 && self.complete(),
                None => false,
            };
        if !(starts_over || follows) {
            let repeated = self.update == Some(delta.update) && delta.level < self.next_level;
            if !repeated {
                self.synced = false;
            }
            return Err(DeltaError::Gap {
                update: delta.update,
                level: delta.level,
            });
        }
        // The structure is checked once per update, at its root (a checksum of every
        // level); the later levels of the update must name the same one.
        let structure = if delta.level == 0 {
            structure_of(octree)
        } else {
            self.mirror.structure
        };
        if delta.structure != structure {
            return Err(DeltaError::Structure {
                got: delta.structure,
                have: structure,
            });
        }
        // Decode before changing anything.
        let indices = delta.changed_indices()?;
        let drop = FULL_PRECISION - u32::from(delta.mantissa_bits);
        let mut coefficients = Vec::with_capacity(indices.len());
        let mut at = 0;
        for _ in &indices {
            let mut c: Six = [[0; 3]; 2];
            for x in c.as_flattened_mut() {
                let v = get_varint(&delta.coefficients, &mut at)
                    .ok_or(DeltaError::Malformed("truncated coefficients"))?;
                *x = unzigzag(v)
                    .checked_mul(1 << drop)
                    .filter(|x| x.unsigned_abs() <= 2 * u64::from(f32::MAX.to_bits()))
                    .ok_or(DeltaError::Malformed("coefficient out of range"))?;
            }
            coefficients.push(c);
        }
        if at != delta.coefficients.len() {
            return Err(DeltaError::Malformed("trailing coefficients"));
        }
        // The values this level would take, checked before anything is kept.
        let l = delta.level as usize;
        if delta.level == 0 {
            if !self.mirror.follows(octree, structure) {
                // Older values stay where their voxels remain, until their level arrives.
                let codes = &self.mirror.codes;
                let empty = Vec::new();
                for (l, level) in octree.levels.iter().enumerate() {
                    let old_codes = codes.get(l).unwrap_or(&empty);
                    let ords = self.ords.get(l).map_or(&[][..], |v| v.as_slice());
                    let values = self.values.get(l).map_or(&[][..], |v| v.as_slice());
                    let (o, v) = (
                        remap(old_codes, ords, &level.codes),
                        remap(old_codes, values, &level.codes),
                    );
                    if l < self.ords.len() {
                        (self.ords[l], self.values[l]) = (o, v);
                    } else {
                        self.ords.push(o);
                        self.values.push(v);
                    }
                }
                self.ords.truncate(levels);
                self.values.truncate(levels);
                self.mirror.follow(octree, structure);
            }
            if delta.key {
                self.mirror.reset();
            }
        }
        let mut mirror_level = self.mirror.coefficients[l].clone();
        for (&i, c) in indices.iter().zip(&coefficients) {
            mirror_level[i] = *c;
        }
        let ords: Vec<Six> = if l == 0 {
            mirror_level.clone()
        } else {
            octree
                .parent_links(l)
                .iter()
                .zip(&mirror_level)
                .map(|(link, c)| {
                    zip6(
                        &link.onto(self.ords[l - 1][link.parent as usize]),
                        c,
                        |p, c| p + c,
                    )
                })
                .collect()
        };
        let values: Vec<[Vec3; 2]> = ords
            .iter()
            .map(value_of)
            .collect::<Option<_>>()
            .ok_or(DeltaError::Malformed("value beyond f32"))?;
        self.mirror.coefficients[l] = mirror_level;
        self.ords[l] = ords;
        self.values[l] = values;
        self.update = Some(delta.update);
        self.next_level = delta.level + 1;
        self.scene_time_s = delta.scene_time_s;
        self.synced = true;
        Ok(())
    }

    /// The deepest level that holds the latest update's values (None before any).
    pub fn complete_level(&self) -> Option<u32> {
        self.update.map(|_| self.next_level - 1)
    }

    /// Whether the latest update has arrived whole.
    pub fn complete(&self) -> bool {
        self.update.is_some() && self.next_level as usize == self.values.len()
    }

    /// The update and scene time of the latest values.
    pub fn latest(&self) -> Option<(u64, f64)> {
        self.update.map(|u| (u, self.scene_time_s))
    }

    /// Per level (root first), per voxel, the irradiance on its two sides. Levels below
    /// [`Self::complete_level`] hold an older update's values.
    pub fn levels(&self) -> &[Vec<[Vec3; 2]>] {
        &self.values
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::voxel::{
        ConeSettings, InjectSettings, VoxelSettings, Voxelizer, filter, gather, inject,
    };
    use crate::{BvhKind, SceneBvh};

    /// The Cornell box's octree at `depth` and its gathered irradiance.
    fn cornell(depth: u32) -> (Octree, Gathered) {
        let scene = cloudlight_scenes::builtin("cornell").unwrap();
        let settings = VoxelSettings {
            max_depth: depth,
            ..Default::default()
        };
        let octree = Voxelizer::new(&scene, &settings).octree_at(&scene, 0.0);
        let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
        let injection = inject(&octree, &scene, &bvh, 0.0, None, &InjectSettings::default());
        let levels = filter(&octree, injection.leaves);
        let gathered = gather(&octree, &levels, &ConeSettings::default());
        (octree, gathered)
    }

    /// Each voxel's value times its own factor in [0.5, 1.5]: every coefficient changes.
    fn perturbed(g: &Gathered, seed: u32) -> Gathered {
        let mut k = seed;
        Gathered {
            levels: g
                .levels
                .iter()
                .map(|l| {
                    l.iter()
                        .map(|v| {
                            k = k.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                            let f = 0.5 + (k >> 8) as f32 / (1u32 << 24) as f32;
                            [v[0] * f, v[1] * f]
                        })
                        .collect()
                })
                .collect(),
            ..g.clone()
        }
    }

    fn decode_all(decoder: &mut DeltaDecoder, octree: &Octree, update: &EncodedUpdate) {
        for d in &update.deltas {
            decoder.apply(octree, d).unwrap();
        }
    }

    fn scaled(g: &Gathered, k: f32) -> Gathered {
        Gathered {
            levels: g
                .levels
                .iter()
                .map(|l| l.iter().map(|v| [v[0] * k, v[1] * k]).collect())
                .collect(),
            ..g.clone()
        }
    }

    #[test]
    fn full_precision_round_trips_bit_for_bit_and_reduced_precision_is_bounded() {
        let (octree, g) = cornell(5);
        let mut enc = DeltaEncoder::new(TransferSettings {
            mantissa_bits: FULL_PRECISION,
            key_every: 0,
        });
        let mut dec = DeltaDecoder::new();
        let update = enc.encode(&octree, &g, 0.5);
        assert_eq!(update.deltas.len(), octree.levels.len());
        decode_all(&mut dec, &octree, &update);
        assert!(dec.complete());
        assert_eq!(dec.latest(), Some((0, 0.5)));
        for (got, want) in dec.levels().iter().zip(&g.levels) {
            for (a, b) in got.iter().zip(want) {
                for side in 0..2 {
                    assert_eq!(
                        a[side].to_array().map(f32::to_bits),
                        b[side].to_array().map(f32::to_bits)
                    );
                }
            }
        }
        for bits in [4u32, 8, 12] {
            let mut enc = DeltaEncoder::new(TransferSettings {
                mantissa_bits: bits,
                key_every: 0,
            });
            let mut dec = DeltaDecoder::new();
            let update = enc.encode(&octree, &g, 0.0);
            decode_all(&mut dec, &octree, &update);
            let bound = 2f32.powi(-(bits as i32 + 1)) * 1.000_001;
            for (got, want) in dec.levels().iter().zip(&g.levels) {
                for (a, b) in got.iter().zip(want) {
                    for side in 0..2 {
                        let err = (a[side] - b[side]).abs();
                        assert!(
                            err.cmple(b[side].abs() * bound).all(),
                            "{bits} bits: {a:?} vs {b:?}"
                        );
                    }
                }
            }
            eprintln!(
                "{bits} mantissa bits: {} B for {} voxels, raw {} B ({:.3} of raw)",
                update.bytes,
                update.voxels,
                update.raw_bytes,
                update.bytes as f64 / update.raw_bytes as f64
            );
        }
    }

    #[test]
    fn only_what_changed_is_sent_and_progressive_decoding_converges() {
        let (octree, g) = cornell(5);
        let mut enc = DeltaEncoder::new(TransferSettings {
            mantissa_bits: 8,
            key_every: 0,
        });
        let mut dec = DeltaDecoder::new();
        let first = enc.encode(&octree, &g, 0.0);
        let nonzero = first.voxels_sent;
        assert!(nonzero > 0 && nonzero < first.voxels);
        decode_all(&mut dec, &octree, &first);
        // Nothing changed: nothing sent, and no update number taken.
        let same = enc.encode(&octree, &g, 0.1);
        assert!(same.deltas.is_empty() && same.bytes == 0);
        // One leaf changes: one voxel sent, the leaf's level only.
        let mut one = g.clone();
        let depth = octree.levels.len() - 1;
        one.levels[depth][7][0] *= 3.0;
        let update = enc.encode(&octree, &one, 0.2);
        assert_eq!(update.voxels_sent, 1);
        decode_all(&mut dec, &octree, &update);
        assert_eq!(dec.latest(), Some((1, 0.2)));
        // Twice the light everywhere: only the root's coefficients change (differences of
        // ordered floats are nearly logarithmic), and those of voxels that are dark or
        // have a dark parent.
        let update = enc.encode(&octree, &scaled(&g, 2.0), 0.25);
        eprintln!(
            "twice the light: {} of {nonzero} voxels sent",
            update.voxels_sent
        );
        assert!(update.voxels_sent < nonzero / 2);
        decode_all(&mut dec, &octree, &update);
        // Light that changes everywhere, sent level by level. Before each level arrives
        // the levels above it already hold the new light; the error of what a renderer
        // shows (each leaf taking its deepest complete ancestor) shrinks to zero.
        let brighter = perturbed(&g, 7);
        let update = enc.encode(&octree, &brighter, 0.3);
        assert!(update.voxels_sent > nonzero / 2);
        let mut reference = DeltaDecoder::new();
        let mut full = DeltaEncoder::new(TransferSettings {
            mantissa_bits: 8,
            key_every: 0,
        });
        decode_all(
            &mut reference,
            &octree,
            &full.encode(&octree, &brighter, 0.3),
        );
        let truth = reference.levels()[depth].clone();
        let mut errors = Vec::new();
        for d in &update.deltas {
            dec.apply(&octree, d).unwrap();
            let shown = crate::voxel::volume::values_at(
                &octree,
                dec.levels(),
                dec.complete_level().unwrap(),
                depth as u32,
            );
            let err: f32 = shown
                .iter()
                .zip(&truth)
                .map(|(a, b)| (a[0] - b[0]).length() + (a[1] - b[1]).length())
                .sum();
            errors.push(err);
        }
        eprintln!("progressive error by level: {errors:?}");
        assert!(
            errors.windows(2).all(|w| w[1] <= w[0] * 1.001),
            "{errors:?}"
        );
        assert_eq!(*errors.last().unwrap(), 0.0);
        assert!(errors[0] > 0.0);
    }

    #[test]
    fn a_fresh_receiver_shows_light_from_the_first_coarsest_delta() {
        // What the frame renderer shows (its volume, looked up on each leaf's surface) after
        // each delta of the first update: light everywhere there is light in the end, from
        // the root alone on, at every level within a factor of the whole update's.
        let (octree, g) = cornell(5);
        let level = octree.depth();
        let mut enc = DeltaEncoder::new(TransferSettings {
            mantissa_bits: 8,
            key_every: 0,
        });
        let update = enc.encode(&octree, &g, 0.0);
        let leaves = octree.leaves();
        let shown = |dec: &DeltaDecoder| -> Vec<f32> {
            let volume = crate::voxel::VoxelVolume::new(
                &octree,
                dec.levels(),
                dec.complete_level().unwrap(),
                level,
            );
            leaves
                .surfaces
                .iter()
                .map(|s| {
                    let n = s.side_normal();
                    (volume.irradiance(s.position, n) + volume.irradiance(s.position, -n))
                        .element_sum()
                })
                .collect()
        };
        let mut whole = DeltaDecoder::new();
        decode_all(&mut whole, &octree, &update);
        let truth = shown(&whole);
        let lit = truth.iter().filter(|&&e| e > 0.0).count();
        assert!(lit > leaves.len() / 2, "{lit} of {} lit", leaves.len());
        let total: f64 = truth.iter().map(|&e| f64::from(e)).sum();
        let mut dec = DeltaDecoder::new();
        for (k, d) in update.deltas.iter().enumerate() {
            dec.apply(&octree, d).unwrap();
            let now = shown(&dec);
            let dark = now
                .iter()
                .zip(&truth)
                .filter(|&(a, b)| *b > 0.0 && *a <= 0.0)
                .count();
            let ratio = now.iter().map(|&e| f64::from(e)).sum::<f64>() / total;
            eprintln!(
                "after delta {k}: {dark} of {lit} lit leaves dark, light {ratio:.3} of the whole"
            );
            assert_eq!(dark, 0, "after delta {k}");
            assert!((0.5..2.0).contains(&ratio), "after delta {k}: {ratio}");
        }
    }

    #[test]
    fn moving_geometry_changes_the_structure_and_receivers_follow_it() {
        // The Cornell box with its short block circling the floor.
        let mut scene = cloudlight_scenes::builtin("cornell").unwrap();
        let block = scene
            .objects
            .iter_mut()
            .find(|o| o.name == "short_block")
            .unwrap();
        block.motion = cloudlight_scenes::Motion::Orbit {
            center: glam::Vec3::ZERO,
            axis: glam::Vec3::Y,
            radius: 0.05,
            period_s: 4.0,
            phase: 0.0,
        };
        let settings = VoxelSettings {
            max_depth: 5,
            ..Default::default()
        };
        let voxelizer = Voxelizer::new(&scene, &settings);
        assert!(!voxelizer.moving_objects().is_empty());
        let mut enc = DeltaEncoder::new(TransferSettings {
            mantissa_bits: FULL_PRECISION,
            key_every: 0,
        });
        let mut dec = DeltaDecoder::new();
        let mut structures = Vec::new();
        for t in [0.0, 0.7, 1.9] {
            let octree = voxelizer.octree_at(&scene, t);
            structures.push(structure_of(&octree));
            let bvh = SceneBvh::at(&scene, t, BvhKind::default());
            let injection = inject(&octree, &scene, &bvh, t, None, &InjectSettings::default());
            let g = gather(
                &octree,
                &filter(&octree, injection.leaves),
                &ConeSettings::default(),
            );
            let update = enc.encode(&octree, &g, t);
            decode_all(&mut dec, &octree, &update);
            assert_eq!(dec.levels(), &g.levels[..], "t = {t}");
        }
        assert!(
            structures[0] != structures[1] && structures[1] != structures[2],
            "{structures:?}"
        );
    }

    #[test]
    fn garbage_and_gaps_are_refused_and_change_nothing() {
        let (octree, g) = cornell(4);
        let mut enc = DeltaEncoder::new(TransferSettings {
            mantissa_bits: 8,
            key_every: 3,
        });
        let mut dec = DeltaDecoder::new();
        let key = enc.encode(&octree, &g, 0.0);
        // A receiver that starts mid-update waits for a key update.
        assert!(matches!(
            dec.apply(&octree, &key.deltas[1]),
            Err(DeltaError::Gap { .. })
        ));
        decode_all(&mut dec, &octree, &key);
        let before = dec.levels().to_vec();
        let next = enc.encode(&octree, &perturbed(&g, 1), 0.1);
        let d = &next.deltas[0];
        let mut flipped = d.clone();
        flipped.coefficients[0] ^= 0x40;
        assert_eq!(dec.apply(&octree, &flipped), Err(DeltaError::Checksum));
        let forge = |mut x: VoxelDelta| {
            x.checksum = x.compute_checksum();
            x
        };
        let mut truncated = d.clone();
        truncated.coefficients.pop();
        assert!(matches!(
            dec.apply(&octree, &forge(truncated)),
            Err(DeltaError::Malformed(_))
        ));
        let mut wrong_level = d.clone();
        wrong_level.level = 99;
        assert!(matches!(
            dec.apply(&octree, &forge(wrong_level)),
            Err(DeltaError::Malformed(_))
        ));
        let mut other = d.clone();
        other.structure ^= 1;
        assert!(matches!(
            dec.apply(&octree, &forge(other)),
            Err(DeltaError::Structure { .. })
        ));
        let mut huge = d.clone();
        huge.coefficients = vec![0xff; 60];
        assert!(dec.apply(&octree, &forge(huge)).is_err());
        assert_eq!(dec.levels(), &before[..]);
        // Level 0 lost: level 1 is a gap, and so is everything until the key update.
        assert!(matches!(
            dec.apply(&octree, &next.deltas[1]),
            Err(DeltaError::Gap { .. })
        ));
        let after = enc.encode(&octree, &perturbed(&g, 2), 0.2);
        assert!(!after.deltas[0].key);
        assert!(matches!(
            dec.apply(&octree, &after.deltas[0]),
            Err(DeltaError::Gap { .. })
        ));
        let key = enc.encode(&octree, &perturbed(&g, 3), 0.3);
        assert!(key.deltas[0].key);
        decode_all(&mut dec, &octree, &key);
        assert!(dec.complete());
        // Any bytes: never a panic.
        for seed in 0..200u64 {
            let mut x = d.clone();
            let mut s = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
            for b in x.coefficients.iter_mut().chain(x.changed.iter_mut()) {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                *b = s as u8;
            }
            x.sparse = seed % 2 == 0;
            let _ = dec.apply(&octree, &forge(x));
        }
    }
}
