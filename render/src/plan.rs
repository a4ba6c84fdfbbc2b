//! `cloudlight plan SCENE`: what a scene is and what each technique would allocate for it
//! with its default settings — the project models only what a scene requires.
//!
//! The allocations are computed from the scene, not guessed: occupied voxels per octree
//! level come from the voxel technique's voxelization ([`crate::voxel`]); photon batches from each light's power; light-map texels from the
//! surface area. The defaults are calibrated on the paper's Cornell box figures (10k photons
//! in one batch, a 128² light map with 50 bases, a 9-level octree).

use cloudlight_scenes::Scene;
use glam::Vec3;

/// Technique settings the plan uses.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlanSettings {
    /// Photons per iteration, spread over the lights by power (the batcher's `photons`).
    pub photons: u64,
    /// Photons emitted per watt (summed over channels), instead of `photons` (the
    /// batcher's `photons_per_watt`).
    pub photons_per_watt: Option<f64>,
    /// Photons per batch.
    pub batch_size: u64,
    /// Octree levels; the leaf grid is 2^levels per axis over the scene's largest extent.
    pub octree_levels: u32,
    /// Light-map texels per square meter of surface.
    pub texels_per_m2: f64,
    /// Light-map texels per basis.
    pub texels_per_basis: f64,
}

impl Default for PlanSettings {
    fn default() -> Self {
        // The batcher's defaults (10k photons an iteration, however many watts the scene's
        // lights emit); Cornell box: 2.0 m² → 128² texels, 50 bases.
        PlanSettings {
            photons: crate::photon::DEFAULT_PHOTONS,
            photons_per_watt: None,
            batch_size: 10_000,
            octree_levels: 9,
            texels_per_m2: 8_200.0,
            texels_per_basis: 330.0,
        }
    }
}

/// A light's photon budget.
#[derive(Clone, Debug, PartialEq)]
pub struct LightPlan {
    /// Light name.
    pub name: String,
    /// Watts summed over channels (directional: irradiance × its footprint, the area of
    /// the scene it lights as it sees it).
    pub power_w: f64,
    /// Photons per iteration (none for a light whose share rounds to no photon).
    pub photons: u64,
    /// Batches per iteration.
    pub batches: u64,
}

/// What `plan` reports.
#[derive(Clone, Debug, PartialEq)]
pub struct ScenePlan {
    /// Triangles.
    pub triangles: usize,
    /// Bounds (min, max), meters.
    pub bounds: (Vec3, Vec3),
    /// Surface area, m².
    pub area_m2: f64,
    /// Whether anything moves.
    pub animated: bool,
    /// Emitted power of lights and emissive surfaces, W per channel.
    pub emitted_w: Vec3,
    /// Photon budget per light (each emissive object counts as one light).
    pub lights: Vec<LightPlan>,
    /// Photons emitted per watt (summed over channels) at that budget.
    pub photons_per_watt: f64,
    /// Occupied voxels per octree level, root (level 0) first.
    pub voxels_per_level: Vec<u64>,
    /// Leaf voxel size, meters.
    pub leaf_voxel_m: f32,
    /// Light-map texels.
    pub lightmap_texels: u64,
    /// Light-map bases.
    pub bases: u64,
}

/// Computes the plan of `scene` at scene time 0.
pub fn plan(scene: &Scene, s: &PlanSettings) -> ScenePlan {
    let tris = scene.triangles_at(0.0);
    let (lo, hi) = scene.bounds_at(0.0);
    let area: f64 = tris
        .iter()
        .map(|t| 0.5 * (t.v[1] - t.v[0]).cross(t.v[2] - t.v[0]).length() as f64)
        .sum();
    // Photon budget: the photon tracer's own lights and batch plan.
    let photon_lights = crate::photon::photon_lights_in(scene, 0.0, &tris);
    let settings = crate::photon::PhotonSettings::for_stage_budget(
        scene,
        Some(s.photons),
        s.photons_per_watt,
        s.batch_size.clamp(1, crate::photon::MAX_BATCH_SIZE as u64) as u32,
    );
    let batch_plan = crate::photon::BatchPlan::new(&photon_lights, &settings);
    let lights: Vec<LightPlan> = photon_lights
        .iter()
        .map(|l| {
            let batches = batch_plan.batches_of(l.id) as u64;
            LightPlan {
                name: l.name.clone(),
                power_w: l.watts(),
                photons: batch_plan.photons_of(l.id),
                batches,
            }
        })
        .collect();

    // The voxel technique's own voxelization at the planned depth (every leaf a surface
    // crosses, exactly), over the geometry's bounds at all times.
    let levels = s.octree_levels.min(12);
    let (swept_lo, swept_hi) = scene.swept_bounds();
    let grid = crate::voxel::Grid::around(swept_lo, swept_hi, levels);
    let leaves = crate::voxel::voxelize::fragments(&tris, &scene.materials, &grid);
    let octree = crate::voxel::Octree::from_leaves(grid, &leaves);
    let voxels_per_level = octree.levels.iter().map(|l| l.len() as u64).collect();
    let leaf = grid.voxel_m(levels);
    let texels = (area * s.texels_per_m2).round() as u64;
    ScenePlan {
        triangles: tris.len(),
        bounds: (lo, hi),
        area_m2: area,
        animated: scene.is_animated(),
        emitted_w: scene.emitted_power_w(),
        lights,
        photons_per_watt: settings.photons_per_watt,
        voxels_per_level,
        leaf_voxel_m: leaf,
        lightmap_texels: texels,
        bases: (texels as f64 / s.texels_per_basis).ceil() as u64,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cornell_box_plans_like_the_paper() {
        let p = plan(
            &cloudlight_scenes::builtin("cornell").unwrap(),
            &PlanSettings::default(),
        );
        assert_eq!(p.triangles, 32);
        assert_eq!(p.lights.len(), 1);
        assert_eq!(p.lights[0].batches, 1, "one batch of 10k photons");
        assert!(
            (9_000..11_000).contains(&p.lights[0].photons),
            "{}",
            p.lights[0].photons
        );
        assert!(
            (14_000..19_000).contains(&p.lightmap_texels),
            "about 128²: {}",
            p.lightmap_texels
        );
        assert!((40..60).contains(&p.bases), "about 50 bases: {}", p.bases);
        assert_eq!(p.voxels_per_level[0], 1);
        assert!(
            p.voxels_per_level
                .windows(2)
                .all(|w| w[1] >= w[0] && w[1] <= w[0] * 8)
        );
        // Surfaces are 2D: occupied leaves grow about 4× per level, far below the 8× of a volume.
        let (a, b) = (p.voxels_per_level[8] as f64, p.voxels_per_level[9] as f64);
        assert!((3.0..5.0).contains(&(b / a)), "{a} → {b}");
    }

    #[test]
    fn photons_follow_the_batchers_budget_whatever_the_scenes_watts() {
        // A town under a sun of megawatts and lamps of 245 W: the batcher's 10k photons an
        // iteration, nearly all the sun's (the rate of the Cornell box, 7k per watt, would
        // give it billions).
        let city = cloudlight_scenes::builtin("city:2000").unwrap();
        let p = plan(&city, &PlanSettings::default());
        let total: u64 = p.lights.iter().map(|l| l.photons).sum();
        assert!(
            total.abs_diff(crate::photon::DEFAULT_PHOTONS) <= 100,
            "{total}"
        );
        let sun = &p.lights[0];
        assert_eq!(sun.name, "sun");
        assert!(sun.photons as f64 >= 0.99 * total as f64, "{:?}", p.lights);
        assert!(
            p.lights.len() > 1,
            "the lamps are listed, with their shares"
        );
        // Photons per watt, when given, set the rate instead.
        let per_watt = PlanSettings {
            photons_per_watt: Some(2.0 * p.photons_per_watt),
            ..PlanSettings::default()
        };
        let doubled: u64 = plan(&city, &per_watt)
            .lights
            .iter()
            .map(|l| l.photons)
            .sum();
        assert!(
            doubled.abs_diff(2 * total) <= 100,
            "{doubled} vs 2 × {total}"
        );
    }

    #[test]
    fn a_scene_without_lights_plans_no_photons() {
        let mut s = cloudlight_scenes::builtin("cornell").unwrap();
        s.materials.iter_mut().for_each(|m| m.emission = Vec3::ZERO);
        assert!(plan(&s, &PlanSettings::default()).lights.is_empty());
    }
}
