//! The raster G-buffer agrees with ray casting.

use glam::{Vec2, Vec3};

use super::*;
use crate::bvh::{BvhKind, SceneBvh};

/// Runs `test` on the Vulkan and on the GL adapter, each where it exists: a backend without
/// an adapter (or excluded by `WGPU_BACKEND`) is skipped with a printed reason; no adapter at
/// all fails the test.
fn on_every_backend(test: impl Fn(&Raster)) {
    let mut ran = 0;
    for (name, backend) in [
        ("Vulkan", wgpu::Backends::VULKAN),
        ("GL", wgpu::Backends::GL),
    ] {
        if device::backends(wgpu::Backends::all()) & backend != backend {
            eprintln!("skipped on {name}: WGPU_BACKEND excludes it");
            continue;
        }
        match Raster::with_backends(backend) {
            Ok(raster) => {
                eprintln!("on {name}: {}", raster.describe());
                test(&raster);
                ran += 1;
            }
            Err(e) => eprintln!("skipped on {name}: {e}"),
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
        let aspect = w as f32 / h as f32;
        let (mut both, mut disagree) = (0, 0);
        for y in 0..h {
            for x in 0..w {
                let i = (y * w + x) as usize;
                let ndc = Vec2::new(
                    (x as f32 + 0.5) / w as f32 * 2.0 - 1.0,
                    1.0 - (y as f32 + 0.5) / h as f32 * 2.0,
                );
                let hit = bvh.closest_hit(
                    camera.position,
                    camera.ray_direction(ndc, aspect),
                    f32::INFINITY,
                );
                let drawn = g.position[i].w > 0.5;
                match hit {
                    Some(hit) if drawn => {
                        both += 1;
                        let p = camera.position + camera.ray_direction(ndc, aspect) * hit.t;
                        let tri = &bvh.triangles()[hit.triangle as usize];
                        let albedo = scene.materials[tri.material as usize].albedo;
                        let mut n = bvh.geometric_normal(hit.triangle);
                        if n.dot(camera.ray_direction(ndc, aspect)) > 0.0 {
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
        let settings = crate::reference::RenderSettings {
            width: w,
            height: h,
            camera,
            time_s: 0.0,
            seed: 3,
            max_bounces: 1,
        };
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
        // Every light alone: its direct light's mean over the covered pixels within 5% of
        // the path tracer's (catches a light kind that a backend loses altogether).
        for light in &scene.lights {
            let mut alone = scene.clone();
            alone.lights.retain(|l| l.name == light.name);
            let states: Vec<_> = alone.lights.iter().map(|l| l.at(0.0)).collect();
            let (_, ours) = raster
                .direct(
                    &alone,
                    bvh.triangles(),
                    &states,
                    &camera,
                    w,
                    h,
                    ShadowSettings::default(),
                )
                .unwrap();
            let traced = crate::reference::render(&alone, &bvh, settings, 4).direct();
            let mean = |img: &[Vec3]| covered.iter().map(|&i| img[i].element_sum()).sum::<f32>();
            let ratio = mean(&ours) / mean(&traced);
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
        let settings = crate::reference::RenderSettings {
            width: w,
            height: h,
            camera,
            time_s: 0.0,
            seed: 5,
            max_bounces: 1,
        };
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
    });
}

#[test]
fn splatting_a_uniform_field_gives_its_irradiance() {
    // Photons on a jittered grid over a floor carry a uniform irradiance E0; the splat must
    // return ρ/π·E0 (a kernel/normalisation mismatch — πr² with a cone — is a 3× error).
    // Photons leaving the surface (travelling up) add nothing.
    on_every_backend(|raster| {
        let mut mesh = cloudlight_scenes::Mesh::default();
        let (a, b) = (Vec3::new(-2.0, 0.0, -2.0), Vec3::new(2.0, 0.0, 2.0));
        mesh.push_quad(a, Vec3::new(a.x, 0.0, b.z), b, Vec3::new(b.x, 0.0, a.z));
        let scene = cloudlight_scenes::Scene {
            name: "floor".into(),
            materials: vec![cloudlight_scenes::Material::diffuse(
                "floor",
                Vec3::splat(0.5),
            )],
            objects: vec![cloudlight_scenes::Object {
                name: "floor".into(),
                mesh,
                material: 0,
                motion: cloudlight_scenes::Motion::identity(),
            }],
            lights: Vec::new(),
            cameras: Vec::new(),
        };
        let tris = scene.triangles_at(0.0);
        assert!(tris[0].n[0].y > 0.9, "floor faces up");
        let camera = cloudlight_scenes::Camera {
            position: Vec3::new(0.0, 1.5, 0.01),
            target: Vec3::ZERO,
            up: Vec3::Y,
            fov_y_rad: 1.0,
        };
        let (e0, h) = (2.0f32, 0.02f32);
        let mut rng = crate::sampling::Rng::new(1, 0);
        let mut photons = Vec::new();
        for i in 0..150 {
            for j in 0..150 {
                let x = -1.5 + (i as f32 + rng.next_f32()) * h;
                let z = -1.5 + (j as f32 + rng.next_f32()) * h;
                for up in [false, true] {
                    photons.push(crate::photon::Photon {
                        position: Vec3::new(x, 0.0, z),
                        direction: if up { Vec3::Y } else { Vec3::NEG_Y },
                        power: Vec3::new(e0, e0 * 0.5, e0 * 0.25) * h * h,
                        radius: 0.1,
                    });
                }
            }
        }
        let (w, hgt) = (64u32, 64u32);
        for downsample in [1, 2] {
            let frame = raster
                .photon_frame(
                    &scene,
                    &tris,
                    &[],
                    &camera,
                    w,
                    hgt,
                    ShadowSettings::default(),
                    &photons,
                    SplatSettings {
                        downsample,
                        ..Default::default()
                    },
                )
                .unwrap();
            let expect = Vec3::new(e0, e0 * 0.5, e0 * 0.25) * 0.5 / std::f32::consts::PI;
            let inner: Vec<Vec3> = (8..56)
                .flat_map(|y| (8..56).map(move |x| (y, x)))
                .map(|(y, x)| frame.indirect[(y * w + x) as usize])
                .collect();
            let mean = inner.iter().copied().sum::<Vec3>() / inner.len() as f32;
            assert!(
                ((mean / expect) - Vec3::ONE).abs().max_element() < 0.03,
                "downsample {downsample}: mean {mean} vs {expect}"
            );
            for v in &inner {
                assert!(
                    ((*v / expect) - Vec3::ONE).abs().max_element() < 0.15,
                    "downsample {downsample}: pixel {v} vs {expect}"
                );
            }
            assert!(frame.direct.iter().all(|d| *d == Vec3::ZERO));
        }
    });
}

#[test]
fn the_photon_client_converges_toward_the_reference_as_the_budget_grows() {
    // Cornell box, indirect only, 64²: relMSE against the path tracer's indirect image must
    // fall as photons per iteration grow (bias and noise both shrink with the radius), and
    // the energy must match. Measured on the scale-invariant metric (128², 4096 spp):
    // 0.149 / 0.129 / 0.122 / 0.079 for 2.5k / 10k / 40k / 160k photons.
    use crate::photon::{PackFormat, PhotonSettings, trace_iteration};
    on_every_backend(|raster| {
        let scene = cloudlight_scenes::builtin("cornell").unwrap();
        let tris = scene.triangles_at(0.0);
        let bvh = SceneBvh::build(tris.clone(), BvhKind::default());
        let camera = scene.cameras[0].camera;
        let (w, h) = (64u32, 64u32);
        let settings = crate::reference::RenderSettings {
            width: w,
            height: h,
            camera,
            time_s: 0.0,
            seed: 21,
            max_bounces: 64,
        };
        let reference = crate::reference::render(&scene, &bvh, settings, 2048).indirect();
        let mut errors = Vec::new();
        for photons in [2_500u64, 10_000, 40_000, 160_000] {
            let s = PhotonSettings::for_budget(&scene, photons, 10_000.min(photons as u32));
            let it = trace_iteration(&scene, &bvh, 0.0, s, 3, PackFormat::Compact12);
            let frame = raster
                .photon_frame(
                    &scene,
                    &tris,
                    &[],
                    &camera,
                    w,
                    h,
                    ShadowSettings::default(),
                    &it.unpacked(),
                    SplatSettings::default(),
                )
                .unwrap();
            assert!(frame.indirect.iter().all(|v| v.is_finite()));
            // The scale-invariant figures (what benchmarks report) and, as before, relMSE
            // with an absolute ε (radiance in watts: it reads ~25× lower).
            let mask: Vec<bool> = (0..(w * h) as usize)
                .map(|i| frame.gbuffer.covered(i))
                .collect();
            let e = crate::metrics::compare(&frame.indirect, &reference, &mask, w, h);
            let absolute = crate::metrics::relmse(
                &frame.indirect,
                &reference,
                crate::metrics::REL_MSE_EPSILON,
            );
            eprintln!(
                "{photons} photons: {} stored, radius {:.4} m, relMSE {:.4} (absolute ε: {absolute:.5}), energy {:.3}",
                it.stored, it.radius, e.relmse, e.energy_ratio
            );
            assert!((e.energy_ratio - 1.0).abs() < 0.1, "{photons}: {e:?}");
            errors.push((e.relmse, absolute));
        }
        for pair in errors.windows(2) {
            assert!(
                pair[1].0 < pair[0].0 && pair[1].1 < pair[0].1,
                "relMSE must fall with the budget: {errors:?}"
            );
        }
        assert!(errors[3].1 < 0.01, "{errors:?}");
        assert!(errors[3].0 < 0.12, "{errors:?}");
    });
}

#[test]
fn extreme_photon_sets_give_finite_frames() {
    // Lights of 1e-6 W and 1e6 W, a scene without lights (no photons), and one photon per
    // batch: the client's frame stays finite and scales with the light.
    use crate::photon::{PackFormat, PhotonSettings, trace_iteration};
    on_every_backend(|raster| {
        let base = cloudlight_scenes::builtin("cornell").unwrap();
        let camera = base.cameras[0].camera;
        let frame = |scene: &cloudlight_scenes::Scene, settings: PhotonSettings| {
            let tris = scene.triangles_at(0.0);
            let bvh = SceneBvh::build(tris.clone(), BvhKind::default());
            let it = trace_iteration(scene, &bvh, 0.0, settings, 1, PackFormat::Compact12);
            let lights = scene.surface_light_samples(0.0, 1);
            let f = raster
                .photon_frame(
                    scene,
                    &tris,
                    &lights,
                    &camera,
                    32,
                    32,
                    ShadowSettings {
                        size: 128,
                        ..Default::default()
                    },
                    &it.unpacked(),
                    SplatSettings::default(),
                )
                .unwrap();
            assert!(
                f.combined()
                    .iter()
                    .all(|v| v.is_finite() && v.min_element() >= 0.0),
                "non-finite or negative pixel"
            );
            f.indirect.iter().copied().sum::<Vec3>().x
        };
        let settings = PhotonSettings::for_budget(&base, 4000, 4000);
        let unit = frame(&base, settings);
        assert!(unit > 0.0);
        for scale in [1e-6f32, 1e6] {
            let mut scene = base.clone();
            for m in &mut scene.materials {
                m.emission *= scale;
            }
            let s = PhotonSettings {
                photons_per_watt: settings.photons_per_watt / scale as f64,
                ..settings
            };
            let sum = frame(&scene, s);
            assert!(
                (sum / (unit * scale) - 1.0).abs() < 0.02,
                "{scale}: {sum} vs {unit}"
            );
        }
        let mut dark = base.clone();
        for m in &mut dark.materials {
            m.emission = Vec3::ZERO;
        }
        assert_eq!(frame(&dark, settings), 0.0);
        let one = PhotonSettings {
            batch_size: 1,
            photons_per_watt: settings.photons_per_watt / 4000.0,
            ..settings
        };
        assert!(frame(&base, one).is_finite());
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
        let mut render = |frame: &mut FrameRenderer, lights: &[LightState]| {
            let inputs = FrameInputs { camera, lights };
            let images = frame
                .render(
                    raster,
                    &inputs,
                    &mut NoIndirect,
                    Readback::Everything,
                    false,
                )
                .unwrap();
            images.direct.unwrap()
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
