//! The raster G-buffer agrees with ray casting.

use glam::{Vec2, Vec3};

use super::*;
use crate::bvh::{BvhKind, SceneBvh};

/// The camera ray through the centre of each pixel of a `w` × `h` frame, row-major from the
/// top.
fn pixel_rays(camera: &cloudlight_scenes::Camera, w: u32, h: u32) -> Vec<Vec3> {
    let aspect = w as f32 / h as f32;
    (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let ndc = Vec2::new(
                (x as f32 + 0.5) / w as f32 * 2.0 - 1.0,
                1.0 - (y as f32 + 0.5) / h as f32 * 2.0,
            );
            camera.ray_direction(ndc, aspect)
        })
        .collect()
}

/// Runs `test` on the Vulkan and on the GL adapter, each where it exists: a backend without
/// an adapter (or excluded by `WGPU_BACKEND`) is skipped with a printed reason; no adapter at
/// all fails the test.
pub(crate) fn on_every_backend(test: impl Fn(&Raster)) {
    use std::io::Write;
    // Written to the process's stderr, not through `eprintln!`, so that the test harness does
    // not capture it: a skipped backend shows in every test log.
    let say = |line: String| {
        let _ = writeln!(std::io::stderr(), "{line}");
    };
    let mut ran = 0;
    for (name, backend) in [
        ("Vulkan", wgpu::Backends::VULKAN),
        ("GL", wgpu::Backends::GL),
    ] {
        if device::backends(wgpu::Backends::all()) & backend != backend {
            say(format!(
                "raster test skipped on {name}: WGPU_BACKEND excludes it"
            ));
            continue;
        }
        match Raster::with_backends(backend) {
            Ok(raster) => {
                eprintln!("on {name}: {}", raster.describe());
                test(&raster);
                ran += 1;
            }
            Err(e) => say(format!("raster test skipped on {name}: {e}")),
        }
    }
    assert!(ran > 0, "no backend has an adapter");
}

#[test]
fn the_gbuffer_of_the_cornell_box_matches_ray_casting() {
    on_every_backend(|raster| {
        eprintln!("adapter: {:?}", raster.adapter());
        let scene = cloudlight_scenes::builtin("cornell").unwrap();
        let tris = scene.triangles_at(0.0);
        let camera = scene.cameras[0].camera;
        let (w, h) = (64u32, 64u32);
        let g = raster.gbuffer(&scene, &tris, &camera, w, h).unwrap();
        let bvh = SceneBvh::build(tris, BvhKind::default());
        let (mut both, mut disagree) = (0, 0);
        for (i, d) in pixel_rays(&camera, w, h).into_iter().enumerate() {
            let hit = bvh.closest_hit(camera.position, d, f32::INFINITY);
            let drawn = g.position[i].w > 0.5;
            match hit {
                Some(hit) if drawn => {
                    both += 1;
                    let p = camera.position + d * hit.t;
                    let tri = &bvh.triangles()[hit.triangle as usize];
                    let albedo = scene.materials[tri.material as usize].albedo;
                    let mut n = bvh.geometric_normal(hit.triangle);
                    if n.dot(d) > 0.0 {
                        n = -n;
                    }
                    let same = (g.position[i].truncate() - p).length() < 2e-3
                        && g.normal[i].dot(n) > 0.99
                        && (g.albedo[i] - albedo).abs().max_element() < 1e-2;
                    if !same {
                        disagree += 1; // a silhouette or a crease between two surfaces
                    }
                }
                None if !drawn => {}
                _ => disagree += 1,
            }
        }
        eprintln!("{both} pixels covered by both, {disagree} disagree");
        assert!(
            both > (w * h) as usize * 9 / 10,
            "only {both} pixels covered"
        );
        assert!(
            disagree <= (w * h) as usize / 50,
            "{disagree} of {} pixels disagree",
            w * h
        );
    });
}

#[test]
fn an_empty_scene_gives_an_empty_gbuffer() {
    on_every_backend(|raster| {
        let scene = cloudlight_scenes::builtin("cornell").unwrap();
        let g = raster
            .gbuffer(&scene, &[], &scene.cameras[0].camera, 8, 8)
            .unwrap();
        assert!(g.position.iter().all(|p| p.w == 0.0));
        assert_eq!(g.normal.len(), 64);
        assert!(g.albedo.iter().all(|a| *a == Vec3::ZERO));
    });
}

/// Per-pixel error of `test` against `reference`, relative with a floor of 2% of the mean
/// (so that nearly black pixels do not dominate), worst channel.
fn relative_error(test: Vec3, reference: Vec3, mean: f32) -> f32 {
    ((test - reference).abs() / (reference + Vec3::splat(0.02 * mean))).max_element()
}

/// The reference's mean over `covered` pixels, and the sorted relative errors there.
fn relative_errors(test: &[Vec3], reference: &[Vec3], covered: &[usize]) -> (f32, Vec<f32>) {
    let mean = covered
        .iter()
        .map(|&i| reference[i].element_sum() / 3.0)
        .sum::<f32>()
        / covered.len() as f32;
    let mut errors: Vec<f32> = covered
        .iter()
        .map(|&i| relative_error(test[i], reference[i], mean))
        .collect();
    errors.sort_by(f32::total_cmp);
    (mean, errors)
}

/// The path tracer's settings for direct light only (one bounce) through `camera`, each
/// pixel's area sampled.
fn direct_settings(
    camera: cloudlight_scenes::Camera,
    (width, height): (u32, u32),
    seed: u64,
) -> crate::reference::RenderSettings {
    crate::reference::RenderSettings {
        width,
        height,
        camera,
        time_s: 0.0,
        seed,
        max_bounces: 1,
        pixel: Default::default(),
    }
}

fn lit_scene() -> cloudlight_scenes::Scene {
    use cloudlight_scenes::{
        Light, LightKind, Material, Mesh, Motion, Object, Scene, model::SunPath,
    };
    let mut ground = Mesh::default();
    ground.push_quad(
        Vec3::new(-5.0, 0.0, 5.0),
        Vec3::new(5.0, 0.0, 5.0),
        Vec3::new(5.0, 0.0, -5.0),
        Vec3::new(-5.0, 0.0, -5.0),
    );
    let mut block = Mesh::default();
    block.push_box(Vec3::new(-0.5, 0.0, -0.5), Vec3::new(0.5, 1.0, 0.5));
    let at = |p: Vec3| Motion::Static(glam::Affine3A::from_translation(p));
    Scene {
        name: "lit".into(),
        materials: vec![
            Material::diffuse("ground", Vec3::splat(0.5)),
            Material::diffuse("block", Vec3::new(0.7, 0.3, 0.2)),
        ],
        objects: vec![
            Object {
                name: "ground".into(),
                mesh: ground,
                material: 0,
                motion: Motion::identity(),
            },
            Object {
                name: "block".into(),
                mesh: block,
                material: 1,
                motion: Motion::identity(),
            },
        ],
        lights: vec![
            Light {
                name: "point".into(),
                kind: LightKind::Point,
                power_w: Vec3::splat(60.0),
                motion: at(Vec3::new(-2.0, 2.0, -1.0)),
                sun_path: None,
            },
            Light {
                name: "spot".into(),
                kind: LightKind::Spot {
                    direction: Vec3::new(-0.3, -1.0, -0.2).normalize(),
                    cone_angle_rad: 0.6,
                },
                power_w: Vec3::new(80.0, 60.0, 40.0),
                motion: at(Vec3::new(1.5, 3.0, 1.0)),
                sun_path: None,
            },
            Light {
                name: "sun".into(),
                kind: LightKind::Directional {
                    irradiance_w_m2: Vec3::splat(10.0),
                },
                power_w: Vec3::ZERO,
                motion: Motion::identity(),
                sun_path: Some(SunPath::fixed(Vec3::new(0.8, -0.6, 0.9))),
            },
        ],
        cameras: vec![cloudlight_scenes::CameraPath {
            name: "view".into(),
            camera: cloudlight_scenes::Camera {
                position: Vec3::new(4.0, 4.0, 5.0),
                target: Vec3::new(0.0, 0.3, 0.0),
                up: Vec3::Y,
                fov_y_rad: 0.9,
            },
            motion: Motion::identity(),
        }],
    }
}

#[test]
fn raster_direct_light_matches_the_path_tracer_direct_image() {
    // Tolerance: the median pixel within 2% and 90% of the pixels both draw within 5%
    // (relative, with a floor of 2% of the mean) of the path tracer's direct-only image. The
    // remaining pixels are edges — silhouettes, the spot cone's border, shadow borders —
    // where the raster samples the pixel center and the path tracer averages 16 jittered
    // samples (measured at 64²: median 0.04%, p90 1.3%, p95 16%).
    on_every_backend(|raster| {
        let scene = lit_scene();
        let tris = scene.triangles_at(0.0);
        let lights: Vec<_> = scene.lights.iter().map(|l| l.at(0.0)).collect();
        let camera = scene.cameras[0].camera;
        let (w, h) = (128u32, 128u32);
        let (g, direct) = raster
            .direct(
                &scene,
                &tris,
                &lights,
                &camera,
                w,
                h,
                ShadowSettings::default(),
            )
            .unwrap();
        let bvh = SceneBvh::build(tris, BvhKind::default());
        let settings = direct_settings(camera, (w, h), 3);
        let reference = crate::reference::render(&scene, &bvh, settings, 16).direct();
        let covered: Vec<usize> = (0..(w * h) as usize)
            .filter(|&i| g.position[i].w > 0.5)
            .collect();
        let (mean, errors) = relative_errors(&direct, &reference, &covered);
        assert!(mean > 0.0);
        let p50 = errors[errors.len() / 2];
        let p95 = errors[errors.len() * 95 / 100];
        eprintln!(
            "relative error p50 {p50:.4}, p90 {:.4}, p95 {p95:.4} over {} pixels",
            errors[errors.len() * 90 / 100],
            errors.len()
        );
        if let Ok(dir) = std::env::var("CLOUDLIGHT_DEBUG_IMAGES") {
            let dir = std::path::Path::new(&dir);
            crate::image_io::write_png(&dir.join("raster_direct.png"), w, h, &direct, 1.0).unwrap();
            crate::image_io::write_png(&dir.join("traced_direct.png"), w, h, &reference, 1.0)
                .unwrap();
            let diff: Vec<Vec3> = direct
                .iter()
                .zip(&reference)
                .map(|(a, b)| (*a - *b).abs() * 4.0)
                .collect();
            crate::image_io::write_png(&dir.join("difference_x4.png"), w, h, &diff, 1.0).unwrap();
        }
        assert!(p50 < 0.02, "median relative error {p50}");
        let p90 = errors[errors.len() * 90 / 100];
        assert!(
            p90 < 0.05,
            "90th percentile relative error {p90} (p95 {p95})"
        );
        // Shadows matter: lit by the sun alone, the block's shadow is black in the reference,
        // and the raster must agree on (nearly) all of it.
        let mut sun_only = scene.clone();
        sun_only.lights.retain(|l| l.name == "sun");
        let sun: Vec<_> = sun_only.lights.iter().map(|l| l.at(0.0)).collect();
        let (_, raster_sun) = raster
            .direct(
                &sun_only,
                bvh.triangles(),
                &sun,
                &camera,
                w,
                h,
                ShadowSettings::default(),
            )
            .unwrap();
        let traced_sun = crate::reference::render(&sun_only, &bvh, settings, 4).direct();
        let shadowed: Vec<usize> = covered
            .iter()
            .copied()
            .filter(|&i| traced_sun[i] == Vec3::ZERO)
            .collect();
        let dark = shadowed
            .iter()
            .filter(|&&i| raster_sun[i].max_element() < 1e-3)
            .count();
        assert!(
            shadowed.len() > covered.len() / 50,
            "the test scene should show a sun shadow ({} pixels)",
            shadowed.len()
        );
        assert!(
            dark * 20 >= shadowed.len() * 19,
            "{dark} of {} sun-shadowed pixels are dark in the raster",
            shadowed.len()
        );
    });
}

#[test]
fn every_light_alone_matches_the_path_tracer() {
    // Each light of the test scene alone: the mean of its direct light over the covered
    // pixels within 5% of the path tracer's (catches a light kind that a backend loses
    // altogether, or a shadow lookup that always says "shadowed").
    on_every_backend(|raster| {
        let scene = lit_scene();
        let tris = scene.triangles_at(0.0);
        let camera = scene.cameras[0].camera;
        let (w, h) = (64u32, 64u32);
        let bvh = SceneBvh::build(tris.clone(), BvhKind::default());
        let g = raster.gbuffer(&scene, &tris, &camera, w, h).unwrap();
        let covered = g.covered_pixels();
        let settings = direct_settings(camera, (w, h), 3);
        for light in &scene.lights {
            let mut alone = scene.clone();
            alone.lights.retain(|l| l.name == light.name);
            let states: Vec<_> = alone.lights.iter().map(|l| l.at(0.0)).collect();
            let (_, ours) = raster
                .direct(
                    &alone,
                    &tris,
                    &states,
                    &camera,
                    w,
                    h,
                    ShadowSettings::default(),
                )
                .unwrap();
            let traced = crate::reference::render(&alone, &bvh, settings, 8).direct();
            let sum = |img: &[Vec3]| covered.iter().map(|&i| img[i].element_sum()).sum::<f32>();
            let ratio = sum(&ours) / sum(&traced);
            assert!(
                (ratio - 1.0).abs() < 0.05,
                "{}: raster / traced = {ratio}",
                light.name
            );
        }
    });
}

#[test]
fn raster_direct_light_of_the_cornell_box_matches_the_path_tracer() {
    // The area light becomes 4² × 2 = 32 Lambertian point emitters with shadow maps; the
    // path tracer (1024 spp) samples the area exactly. Tolerance: median pixel within 2%,
    // 90% within 15% (relative, floor 2% of the mean); the rest are penumbrae (banded hard
    // shadows of 32 points against the true soft ones) and silhouettes. Measured at 96²:
    // p50 0.4%, p90 12%, p95 42%. Emitter pixels are left out (the raster's direct term is
    // reflected light only).
    on_every_backend(|raster| {
        let scene = cloudlight_scenes::builtin("cornell").unwrap();
        let tris = scene.triangles_at(0.0);
        let lights = scene.surface_light_samples(0.0, 4);
        assert_eq!(lights.len(), 32);
        let camera = scene.cameras[0].camera;
        let (w, h) = (96u32, 96u32);
        let shadows = ShadowSettings {
            size: 512,
            ..ShadowSettings::default()
        };
        let (g, direct) = raster
            .direct(&scene, &tris, &lights, &camera, w, h, shadows)
            .unwrap();
        let bvh = SceneBvh::build(tris, BvhKind::default());
        let settings = direct_settings(camera, (w, h), 5);
        let reference = crate::reference::render(&scene, &bvh, settings, 1024).direct();
        let aspect = w as f32 / h as f32;
        let covered: Vec<usize> = (0..(w * h) as usize)
            .filter(|&i| {
                let (x, y) = ((i as u32 % w) as f32 + 0.5, (i as u32 / w) as f32 + 0.5);
                let ndc = Vec2::new(x / w as f32 * 2.0 - 1.0, 1.0 - y / h as f32 * 2.0);
                let hit = bvh.closest_hit(
                    camera.position,
                    camera.ray_direction(ndc, aspect),
                    f32::INFINITY,
                );
                g.position[i].w > 0.5
                    && hit.is_some_and(|h| {
                        !scene.materials[bvh.triangles()[h.triangle as usize].material as usize]
                            .is_emissive()
                    })
            })
            .collect();
        let (mean, errors) = relative_errors(&direct, &reference, &covered);
        let q = |p: usize| errors[errors.len() * p / 100];
        if let Ok(dir) = std::env::var("CLOUDLIGHT_DEBUG_IMAGES") {
            let dir = std::path::Path::new(&dir);
            let err_img: Vec<Vec3> = (0..(w * h) as usize)
                .map(|i| Vec3::splat(relative_error(direct[i], reference[i], mean)))
                .collect();
            crate::image_io::write_png(&dir.join("cornell_raster.png"), w, h, &direct, 0.0)
                .unwrap();
            crate::image_io::write_png(&dir.join("cornell_traced.png"), w, h, &reference, 0.0)
                .unwrap();
            crate::image_io::write_png(&dir.join("cornell_relerr.png"), w, h, &err_img, 0.0)
                .unwrap();
        }
        eprintln!(
            "Cornell direct: relative error p50 {:.4}, p90 {:.4}, p95 {:.4} over {} pixels",
            q(50),
            q(90),
            q(95),
            errors.len()
        );
        assert!(q(50) < 0.02, "median relative error {}", q(50));
        assert!(q(90) < 0.15, "90th percentile relative error {}", q(90));
    });
}

#[test]
fn a_tilted_surface_emitter_lights_what_is_in_front_of_it_and_shadows_it() {
    // A surface emitter's cube faces are drawn only where they look in front of it
    // (shadow.rs's `front_part`); tilted, its plane cuts every side face obliquely. Each
    // pixel's direct light against the closed form (Lambertian emitter, cosine at the
    // receiver, inverse square) with a ray-cast shadow: 97% of the covered pixels within 5%
    // (relative, floor 2% of the mean); the rest lie on shadow edges. A face drawn short
    // would leave a lit wedge black.
    on_every_backend(|raster| {
        let scene = lit_scene();
        let tris = scene.triangles_at(0.0);
        let bvh = SceneBvh::build(tris.clone(), BvhKind::default());
        let normal = Vec3::new(0.5, -0.6, 0.4).normalize();
        let position = Vec3::new(-1.2, 1.6, -0.8);
        let intensity = Vec3::new(6.0, 5.0, 4.0);
        let light = cloudlight_scenes::LightState::Surface {
            position,
            normal,
            intensity,
        };
        let camera = scene.cameras[0].camera;
        let (w, h) = (64u32, 64u32);
        let (g, ours) = raster
            .direct(
                &scene,
                &tris,
                &[light],
                &camera,
                w,
                h,
                ShadowSettings::default(),
            )
            .unwrap();
        let covered = g.covered_pixels();
        let expected: Vec<Vec3> = (0..(w * h) as usize)
            .map(|i| {
                if !g.covered(i) {
                    return Vec3::ZERO;
                }
                let (x, n) = (g.position[i].truncate(), g.normal[i]);
                let to = position - x;
                let d2 = to.length_squared();
                let dir = to / d2.sqrt();
                let e = intensity * normal.dot(-dir).max(0.0) * n.dot(dir).max(0.0) / d2;
                let shadowed = bvh.occluded(x + n * 1e-3, dir, d2.sqrt() - 2e-3);
                if shadowed {
                    Vec3::ZERO
                } else {
                    g.albedo[i] / std::f32::consts::PI * e
                }
            })
            .collect();
        let lit = covered
            .iter()
            .filter(|&&i| expected[i].max_element() > 0.0)
            .count();
        let behind = covered.len() - lit;
        assert!(
            lit > covered.len() / 4 && behind > covered.len() / 10,
            "the view shows both sides of the emitter's plane: {lit} lit, {behind} not"
        );
        let (_, errors) = relative_errors(&ours, &expected, &covered);
        let within = errors.iter().filter(|e| **e < 0.05).count();
        eprintln!(
            "tilted emitter: {within} of {} pixels within 5%",
            errors.len()
        );
        assert!(
            within as f32 >= 0.97 * errors.len() as f32,
            "{within} of {} pixels within 5%",
            errors.len()
        );
    });
}

#[test]
fn too_many_lights_is_an_error_not_a_panic() {
    on_every_backend(|raster| {
        let scene = cloudlight_scenes::builtin("cornell").unwrap();
        // 6 views per emitter, 2·n² emitters: one more than the device's layers.
        let max = raster.device.limits().max_texture_array_layers;
        let n = ((max as f32 / 12.0).sqrt().ceil() as u32) + 1;
        let lights = scene.surface_light_samples(0.0, n);
        assert!(lights.len() as u32 * 6 > max);
        let err = raster
            .direct(
                &scene,
                &scene.triangles_at(0.0),
                &lights,
                &scene.cameras[0].camera,
                8,
                8,
                ShadowSettings {
                    size: 16,
                    ..Default::default()
                },
            )
            .unwrap_err();
        assert!(
            matches!(err, RasterError::TooManyShadowViews { .. }),
            "{err}"
        );
        // One view each, but more lights than the direct pass holds.
        let sun = cloudlight_scenes::LightState::Directional {
            direction: Vec3::NEG_Y,
            irradiance: Vec3::ONE,
        };
        let suns = vec![sun; crate::raster::MAX_LIGHTS + 1];
        let render = |lights: &[cloudlight_scenes::LightState]| {
            raster.direct(
                &scene,
                &scene.triangles_at(0.0),
                lights,
                &scene.cameras[0].camera,
                8,
                8,
                ShadowSettings {
                    size: 16,
                    ..Default::default()
                },
            )
        };
        let err = render(&suns).unwrap_err();
        assert!(
            matches!(err, RasterError::TooManyLights { lights, max } if lights == max + 1),
            "{err}"
        );
        render(&suns[1..]).unwrap();
    });
}

#[test]
fn wgpu_validation_errors_are_error_values_and_the_device_keeps_working() {
    on_every_backend(|raster| {
        let bad_texture = || {
            raster.device.create_texture(&wgpu::TextureDescriptor {
                label: Some("zero-sized on purpose"),
                size: wgpu::Extent3d {
                    width: 0,
                    height: 4,
                    depth_or_array_layers: 1,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format: wgpu::TextureFormat::Rgba8Unorm,
                usage: wgpu::TextureUsages::TEXTURE_BINDING,
                view_formats: &[],
            })
        };
        let err = raster
            .checked("a test", || {
                bad_texture();
                Ok(())
            })
            .unwrap_err();
        assert!(
            matches!(&err, RasterError::Wgpu { operation, .. } if operation == "a test"),
            "{err}"
        );
        let err = raster
            .checked("a broken shader", || {
                let _module = raster
                    .device
                    .create_shader_module(wgpu::ShaderModuleDescriptor {
                        label: Some("broken on purpose"),
                        source: wgpu::ShaderSource::Wgsl("fn broken( {".into()),
                    });
                Ok(())
            })
            .unwrap_err();
        assert!(matches!(err, RasterError::Wgpu { .. }), "{err}");
        // An error outside any scope reaches the uncaptured handler (not wgpu's panicking
        // default) and is the next operation's error.
        bad_texture();
        let err = raster
            .gbuffer(
                &cloudlight_scenes::builtin("cornell").unwrap(),
                &[],
                &cloudlight_scenes::builtin("cornell").unwrap().cameras[0].camera,
                4,
                4,
            )
            .unwrap_err();
        assert!(matches!(err, RasterError::Wgpu { .. }), "{err}");
        // Then the device works again.
        let scene = cloudlight_scenes::builtin("cornell").unwrap();
        let g = raster
            .gbuffer(
                &scene,
                &scene.triangles_at(0.0),
                &scene.cameras[0].camera,
                8,
                8,
            )
            .unwrap();
        assert!(g.covered_pixels().len() > 32);
        assert!(matches!(
            FrameRenderer::new(raster, 0, 8, ShadowSettings::default()),
            Err(RasterError::BadSize { .. })
        ));
    });
}

/// One frame of `frame` (no technique, not still) through `camera` under `lights`, every
/// image read back.
fn everything(
    raster: &Raster,
    frame: &mut FrameRenderer,
    camera: cloudlight_scenes::Camera,
    lights: &[cloudlight_scenes::LightState],
) -> FrameImages {
    let inputs = FrameInputs {
        camera,
        lights,
        still: None,
    };
    frame
        .render(
            raster,
            &inputs,
            &mut NoIndirect,
            Readback::Everything,
            false,
        )
        .unwrap()
}

/// `light` with its power multiplied by `k` (its position and direction unchanged).
fn brighter(light: &cloudlight_scenes::LightState, k: f32) -> cloudlight_scenes::LightState {
    use cloudlight_scenes::LightState as L;
    match *light {
        L::Point {
            position,
            intensity,
        } => L::Point {
            position,
            intensity: intensity * k,
        },
        L::Spot {
            position,
            direction,
            cos_cone,
            intensity,
        } => L::Spot {
            position,
            direction,
            cos_cone,
            intensity: intensity * k,
        },
        L::Directional {
            direction,
            irradiance,
        } => L::Directional {
            direction,
            irradiance: irradiance * k,
        },
        L::Surface {
            position,
            normal,
            intensity,
        } => L::Surface {
            position,
            normal,
            intensity: intensity * k,
        },
    }
}

#[test]
fn a_frame_renderer_keeps_its_shadow_maps_until_a_light_moves() {
    // A point (6 views), a spot (1) and the sun (1): rendered once; kept while nothing moves
    // or only the power changes; a moved light re-renders its own views only; new geometry
    // re-renders all. Every frame equals what a fresh renderer draws.
    on_every_backend(|raster| {
        use cloudlight_scenes::LightState;
        let scene = lit_scene();
        let tris = scene.triangles_at(0.0);
        let camera = scene.cameras[0].camera;
        let shadows = ShadowSettings {
            size: 128,
            ..Default::default()
        };
        let mut frame = FrameRenderer::new(raster, 48, 32, shadows).unwrap();
        frame.set_geometry(raster, &scene, &tris).unwrap();
        let render = |frame: &mut FrameRenderer, lights: &[LightState]| {
            everything(raster, frame, camera, lights).direct.unwrap()
        };
        let lights: Vec<LightState> = scene.lights.iter().map(|l| l.at(0.0)).collect();
        let first = render(&mut frame, &lights);
        assert_eq!(frame.shadow_views_rendered(), 8);
        assert_eq!(render(&mut frame, &lights), first);
        assert_eq!(frame.shadow_views_rendered(), 8, "nothing moved");
        let doubled: Vec<LightState> = lights.iter().map(|l| brighter(l, 2.0)).collect();
        let twice = render(&mut frame, &doubled);
        assert_eq!(frame.shadow_views_rendered(), 8, "power is not geometry");
        for (a, b) in twice.iter().zip(&first) {
            assert!((*a - *b * 2.0).abs().max_element() <= 1e-5 * b.max_element().max(1e-3));
        }
        let mut moved = lights.clone();
        let LightState::Point { position, .. } = &mut moved[0] else {
            panic!("the first light is the point light");
        };
        *position += Vec3::new(0.4, 0.0, 0.2);
        let after = render(&mut frame, &moved);
        assert_eq!(
            frame.shadow_views_rendered(),
            14,
            "only the point light's six views"
        );
        let (_, fresh) = raster
            .direct(&scene, &tris, &moved, &camera, 48, 32, shadows)
            .unwrap();
        assert_eq!(after, fresh);
        frame.set_geometry(raster, &scene, &tris).unwrap();
        render(&mut frame, &moved);
        assert_eq!(
            frame.shadow_views_rendered(),
            22,
            "new geometry: every view"
        );
    });
}

#[test]
fn a_technique_pass_builds_its_pipelines_once_per_device() {
    struct Built(u32);
    let raster = Raster::new().expect("an adapter");
    let calls = std::sync::atomic::AtomicU32::new(0);
    let build = |_: &Raster| Built(calls.fetch_add(1, std::sync::atomic::Ordering::SeqCst));
    let a = raster.pipelines_of(build).unwrap();
    let b = raster.pipelines_of(build).unwrap();
    assert!(std::sync::Arc::ptr_eq(&a, &b));
    assert_eq!((a.0, calls.into_inner()), (0, 1));
    // Another device builds its own.
    let other = Raster::new().expect("an adapter");
    assert_eq!(other.pipelines_of(|_| Built(7)).unwrap().0, 7);
}

#[test]
fn the_gbuffer_carries_light_map_uvs_where_the_geometry_has_them() {
    // The Cornell box's light map: its scene carries the unwrapped UVs. Each pixel's UV must
    // be what ray casting interpolates at the same hit (the gather's lookup).
    let cornell = cloudlight_scenes::builtin("cornell").unwrap();
    let lm = crate::lightmap::Lightmap::cached(&cornell, &Default::default()).unwrap();
    let scene = &lm.scene;
    let tris = scene.triangles_at(0.0);
    assert!(
        tris.iter()
            .all(|t| t.lightmap_uv.iter().any(|uv| *uv != Vec2::ZERO))
    );
    let camera = cornell.cameras[0].camera;
    let (w, h) = (64u32, 64u32);
    let bvh = SceneBvh::build(tris.clone(), BvhKind::default());
    let texel = 1.0 / lm.texels.width as f32;
    on_every_backend(|raster| {
        let g = raster.gbuffer(scene, &tris, &camera, w, h).unwrap();
        let (mut both, mut disagree) = (0, 0);
        for (i, d) in pixel_rays(&camera, w, h).into_iter().enumerate() {
            let (Some(hit), Some(uv)) = (
                bvh.closest_hit(camera.position, d, f32::INFINITY),
                g.lightmap_uv_at(i),
            ) else {
                assert_eq!(g.covered(i), g.lightmap_uv_at(i).is_some());
                continue;
            };
            both += 1;
            let tri = &bvh.triangles()[hit.triangle as usize];
            let (u, v) = (hit.uv.x, hit.uv.y);
            let want = tri.lightmap_uv[0] * (1.0 - u - v)
                + tri.lightmap_uv[1] * u
                + tri.lightmap_uv[2] * v;
            // Within a quarter texel, but at silhouettes and chart seams.
            if (uv - want).abs().max_element() > texel * 0.25 {
                disagree += 1;
            }
        }
        eprintln!("light-map UVs: {both} pixels, {disagree} disagree");
        assert!(both > (w * h) as usize * 9 / 10, "only {both} pixels");
        assert!(disagree <= (w * h) as usize / 50, "{disagree} disagree");
        // The original scene has no light-map UVs: covered pixels read None.
        let plain = raster
            .gbuffer(&cornell, &cornell.triangles_at(0.0), &camera, w, h)
            .unwrap();
        let covered = plain.covered_pixels();
        assert!(!covered.is_empty());
        assert!(covered.iter().all(|&i| plain.lightmap_uv_at(i).is_none()));
    });
}

#[test]
fn a_textured_surface_is_drawn_with_its_texels_up_close_and_their_mean_far_away() {
    // A 4×4 texture of 16 greys under an albedo of 0.8, on a 2 m square facing the camera:
    // seen whole (each texel ~16 pixels across), each pixel's albedo is 0.8 times the texel
    // the path tracer reads at its centre (away from texel edges); repeated 64 times across
    // (16 texels to a pixel), it is 0.8 times the texture's mean; an untextured square keeps
    // its material's albedo.
    use cloudlight_scenes::{Camera, Material, Texture, WorldTriangle};
    let texture = Texture {
        width: 4,
        height: 4,
        texels: (0..16).map(|i| Vec3::splat(i as f32 / 15.0)).collect(),
    };
    let mut scene = cloudlight_scenes::builtin("cornell").unwrap();
    scene.materials = vec![
        Material {
            texture: Some(texture.clone()),
            ..Material::diffuse("greys", Vec3::splat(0.8))
        },
        Material::diffuse("plain", Vec3::new(0.1, 0.2, 0.3)),
    ];
    let square = |repeats: f32, material: u32| -> Vec<WorldTriangle> {
        let (v, uv) = (
            [
                Vec3::new(-1.0, -1.0, 0.0),
                Vec3::new(1.0, -1.0, 0.0),
                Vec3::new(1.0, 1.0, 0.0),
                Vec3::new(-1.0, 1.0, 0.0),
            ],
            [
                Vec2::new(0.0, repeats),
                Vec2::new(repeats, repeats),
                Vec2::new(repeats, 0.0),
                Vec2::ZERO,
            ],
        );
        [[0, 1, 2], [0, 2, 3]]
            .map(|k| WorldTriangle {
                v: k.map(|k| v[k]),
                n: [Vec3::Z; 3],
                uv: k.map(|k| uv[k]),
                lightmap_uv: [Vec2::ZERO; 3],
                material,
            })
            .to_vec()
    };
    let camera = Camera {
        position: Vec3::new(0.0, 0.0, 2.0),
        target: Vec3::ZERO,
        up: Vec3::Y,
        fov_y_rad: 60f32.to_radians(),
    };
    let (w, h) = (64u32, 64u32);
    on_every_backend(|raster| {
        let whole = raster
            .gbuffer(&scene, &square(1.0, 0), &camera, w, h)
            .unwrap();
        let bvh = SceneBvh::build(square(1.0, 0), BvhKind::default());
        let (mut checked, mut off) = (0, 0);
        for (i, d) in pixel_rays(&camera, w, h).into_iter().enumerate() {
            let Some(hit) = bvh.closest_hit(camera.position, d, f32::INFINITY) else {
                continue;
            };
            let uv = bvh.hit_uv(&hit);
            let to_edge = (uv * 4.0 - (uv * 4.0).round()).abs().min_element();
            if to_edge < 0.1 {
                continue; // within a tenth of a texel of its edge
            }
            checked += 1;
            let want = 0.8 * texture.sample(uv);
            if (whole.albedo[i] - want).abs().max_element() > 0.01 {
                off += 1;
                eprintln!("pixel {i}: {} vs {want} at uv {uv}", whole.albedo[i]);
            }
        }
        assert!(checked > 1000, "only {checked} pixels checked");
        assert_eq!(off, 0, "{off} of {checked} pixels off their texel");
        let mean = 0.8 * texture.texels.iter().sum::<Vec3>() / 16.0;
        let far = raster
            .gbuffer(&scene, &square(64.0, 0), &camera, w, h)
            .unwrap();
        let plain = raster
            .gbuffer(&scene, &square(1.0, 1), &camera, w, h)
            .unwrap();
        for i in 0..(w * h) as usize {
            if far.position[i].w > 0.5 {
                assert!(
                    (far.albedo[i] - mean).abs().max_element() < 0.05,
                    "pixel {i}: {} vs the mean {mean}",
                    far.albedo[i]
                );
            }
            if plain.position[i].w > 0.5 {
                assert!(
                    (plain.albedo[i] - Vec3::new(0.1, 0.2, 0.3))
                        .abs()
                        .max_element()
                        < 1e-3
                );
            }
        }
    });
}

#[test]
fn a_still_views_jittered_frames_average_each_pixel_over_its_area() {
    // One frame samples each pixel's centre, the path tracer the pixel's area: at edges
    // (silhouettes, shadow borders) they differ by whatever the pixel straddles. The mean of
    // 16 frames jittered over the pixel (`OneFrame::samples`) must come close to the area's
    // mean: at 48², the relMSE against a 256-spp area reference below half the one-frame
    // image's (measured: 0.022 → 0.0032), partly covered pixels seen as such, and the
    // jitter inside the pixel, centre first.
    assert_eq!(pixel_jitter(0), Vec2::ZERO);
    let jitters: Vec<Vec2> = (0..16).map(pixel_jitter).collect();
    assert!(jitters.iter().all(|j| j.abs().max_element() <= 0.5));
    let mean = jitters.iter().sum::<Vec2>() / 16.0;
    assert!(
        mean.abs().max_element() < 0.07,
        "the jitter spreads evenly: mean {mean}"
    );
    on_every_backend(|raster| {
        let scene = lit_scene();
        let tris = scene.triangles_at(0.0);
        let lights: Vec<_> = scene.lights.iter().map(|l| l.at(0.0)).collect();
        let camera = scene.cameras[0].camera;
        let (w, h) = (48u32, 48u32);
        let view = OneFrame::new(&scene, &tris, &lights, &camera, (w, h), Default::default());
        let one = raster.read_frame(&view, &mut NoIndirect).unwrap();
        let still = raster
            .read_frame(&view.with_samples(16), &mut NoIndirect)
            .unwrap();
        let bvh = SceneBvh::build(tris.clone(), BvhKind::default());
        let settings = direct_settings(camera, (w, h), 3);
        let reference = crate::reference::render(&scene, &bvh, settings, 256).direct();
        let mask: Vec<bool> = (0..reference.len())
            .map(|i| one.coverage[i] > 0.0 || still.coverage[i] > 0.0 || reference[i] != Vec3::ZERO)
            .collect();
        let error = |image: &[Vec3]| crate::metrics::compare(image, &reference, &mask, w, h).relmse;
        let (e1, e16) = (error(&one.direct), error(&still.direct));
        eprintln!("relMSE against the area's mean: one frame {e1:.4}, 16 jittered {e16:.4}");
        assert!(e16 < 0.5 * e1, "16 jittered frames {e16} against one {e1}");
        assert!(one.coverage.iter().all(|&c| c == 0.0 || c == 1.0));
        let partly = still
            .coverage
            .iter()
            .filter(|&&c| c > 0.0 && c < 1.0)
            .count();
        assert!(partly > 0, "a silhouette's pixels are partly covered");
    });
}

#[test]
fn a_frame_shows_nothing_where_it_sees_no_surface_whatever_the_frame_before_drew_there() {
    // Full-screen passes load their targets instead of clearing them and the G-buffer pass
    // clears only its positions: a pixel that saw a surface last frame and sees none now
    // must still read back as nothing (G-buffer, direct, indirect, composed), as a fresh
    // renderer draws it.
    on_every_backend(|raster| {
        let scene = lit_scene();
        let tris = scene.triangles_at(0.0);
        let lights: Vec<_> = scene.lights.iter().map(|l| l.at(0.0)).collect();
        // Looking down on the ground and the block: nearly every pixel sees a surface.
        let on_ground = cloudlight_scenes::Camera {
            position: Vec3::new(0.5, 6.0, 0.8),
            target: Vec3::new(0.0, 0.0, 0.0),
            ..scene.cameras[0].camera
        };
        // Looking up from above the ground: only a sliver of the block at the bottom.
        let at_sky = cloudlight_scenes::Camera {
            position: Vec3::new(3.0, 0.5, 3.0),
            target: Vec3::new(3.0, 5.0, 2.0),
            ..on_ground
        };
        let (w, h) = (48u32, 32u32);
        let render = |frame: &mut FrameRenderer, camera| everything(raster, frame, camera, &lights);
        let mut frame = FrameRenderer::new(raster, w, h, ShadowSettings::default()).unwrap();
        frame.set_geometry(raster, &scene, &tris).unwrap();
        let first = render(&mut frame, on_ground);
        let g0 = first.gbuffer.unwrap();
        let seen = g0.covered_pixels().len();
        assert!(
            seen * 20 >= (w * h) as usize * 19,
            "the ground fills the view: {seen}"
        );
        let second = render(&mut frame, at_sky);
        let mut fresh = FrameRenderer::new(raster, w, h, ShadowSettings::default()).unwrap();
        fresh.set_geometry(raster, &scene, &tris).unwrap();
        let alone = render(&mut fresh, at_sky);
        let (g, ga) = (
            second.gbuffer.clone().unwrap(),
            alone.gbuffer.clone().unwrap(),
        );
        let empty = (0..(w * h) as usize).filter(|&i| !g.covered(i)).count();
        assert!(
            empty > (w * h) as usize / 2,
            "the sky fills most of the view: {empty}"
        );
        let differ = |a: &[Vec3], b: &[Vec3]| a.iter().zip(b).filter(|(x, y)| x != y).count();
        let images = |f: &FrameImages| {
            [&f.direct, &f.indirect, &f.composed].map(|i| i.clone().unwrap_or_default())
        };
        assert_eq!(g.position, ga.position);
        for (name, a, b) in [
            ("normal", &g.normal, &ga.normal),
            ("albedo", &g.albedo, &ga.albedo),
        ] {
            assert_eq!(differ(a, b), 0, "{name}: pixels unlike a fresh renderer's");
        }
        for (name, (a, b)) in ["direct", "indirect", "composed"]
            .iter()
            .zip(images(&second).iter().zip(&images(&alone)))
        {
            assert!(!a.is_empty(), "{name} read back");
            assert_eq!(differ(a, b), 0, "{name}: pixels unlike a fresh renderer's");
        }
        for i in (0..(w * h) as usize).filter(|&i| !g.covered(i)) {
            assert_eq!(g.normal[i], Vec3::ZERO);
            assert_eq!(second.direct.as_ref().unwrap()[i], Vec3::ZERO);
        }
    });
}
