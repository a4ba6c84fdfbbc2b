//! The client's photons: the newest batch per (light, pass, slot), and how current they are.
//!
//! The batcher sends batches as they complete and, after each iteration, a [`Manifest`]:
//! the generation, batch count and refinement passes of every light as of a scene time. A
//! [`PhotonSet`] keeps the batches of each light's newest generation (ignoring older ones
//! that arrive late; a new generation drops that light's passes, and only that light's),
//! drops passes, slots and lights the manifest no longer lists, and knows the newest scene
//! time whose manifest it holds completely: the light it shows is *valid as of* that time,
//! so `now − valid_as_of` is the age of the indirect light on screen.
//!
//! **Progressive photon mapping**: while a light stands still the batcher sends one more
//! pass of fresh photons per iteration. [`PhotonSet::photons`] draws a light's complete
//! passes together, each photon's power divided by their number P and its radius scaled
//! by [`progressive_radius_scale`]`(P)`, so the light's estimate converges as passes come.
//!
//! **A moving light's window** ([`PhotonSet::with_window`]): a light that changes every
//! iteration never gets a second pass, so each frame shows one generation's noise and the
//! bias of its radius. With a window of W, the set keeps the light's last W − 1 complete
//! generations beside the newest and draws them together as passes (power / G, radius ×
//! [`progressive_radius_scale`]`(G)` for the G drawn): the same bytes on the wire, the
//! estimate of G passes, lagging the light by (G − 1)/2 iterations on average. A light
//! that a manifest lists at the generation the one before it listed stands still, and its
//! older generations go.

use std::collections::BTreeMap;
use std::sync::OnceLock;

use serde::{Deserialize, Serialize};

use super::{PackError, PackedBatch, Photon, progressive_radius_scale};

/// One light's entry in a manifest.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ManifestLight {
    /// Light id.
    pub light: u32,
    /// Generation of its current batch set.
    pub generation: u64,
    /// Batches in each pass.
    pub slots: u32,
    /// Refinement passes held by the batcher (1: the first only).
    #[serde(default = "one")]
    pub passes: u32,
}

fn one() -> u32 {
    1
}

/// The complete photon set as of one scene time.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// Batcher iteration (increasing).
    pub iteration: u64,
    /// Scene time the set is valid for, seconds.
    pub scene_time_s: f64,
    /// Every light that emits, with its current generation.
    pub lights: Vec<ManifestLight>,
}

/// What [`PhotonSet::insert`] did with a batch.
#[derive(Clone, Debug, PartialEq)]
pub enum Inserted {
    /// A slot that was empty.
    New,
    /// Replaced an older (or equal, re-sent) batch of the slot.
    Replaced,
    /// Older than what is held: ignored.
    Stale,
    /// Invalid: ignored.
    Rejected(PackError),
}

#[derive(Clone)]
struct Held {
    generation: u64,
    scene_time_s: f64,
    batch: PackedBatch,
    /// Decoded on first use (a client that does not draw never pays for decoding).
    photons: OnceLock<Vec<Photon>>,
}

impl Held {
    fn photons(&self) -> &[Photon] {
        self.photons.get_or_init(|| match self.batch.unpack() {
            Ok(p) => p,
            Err(e) => {
                // Checked when inserted; only a batch that decodes to non-finite values
                // gets here, and it is drawn as empty.
                tracing::warn!("a photon batch that passed its checks does not decode: {e}");
                Vec::new()
            }
        })
    }
}

/// Counters of a [`PhotonSet`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct SetStats {
    /// Batches accepted.
    pub accepted: u64,
    /// Batches that replaced a held one.
    pub replaced: u64,
    /// Batches ignored as older than what is held.
    pub stale: u64,
    /// Batches rejected as invalid.
    pub rejected: u64,
    /// Manifests applied.
    pub manifests: u64,
}

/// The client's set of photon batches.
#[derive(Default)]
pub struct PhotonSet {
    /// By (light, pass, slot).
    held: BTreeMap<(u32, u32, u32), Held>,
    /// Generations of each light drawn at most (0 and 1: the newest only).
    window: u32,
    /// Per light, its older complete generations' first-pass batches, newest first (at most
    /// `window − 1`).
    previous: BTreeMap<u32, std::collections::VecDeque<Vec<Held>>>,
    manifest: Option<Manifest>,
    valid_as_of: Option<f64>,
    stats: SetStats,
    version: u64,
}

impl PhotonSet {
    /// An empty set.
    pub fn new() -> Self {
        Self::default()
    }

    /// An empty set that draws each light's last `window` generations together while it
    /// has one pass (a moving light: see the module's documentation; 1: the newest only).
    pub fn with_window(window: u32) -> Self {
        PhotonSet {
            window,
            ..Self::default()
        }
    }

    /// Takes a batch: kept unless it is invalid (header, lengths, checksum) or older than
    /// the slot's. Its photons are decoded when first asked for.
    pub fn insert(&mut self, batch: &PackedBatch) -> Inserted {
        if let Err(e) = batch.validate() {
            self.stats.rejected += 1;
            return Inserted::Rejected(e);
        }
        let listed = self.manifest.as_ref().and_then(|m| {
            m.lights
                .iter()
                .find(|l| l.light == batch.header.light)
                .map(|l| l.generation)
        });
        let h = &batch.header;
        let light_gen = self
            .held
            .range((h.light, 0, 0)..=(h.light, u32::MAX, u32::MAX))
            .map(|(_, held)| held.generation)
            .max();
        if listed.is_some_and(|g| g > h.generation) || light_gen.is_some_and(|g| g > h.generation) {
            self.stats.stale += 1;
            return Inserted::Stale;
        }
        let key = (h.light, h.pass, h.slot);
        if self.window > 1 && light_gen.is_some_and(|g| g < h.generation) {
            self.keep_previous(h.light);
        }
        // A batch sent again unchanged (the batcher's `resend_s`, for clients that joined
        // late) changes nothing: the set keeps its version, so a client's still view keeps
        // accumulating.
        if self.held.get(&key).is_some_and(|held| held.batch == *batch) {
            self.stats.accepted += 1;
            self.stats.replaced += 1;
            return Inserted::Replaced;
        }
        let held_gen = self.held.get(&key).map(|h| h.generation);
        self.held.insert(
            key,
            Held {
                generation: h.generation,
                scene_time_s: h.scene_time_s,
                batch: batch.clone(),
                photons: OnceLock::new(),
            },
        );
        // The light's refinement passes of older generations go (its first pass is
        // replaced slot by slot, so a moving light never goes dark); its passes now have
        // `slots` batches: forget slots beyond them.
        self.held.retain(|&(l, p, s), held| {
            l != h.light || (s < h.slots && (p == 0 || held.generation == h.generation))
        });
        self.stats.accepted += 1;
        self.version += 1;
        self.refresh_validity();
        if held_gen.is_some() {
            self.stats.replaced += 1;
            Inserted::Replaced
        } else {
            Inserted::New
        }
    }

    /// Takes a manifest (older ones than the last are ignored): lights it does not list are
    /// dropped, and the set becomes valid as of its time once every listed batch is held.
    pub fn apply_manifest(&mut self, manifest: Manifest) {
        if self
            .manifest
            .as_ref()
            .is_some_and(|m| m.iteration > manifest.iteration)
        {
            return;
        }
        let before = self.held.len();
        self.held.retain(|&(l, p, s), _| {
            manifest
                .lights
                .iter()
                .any(|m| m.light == l && s < m.slots && p < m.passes.max(1))
        });
        if self.held.len() != before {
            self.version += 1;
        }
        // A light's older generations are drawn only while it keeps changing: one listed
        // at the generation the last manifest listed stands still (or is gone), and they go.
        let before = self.previous.len();
        let last = self.manifest.as_ref();
        self.previous.retain(|&l, _| {
            let now = manifest.lights.iter().find(|m| m.light == l);
            let then = last.and_then(|m| m.lights.iter().find(|m| m.light == l));
            now.is_some_and(|n| then.is_none_or(|t| t.generation != n.generation))
        });
        if self.previous.len() != before {
            self.version += 1;
        }
        self.manifest = Some(manifest);
        self.stats.manifests += 1;
        self.refresh_validity();
    }

    /// Before `light`'s first batch of a newer generation replaces any of its slots: its
    /// first pass, when complete and of one generation, joins its older generations.
    fn keep_previous(&mut self, light: u32) {
        let first: Vec<&Held> = self
            .held
            .range((light, 0, 0)..=(light, 0, u32::MAX))
            .map(|(_, h)| h)
            .collect();
        let complete = first.first().is_some_and(|h0| {
            first.len() as u32 == h0.batch.header.slots
                && first.iter().all(|h| h.generation == h0.generation)
        });
        if !complete {
            return;
        }
        let generation: Vec<Held> = first.into_iter().cloned().collect();
        let previous = self.previous.entry(light).or_default();
        previous.push_front(generation);
        previous.truncate(self.window.saturating_sub(1) as usize);
    }

    fn refresh_validity(&mut self) {
        let Some(m) = &self.manifest else {
            return;
        };
        let complete = m.lights.iter().all(|l| {
            (0..l.passes.max(1)).all(|p| {
                (0..l.slots).all(|s| {
                    self.held
                        .get(&(l.light, p, s))
                        .is_some_and(|h| h.generation >= l.generation)
                })
            })
        });
        if complete && self.valid_as_of.is_none_or(|t| t < m.scene_time_s) {
            self.valid_as_of = Some(m.scene_time_s);
        }
    }

    /// Scene time the held photons are complete and current for, if ever.
    pub fn valid_as_of(&self) -> Option<f64> {
        self.valid_as_of
    }

    /// The photons to draw (decoding batches not decoded yet): each light's first pass
    /// (whatever of it is held, as the newest batch per slot) and its refinement passes
    /// that are complete, up to the first that is not, with powers divided by the passes'
    /// number and radii scaled by [`progressive_radius_scale`].
    pub fn photons(&self) -> impl Iterator<Item = Photon> + '_ {
        self.drawn().flat_map(|(passes, held)| {
            let (power, radius) = (1.0 / passes as f32, progressive_radius_scale(passes));
            held.into_iter().flat_map(move |h| {
                h.photons().iter().map(move |p| Photon {
                    power: p.power * power,
                    radius: p.radius * radius,
                    ..*p
                })
            })
        })
    }

    /// Per light: its drawn passes and their batches (a one-pass light's window of
    /// generations counted as passes).
    fn drawn(&self) -> impl Iterator<Item = (u32, Vec<&Held>)> + '_ {
        let lights: std::collections::BTreeSet<u32> = self.held.keys().map(|k| k.0).collect();
        lights.into_iter().filter_map(|light| {
            let (passes, mut batches) = self.drawn_of(light)?;
            let older = self.previous.get(&light).filter(|_| passes == 1);
            let Some(older) = older else {
                return Some((passes, batches));
            };
            batches.extend(older.iter().flatten());
            Some((1 + older.len() as u32, batches))
        })
    }

    /// Generations drawn for `light` (its window; 0: nothing held).
    pub fn generations_of(&self, light: u32) -> u32 {
        match self.drawn_of(light) {
            Some((1, _)) => 1 + self.previous.get(&light).map_or(0, |p| p.len() as u32),
            Some(_) => 1,
            None => 0,
        }
    }

    /// `light`'s drawn passes (its first, then each complete one up to the first that is
    /// not) and their batches; `None` when nothing of it is held.
    fn drawn_of(&self, light: u32) -> Option<(u32, Vec<&Held>)> {
        let mut passes = Vec::new();
        for pass in 0.. {
            let batches: Vec<&Held> = self
                .held
                .range((light, pass, 0)..=(light, pass, u32::MAX))
                .map(|(_, h)| h)
                .collect();
            let slots = batches.first().map_or(0, |h| h.batch.header.slots);
            if batches.is_empty() || (pass > 0 && batches.len() as u32 != slots) {
                break;
            }
            passes.push(batches);
        }
        let count = passes.len() as u32;
        (count > 0).then(|| (count, passes.concat()))
    }

    /// Passes drawn for `light`: its first and its complete refinement passes (0: nothing
    /// held).
    pub fn passes_of(&self, light: u32) -> u32 {
        self.drawn_of(light).map_or(0, |(passes, _)| passes)
    }

    /// Photons held.
    pub fn photon_count(&self) -> usize {
        self.held.values().map(|h| h.batch.count as usize).sum()
    }

    /// Batches held.
    pub fn batch_count(&self) -> usize {
        self.held.len()
    }

    /// Packed bytes held (the memory footprint of the set on the wire format).
    pub fn packed_bytes(&self) -> usize {
        self.held.values().map(|h| h.batch.data.len()).sum()
    }

    /// Scene time of the oldest batch held.
    pub fn oldest_batch_time(&self) -> Option<f64> {
        self.held
            .values()
            .map(|h| h.scene_time_s)
            .min_by(f64::total_cmp)
    }

    /// Counters.
    pub fn stats(&self) -> SetStats {
        self.stats
    }

    /// Increases whenever the held photons change (to skip re-uploading them).
    pub fn version(&self) -> u64 {
        self.version
    }
}
