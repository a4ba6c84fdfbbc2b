//! What every scene must be before a kernel sees it: finite numbers, geometry within
//! [`MAX_EXTENT_M`], indices in range, lights and cameras that mean something.
//!
//! [`crate::load`] runs [`check`] on every scene it returns (built-in or glTF), so the
//! kernels, the raster and `plan` may rely on it: no NaN reaches a BVH, no squared length
//! overflows `f32` (coordinates near 1e20 m made `plan`'s voxel walk run for ever), no
//! camera is degenerate. Checking is linear in the scene's size.

use glam::{Affine3A, Vec3};

use crate::model::{Camera, LightKind, Motion, Scene};

/// Largest distance from the origin of any vertex, light or camera, meters (100 km: far
/// beyond any level, city or terrain tile here; `f32` still resolves 8 mm there, and squared
/// lengths stay far from overflow).
pub const MAX_EXTENT_M: f32 = 100_000.0;
/// Largest emitted radiance of a material, W·m⁻²·sr⁻¹ per channel, and power of a light, W
/// per channel (a stadium floodlight is 10⁵ W; the sun's irradiance is 10³ W·m⁻²).
pub const MAX_EMISSION: f32 = 1e9;
/// Narrowest and widest vertical field of view of a camera, degrees.
pub const FOV_RANGE_DEG: (f32, f32) = (0.1, 179.0);

/// Checks `scene`, returning every problem found (at most a few per kind, so a broken file
/// of millions of vertices gives a readable list).
pub fn check(scene: &Scene) -> Result<(), String> {
    let mut problems = Problems::default();
    check_materials(scene, &mut problems);
    check_objects(scene, &mut problems);
    check_lights(scene, &mut problems);
    for (i, c) in scene.cameras.iter().enumerate() {
        let name = format!("camera {i} (`{}`)", c.name);
        if let Err(e) = check_camera(&c.camera) {
            problems.push("camera", format!("{name}: {e}"));
        }
        check_motion(&c.motion, &name, &mut problems);
    }
    problems.finish()
}

/// Checks one camera: finite, within the extent, looking somewhere, an up direction not
/// along the view, and a field of view in [`FOV_RANGE_DEG`].
pub fn check_camera(c: &Camera) -> Result<(), String> {
    if !(c.position.is_finite() && c.target.is_finite() && c.up.is_finite()) {
        return Err("position, target and up must be finite".into());
    }
    if c.position.abs().max_element() > MAX_EXTENT_M || c.target.abs().max_element() > MAX_EXTENT_M
    {
        return Err(format!(
            "position and target must lie within {MAX_EXTENT_M} m of the origin"
        ));
    }
    let forward = c.target - c.position;
    if forward.length() < 1e-6 {
        return Err("target is the position: the camera looks nowhere".into());
    }
    if forward.normalize().cross(c.up.normalize_or_zero()).length() < 1e-3 {
        return Err("up is zero or along the view direction".into());
    }
    let fov = c.fov_y_rad.to_degrees();
    if !(fov.is_finite() && fov >= FOV_RANGE_DEG.0 && fov <= FOV_RANGE_DEG.1) {
        return Err(format!(
            "field of view {fov}° is out of range: must be in [{}, {}] degrees",
            FOV_RANGE_DEG.0, FOV_RANGE_DEG.1
        ));
    }
    Ok(())
}

/// Problems grouped by kind, a few of each kept with the count of the rest.
#[derive(Default)]
struct Problems {
    kinds: Vec<(&'static str, Vec<String>, usize)>,
}

impl Problems {
    const SHOWN: usize = 3;

    fn push(&mut self, kind: &'static str, message: String) {
        let at = match self.kinds.iter().position(|(k, ..)| *k == kind) {
            Some(i) => i,
            None => {
                self.kinds.push((kind, Vec::new(), 0));
                self.kinds.len() - 1
            }
        };
        let (_, shown, more) = &mut self.kinds[at];
        if shown.len() < Self::SHOWN {
            shown.push(message);
        } else {
            *more += 1;
        }
    }

    fn finish(self) -> Result<(), String> {
        if self.kinds.is_empty() {
            return Ok(());
        }
        let mut lines = Vec::new();
        for (kind, shown, more) in self.kinds {
            lines.extend(shown);
            if more > 0 {
                lines.push(format!("… and {more} more {kind} problems"));
            }
        }
        Err(lines.join("; "))
    }
}

fn in_extent(p: Vec3) -> bool {
    p.is_finite() && p.abs().max_element() <= MAX_EXTENT_M
}

fn check_materials(scene: &Scene, problems: &mut Problems) {
    for (i, m) in scene.materials.iter().enumerate() {
        let name = format!("material {i} (`{}`)", m.name);
        if !(m.albedo.is_finite() && m.albedo.min_element() >= 0.0 && m.albedo.max_element() <= 1.0)
        {
            problems.push("material", format!("{name}: albedo must be in [0, 1]"));
        }
        if !(m.emission.is_finite()
            && m.emission.min_element() >= 0.0
            && m.emission.max_element() <= MAX_EMISSION)
        {
            problems.push(
                "material",
                format!("{name}: emission must be in [0, {MAX_EMISSION:e}] W·m⁻²·sr⁻¹"),
            );
        }
        if let Some(t) = &m.texture
            && (t.width == 0
                || t.height == 0
                || t.texels.len() as u64 != t.width as u64 * t.height as u64)
        {
            problems.push(
                "material",
                format!("{name}: texture is not {}×{} texels", t.width, t.height),
            );
        }
    }
}

fn check_objects(scene: &Scene, problems: &mut Problems) {
    for (i, o) in scene.objects.iter().enumerate() {
        let name = format!("object {i} (`{}`)", o.name);
        let mesh = &o.mesh;
        let n = mesh.positions.len();
        if o.material as usize >= scene.materials.len() {
            problems.push(
                "object",
                format!("{name}: material {} does not exist", o.material),
            );
        }
        if mesh.normals.len() != n
            || (!mesh.uvs.is_empty() && mesh.uvs.len() != n)
            || (!mesh.lightmap_uvs.is_empty() && mesh.lightmap_uvs.len() != n)
        {
            problems.push(
                "object",
                format!("{name}: normals or UVs do not match its {n} positions"),
            );
        }
        if let Some(bad) = mesh.indices.iter().flatten().find(|&&k| k as usize >= n) {
            problems.push(
                "object",
                format!("{name}: index {bad} is out of range ({n} vertices)"),
            );
        }
        if !mesh.normals.iter().all(|v| v.is_finite())
            || !mesh
                .uvs
                .iter()
                .chain(&mesh.lightmap_uvs)
                .all(|v| v.is_finite())
        {
            problems.push("object", format!("{name}: non-finite normals or UVs"));
        }
        check_motion(&o.motion, &name, problems);
        let world = o.motion.world_from_local(0.0);
        if let Some(p) = mesh
            .positions
            .iter()
            .map(|p| world.transform_point3(*p))
            .find(|p| !in_extent(*p))
        {
            problems.push(
                "object",
                format!(
                    "{name}: vertex at {p} m lies beyond {MAX_EXTENT_M} m of the origin (or is not finite)"
                ),
            );
        }
    }
}

fn check_lights(scene: &Scene, problems: &mut Problems) {
    for (i, l) in scene.lights.iter().enumerate() {
        let name = format!("light {i} (`{}`)", l.name);
        let power_ok =
            |v: Vec3| v.is_finite() && v.min_element() >= 0.0 && v.max_element() <= MAX_EMISSION;
        if !power_ok(l.power_w) {
            problems.push(
                "light",
                format!("{name}: power must be in [0, {MAX_EMISSION:e}] W"),
            );
        }
        match &l.kind {
            LightKind::Point => {}
            LightKind::Spot {
                direction,
                cone_angle_rad,
            } => {
                if !(direction.is_finite() && direction.length() > 1e-6) {
                    problems.push(
                        "light",
                        format!("{name}: spot direction is zero or not finite"),
                    );
                }
                if !(cone_angle_rad.is_finite()
                    && *cone_angle_rad > 0.0
                    && *cone_angle_rad <= std::f32::consts::PI)
                {
                    problems.push(
                        "light",
                        format!("{name}: cone angle {cone_angle_rad} rad must be in (0, π]"),
                    );
                }
            }
            LightKind::Directional { irradiance_w_m2 } => {
                if !power_ok(*irradiance_w_m2) {
                    problems.push(
                        "light",
                        format!("{name}: irradiance must be in [0, {MAX_EMISSION:e}] W·m⁻²"),
                    );
                }
            }
        }
        if let Some(sun) = &l.sun_path {
            let fixed_ok = sun.fixed.is_none_or(|d| d.is_finite() && d.length() > 1e-6);
            if !(fixed_ok
                && sun.day_length_s.is_finite()
                && sun.day_length_s > 0.0
                && sun.phase.is_finite()
                && sun.max_elevation_rad.is_finite())
            {
                problems.push("light", format!("{name}: sun path is not finite"));
            }
        }
        check_motion(&l.motion, &name, problems);
    }
}

/// A motion is finite, periodic with a positive period, and stays within the extent.
fn check_motion(m: &Motion, name: &str, problems: &mut Problems) {
    let ok = match m {
        Motion::Static(a) => affine_ok(a),
        Motion::Orbit {
            center,
            axis,
            radius,
            period_s,
            phase,
        } => {
            in_extent(*center)
                && axis.is_finite()
                && radius.is_finite()
                && radius.abs() <= MAX_EXTENT_M
                && period_s.is_finite()
                && *period_s > 0.0
                && phase.is_finite()
        }
        Motion::Path { keys } => {
            keys.iter().all(|(t, p)| t.is_finite() && in_extent(*p))
                && keys.windows(2).all(|w| w[0].0 <= w[1].0)
        }
    };
    if !ok {
        problems.push(
            "motion",
            format!(
                "{name}: its motion is not finite, not periodic, or leaves {MAX_EXTENT_M} m of the origin"
            ),
        );
    }
}

fn affine_ok(a: &Affine3A) -> bool {
    a.is_finite() && in_extent(a.translation.into())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::builtin;

    #[test]
    fn the_built_in_scenes_pass() {
        for name in ["cornell", "cornell-animated", "city:1000"] {
            check(&builtin(name).unwrap()).unwrap();
        }
    }

    #[test]
    fn far_non_finite_and_degenerate_scenes_are_refused() {
        let base = builtin("cornell").unwrap();
        type Breaks = Box<dyn Fn(&mut Scene)>;
        let cases: Vec<(&str, Breaks)> = vec![
            (
                "beyond",
                Box::new(|s| s.objects[0].mesh.positions[0] = Vec3::splat(1e20)),
            ),
            (
                "beyond",
                Box::new(|s| s.objects[0].mesh.positions[0].x = f32::NAN),
            ),
            (
                "index",
                Box::new(|s| s.objects[0].mesh.indices[0][1] = 1 << 30),
            ),
            (
                "albedo",
                Box::new(|s| s.materials[0].albedo = Vec3::splat(-1.0)),
            ),
            (
                "emission",
                Box::new(|s| s.materials[0].emission.y = f32::INFINITY),
            ),
            (
                "looks nowhere",
                Box::new(|s| s.cameras[0].camera.target = s.cameras[0].camera.position),
            ),
            (
                "field of view",
                Box::new(|s| s.cameras[0].camera.fov_y_rad = std::f32::consts::PI),
            ),
            (
                "field of view",
                Box::new(|s| s.cameras[0].camera.fov_y_rad = 0.0),
            ),
            ("up", Box::new(|s| s.cameras[0].camera.up = Vec3::ZERO)),
            (
                "finite",
                Box::new(|s| s.cameras[0].camera.position.z = f32::NAN),
            ),
            (
                "motion",
                Box::new(|s| {
                    s.objects[0].motion = Motion::Orbit {
                        center: Vec3::ZERO,
                        axis: Vec3::Y,
                        radius: 1.0,
                        period_s: 0.0,
                        phase: 0.0,
                    }
                }),
            ),
        ];
        for (words, break_it) in cases {
            let mut s = base.clone();
            if s.cameras.is_empty() {
                s.cameras.push(crate::CameraPath {
                    name: "c".into(),
                    camera: s.overview_camera(),
                    motion: Motion::identity(),
                });
            }
            break_it(&mut s);
            let e = check(&s).unwrap_err();
            assert!(e.contains(words), "{words}: {e}");
        }
    }

    #[test]
    fn a_broken_mesh_reports_a_few_problems_and_counts_the_rest() {
        let mut s = builtin("cornell").unwrap();
        for o in &mut s.objects {
            o.mesh.positions[0] = Vec3::splat(f32::NAN);
        }
        let e = check(&s).unwrap_err();
        assert_eq!(e.matches("lies beyond").count(), Problems::SHOWN, "{e}");
        assert!(e.contains("more object problems"), "{e}");
    }
}
