//! Physics checks of the reference path tracer.

use cloudlight_scenes::{Camera, Material, Mesh, Motion, Object, Scene};
use glam::Vec3;

use super::*;
use crate::bvh::BvhKind;

/// A closed unit cube, inside faces of albedo `a`, every face emitting radiance `le`.
fn furnace(a: f32, le: f32) -> Scene {
    let mut mesh = Mesh::default();
    mesh.push_box(Vec3::ZERO, Vec3::ONE);
    Scene {
        name: "furnace".into(),
        materials: vec![Material {
            emission: Vec3::splat(le),
            ..Material::diffuse("wall", Vec3::splat(a))
        }],
        objects: vec![Object {
            name: "box".into(),
            mesh: mesh.flipped(),
            material: 0,
            motion: Motion::identity(),
        }],
        lights: Vec::new(),
        cameras: Vec::new(),
    }
}

fn settings(camera: Camera, size: u32) -> RenderSettings {
    RenderSettings {
        width: size,
        height: size,
        camera,
        time_s: 0.0,
        seed: 9,
        max_bounces: 256,
        pixel: Default::default(),
    }
}

fn rmse(img: &[Vec3], expect: f32) -> f64 {
    (img.iter()
        .map(|v| ((v.x - expect) as f64).powi(2))
        .sum::<f64>()
        / img.len() as f64)
        .sqrt()
}

fn mean(img: &[Vec3]) -> Vec3 {
    img.iter().copied().sum::<Vec3>() / img.len() as f32
}

#[test]
fn a_furnace_converges_to_the_analytic_radiance() {
    // Radiance everywhere is Le / (1 − a): Le seen directly, a·Le reflected once, the rest
    // from longer paths.
    let (a, le) = (0.5, 1.0);
    let scene = furnace(a, le);
    let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
    let cam = Camera {
        position: Vec3::splat(0.5),
        target: Vec3::new(0.5, 0.5, 1.0),
        up: Vec3::Y,
        fov_y_rad: 1.2,
    };
    let few = render(&scene, &bvh, settings(cam, 16), 4);
    let many = render(&scene, &bvh, settings(cam, 16), 64);
    let full = mean(&many.full());
    assert!((full.x - le / (1.0 - a)).abs() < 0.02, "full {full}");
    let direct = mean(&many.direct());
    assert!((direct.x - (le + a * le)).abs() < 0.02, "direct {direct}");
    let indirect = mean(&many.indirect());
    assert!(
        (indirect.x - a * a * le / (1.0 - a)).abs() < 0.02,
        "indirect {indirect}"
    );
    // Error falls as 1/√spp: 16× the samples, about a quarter of the error.
    let (e_few, e_many) = (rmse(&few.indirect(), 0.5), rmse(&many.indirect(), 0.5));
    let ratio = e_few / e_many;
    assert!(
        (2.5..6.5).contains(&ratio),
        "error {e_few} at 4 spp, {e_many} at 64 spp: ratio {ratio}"
    );
}

#[test]
fn images_are_deterministic_and_passes_add_up() {
    let scene = cloudlight_scenes::builtin("cornell").unwrap();
    let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
    let s = settings(scene.cameras[0].camera, 12);
    let whole = render(&scene, &bvh, s, 6);
    let r = ReferenceRenderer::new(&scene, &bvh, s);
    let mut split = ReferenceImages::new(12, 12);
    r.render_pass(&mut split, 0, 2);
    r.render_pass(&mut split, 2, 4);
    for (a, b) in whole.full().iter().zip(split.full()) {
        assert!((*a - b).abs().max_element() <= 1e-5 * a.max_element().max(1.0));
    }
    assert_eq!(whole, render(&scene, &bvh, s, 6));
    // Paths go in batches of whole pixels: 128 samples of a 40-pixel row make two batches
    // of a row, 64 make one; the sums are the same.
    let s = settings(scene.cameras[0].camera, 40);
    const { assert!(PATHS_PER_BATCH / 128 < 40 && PATHS_PER_BATCH / 64 >= 40) };
    let whole = render(&scene, &bvh, s, 128);
    let r = ReferenceRenderer::new(&scene, &bvh, s);
    let mut split = ReferenceImages::new(40, 40);
    r.render_pass(&mut split, 0, 64);
    r.render_pass(&mut split, 64, 64);
    let (whole, split) = (whole.full(), split.full());
    assert!(whole.iter().filter(|p| p.max_element() > 0.0).count() > 40 * 40 / 2);
    for (a, b) in whole.iter().zip(&split) {
        assert!((*a - *b).abs().max_element() <= 1e-5 * a.max_element().max(1.0));
    }
}

#[test]
fn scene_scale_and_light_power_change_images_as_physics_says() {
    let base = cloudlight_scenes::builtin("cornell").unwrap();
    let image = |scene: &Scene| {
        let bvh = SceneBvh::at(scene, 0.0, BvhKind::default());
        let img = render(scene, &bvh, settings(scene.cameras[0].camera, 10), 8);
        let full = img.full();
        assert!(full.iter().all(|v| v.is_finite() && v.min_element() >= 0.0));
        mean(&full)
    };
    let reference = image(&base);
    assert!(reference.min_element() > 0.0);
    // Radiance does not depend on the unit of length.
    for s in [1e-3, 1e4] {
        let m = image(&base.clone().scaled(s));
        assert!(
            ((m - reference) / reference).abs().max_element() < 0.02,
            "scale {s}: {m} vs {reference}"
        );
    }
    // It is linear in the emitted power: the 0.7 W light at 1e-6 W and 1e6 W.
    let power = base.emitted_power_w().x;
    for watts in [1e-6f32, 1e6] {
        let mut s = base.clone();
        let k = watts / power;
        s.materials.iter_mut().for_each(|m| m.emission *= k);
        let m = image(&s);
        assert!(
            ((m / k - reference) / reference).abs().max_element() < 1e-3,
            "{watts} W: {m}"
        );
    }
}

#[test]
fn a_scene_without_lights_is_black_and_degenerate_triangles_are_harmless() {
    let mut s = cloudlight_scenes::builtin("cornell").unwrap();
    s.materials.iter_mut().for_each(|m| m.emission = Vec3::ZERO);
    let junk = Mesh {
        positions: vec![Vec3::splat(0.3); 3],
        normals: vec![Vec3::ZERO; 3],
        indices: vec![[0, 1, 2]],
        ..Default::default()
    };
    s.objects.push(Object {
        name: "degenerate".into(),
        mesh: junk,
        material: 0,
        motion: Motion::identity(),
    });
    let bvh = SceneBvh::at(&s, 0.0, BvhKind::default());
    let img = render(&s, &bvh, settings(s.cameras[0].camera, 8), 2);
    assert!(img.full().iter().all(|v| *v == Vec3::ZERO));
}

/// Paths traced one at a time with one ray at a time (closest hits and shadow rays), each
/// vertex's next-event estimate resolved at once: the (direct, indirect) sums per pixel that
/// [`ReferenceRenderer::render_pass`] must reproduce with its batches.
fn one_path_at_a_time(r: &ReferenceRenderer, spp: u32) -> (Vec<Vec3>, Vec<Vec3>) {
    let s = r.settings;
    let n = (s.width * s.height) as usize;
    let (mut direct, mut indirect) = (vec![Vec3::ZERO; n], vec![Vec3::ZERO; n]);
    for pixel in 0..n {
        let (x, y) = (pixel % s.width as usize, pixel / s.width as usize);
        for k in 0..spp {
            let mut path = r.camera_path(x, y, k);
            for bounce in 0..s.max_bounces {
                let Some(hit) = r.bvh.closest_hit(path.o, path.d, f32::INFINITY) else {
                    break;
                };
                let (mut lit, mut vertices) = (Vec::new(), Vec::new());
                let goes_on = r.step(&mut path, 0, bounce, &hit, &mut lit, &mut vertices);
                let blocked: Vec<bool> = lit
                    .iter()
                    .map(|l| r.bvh.occluded(l.ray.0, l.ray.1, l.ray.2))
                    .collect();
                vertices[0].add(&mut path, DirectLight::sum_clear(&lit, &blocked));
                if !goes_on {
                    break;
                }
            }
            direct[pixel] += path.direct;
            indirect[pixel] += path.indirect;
        }
    }
    (direct, indirect)
}

#[test]
fn batched_paths_and_shadow_rays_give_what_one_path_at_a_time_gives() {
    // A city: a sun and street lamps, so each vertex casts several shadow rays, some
    // blocked; the batches cast them light by light and must hand each result back to its
    // own vertex and term.
    let scene = cloudlight_scenes::builtin("city:2000").unwrap();
    let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
    assert!(scene.lights.len() > 2, "{} lights", scene.lights.len());
    let mut s = settings(scene.cameras[0].camera, 16);
    s.max_bounces = 4;
    let r = ReferenceRenderer::new(&scene, &bvh, s);
    let mut images = ReferenceImages::new(16, 16);
    r.render_pass(&mut images, 0, 4);
    let (direct, indirect) = one_path_at_a_time(&r, 4);
    assert!(direct.iter().filter(|d| d.max_element() > 0.0).count() > 16 * 16 / 4);
    let lit = indirect.iter().filter(|d| d.max_element() > 0.0).count();
    assert!(lit > 16, "{lit} pixels with indirect light");
    for (i, (a, b)) in images.direct_sum.iter().zip(&direct).enumerate() {
        assert_eq!(a, b, "direct light of pixel {i}");
    }
    for (i, (a, b)) in images.indirect_sum.iter().zip(&indirect).enumerate() {
        assert_eq!(a, b, "indirect light of pixel {i}");
    }
}
