//! The photon splat: a uniform field gives its irradiance, the client converges toward the
//! path tracer as the budget grows, and extreme photon sets give finite frames — on every
//! backend.

use glam::Vec3;

use super::SplatSettings;
use crate::bvh::{BvhKind, SceneBvh};
use crate::raster::ShadowSettings;
use crate::raster::tests::on_every_backend;

/// Photons on a jittered grid of spacing `h` over the floor (x, z in [−1.5, 1.5]), carrying
/// irradiance (E0, E0/2, E0/4) downwards, each with a twin travelling up (away from it).
fn uniform_field(e0: f32, h: f32) -> Vec<crate::photon::Photon> {
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
                    receive: Default::default(),
                });
            }
        }
    }
    photons
}

/// A scene of flat quads (each counter-clockwise seen from the front) of albedo 0.5, without
/// lights.
fn quads(name: &str, quads: &[[Vec3; 4]]) -> cloudlight_scenes::Scene {
    let mut mesh = cloudlight_scenes::Mesh::default();
    for [a, b, c, d] in quads {
        mesh.push_quad(*a, *b, *c, *d);
    }
    cloudlight_scenes::Scene {
        name: name.into(),
        materials: vec![cloudlight_scenes::Material::diffuse(name, Vec3::splat(0.5))],
        objects: vec![cloudlight_scenes::Object {
            name: name.into(),
            mesh,
            material: 0,
            motion: cloudlight_scenes::Motion::identity(),
        }],
        lights: Vec::new(),
        cameras: Vec::new(),
    }
}

/// A floor 4 m square at y = 0, facing up.
fn floor() -> cloudlight_scenes::Scene {
    let (a, b) = (Vec3::new(-2.0, 0.0, -2.0), Vec3::new(2.0, 0.0, 2.0));
    quads(
        "floor",
        &[[a, Vec3::new(a.x, 0.0, b.z), b, Vec3::new(b.x, 0.0, a.z)]],
    )
}

/// The photon client's frame of `photons` alone (no direct light, default shadows).
#[allow(clippy::too_many_arguments)]
fn unlit_frame(
    raster: &crate::raster::Raster,
    scene: &cloudlight_scenes::Scene,
    tris: &[cloudlight_scenes::WorldTriangle],
    camera: &cloudlight_scenes::Camera,
    (width, height): (u32, u32),
    photons: &[crate::photon::Photon],
    splat: SplatSettings,
) -> super::PhotonFrame {
    super::photon_frame(
        raster,
        scene,
        tris,
        &[],
        camera,
        width,
        height,
        ShadowSettings::default(),
        photons,
        splat,
    )
    .unwrap()
}

#[test]
fn no_light_rounds_a_convex_edge_onto_a_surface_facing_elsewhere() {
    // A platform's top (y = 0, facing up) and its front face (z = 0, facing the camera),
    // photons on the top within 10 cm of the edge, travelling down and away from the
    // front face, disks of 40 cm. Carrying the top's normal, they light the top and not
    // the face (its normal is 90° from theirs); carrying their travel direction, the
    // face's points within the flatten distance receive them too: the leak that lit the
    // dungeon's platform sides and the city's walls.
    use crate::photon::Receive;
    on_every_backend(|raster| {
        let scene = quads(
            "platform",
            &[
                [
                    Vec3::new(-1.0, 0.0, -1.0),
                    Vec3::new(-1.0, 0.0, 0.0),
                    Vec3::new(1.0, 0.0, 0.0),
                    Vec3::new(1.0, 0.0, -1.0),
                ],
                [
                    Vec3::new(-1.0, -1.0, 0.0),
                    Vec3::new(1.0, -1.0, 0.0),
                    Vec3::new(1.0, 0.0, 0.0),
                    Vec3::new(-1.0, 0.0, 0.0),
                ],
            ],
        );
        let tris = scene.triangles_at(0.0);
        let camera = cloudlight_scenes::Camera {
            position: Vec3::new(0.0, 0.8, 2.0),
            target: Vec3::new(0.0, -0.2, 0.0),
            up: Vec3::Y,
            fov_y_rad: 1.0,
        };
        let (w, h) = (96u32, 96u32);
        let lit = |receive| {
            let photons: Vec<_> = (0..40)
                .flat_map(|i| (0..4).map(move |j| (i, j)))
                .map(|(i, j)| crate::photon::Photon {
                    position: Vec3::new(-0.8 + 0.04 * i as f32, 0.0, -0.02 - 0.025 * j as f32),
                    direction: match receive {
                        Receive::Normal => Vec3::NEG_Y,
                        Receive::Direction => Vec3::new(0.0, -1.0, -1.0).normalize(),
                    },
                    power: Vec3::splat(0.01),
                    radius: 0.4,
                    receive,
                })
                .collect();
            let frame = unlit_frame(
                raster,
                &scene,
                &tris,
                &camera,
                (w, h),
                &photons,
                SplatSettings::default(),
            );
            // Mean indirect luminance of the pixels seeing the top and of those seeing the
            // face (by their normal).
            let mut sums = [(0.0f32, 0u32); 2];
            for i in frame.gbuffer.covered_pixels() {
                let face = usize::from(frame.gbuffer.normal[i].z > 0.9);
                sums[face].0 += frame.indirect[i].element_sum();
                sums[face].1 += 1;
            }
            assert!(
                sums.iter().all(|s| s.1 > 100),
                "both surfaces in view: {sums:?}"
            );
            sums.map(|(sum, n)| sum / n as f32)
        };
        let [top, face] = lit(Receive::Normal);
        assert!(top > 0.0 && face == 0.0, "normal: top {top}, face {face}");
        let [top, face] = lit(Receive::Direction);
        assert!(
            top > 0.0 && face > 0.1 * top,
            "direction: top {top}, face {face}"
        );
    });
}

#[test]
fn a_ledge_a_pixel_high_gets_its_own_light_not_its_neighbours() {
    // Steps seen from above and in front: tops (facing up) 20 cm deep and risers (facing
    // the camera) 3 cm high, about one pixel of a 96² frame, so the level-0 buffer (half the
    // resolution) stands for few of their rows. Red photons lie on the tops, carrying their
    // normal; blue ones on the risers. A riser's pixels must show blue alone, as splatting
    // every photon at full resolution (one level, no downsampling) shows it — without
    // edges, the upsample gives them the tops' red through the bilateral weights.
    use crate::photon::{Photon, Receive};
    on_every_backend(|raster| {
        if !raster.supports_compute() {
            eprintln!("edges need the compute splat: {}", raster.describe());
            return;
        }
        let (steps, rise, depth) = (5, 0.03f32, 0.2f32);
        let mut faces = Vec::new();
        let mut photons = Vec::new();
        let mut rng = crate::sampling::Rng::new(3, 0);
        for k in 0..steps {
            let (y, z0) = (-rise * k as f32, depth * k as f32 - 1.0);
            let z1 = z0 + depth;
            faces.push([
                Vec3::new(-1.0, y, z0),
                Vec3::new(-1.0, y, z1),
                Vec3::new(1.0, y, z1),
                Vec3::new(1.0, y, z0),
            ]);
            faces.push([
                Vec3::new(-1.0, y - rise, z1),
                Vec3::new(1.0, y - rise, z1),
                Vec3::new(1.0, y, z1),
                Vec3::new(-1.0, y, z1),
            ]);
            for _ in 0..400 {
                let x = 2.0 * rng.next_f32() - 1.0;
                photons.push(Photon {
                    position: Vec3::new(x, y, z0 + depth * rng.next_f32()),
                    direction: Vec3::NEG_Y,
                    power: Vec3::new(1e-3, 0.0, 0.0),
                    radius: 0.1,
                    receive: Receive::Normal,
                });
                photons.push(Photon {
                    position: Vec3::new(x, y - rise * rng.next_f32(), z1),
                    direction: Vec3::NEG_Z,
                    power: Vec3::new(0.0, 0.0, 1e-4),
                    radius: 0.1,
                    receive: Receive::Normal,
                });
            }
        }
        let scene = quads("steps", &faces);
        let tris = scene.triangles_at(0.0);
        let camera = cloudlight_scenes::Camera {
            position: Vec3::new(0.0, 0.8, 2.0),
            target: Vec3::new(0.0, -0.2, -0.4),
            up: Vec3::Y,
            fov_y_rad: 1.0,
        };
        let size = (96u32, 96u32);
        let frame = |splat| unlit_frame(raster, &scene, &tris, &camera, size, &photons, splat);
        let exact = frame(SplatSettings {
            downsample: 1,
            levels: 1,
            edges: false,
            ..Default::default()
        });
        let with_edges = frame(SplatSettings {
            edges: true,
            ..Default::default()
        });
        let without = frame(SplatSettings::default());
        // The pixels whose surface faces along `axis` (within 26°).
        let facing = |axis: Vec3| -> Vec<usize> {
            exact
                .gbuffer
                .covered_pixels()
                .into_iter()
                .filter(|&i| exact.gbuffer.normal[i].dot(axis) > 0.9)
                .collect()
        };
        let risers = facing(Vec3::Z);
        assert!(
            risers.len() >= 40,
            "risers in view: {} pixels",
            risers.len()
        );
        let tops_red = {
            let tops = facing(Vec3::Y);
            tops.iter().map(|&i| exact.indirect[i].x).sum::<f32>() / tops.len() as f32
        };
        let riser_sums =
            |f: &super::PhotonFrame| risers.iter().fold(Vec3::ZERO, |a, &i| a + f.indirect[i]);
        let (exact_sum, edges_sum, without_sum) = (
            riser_sums(&exact),
            riser_sums(&with_edges),
            riser_sums(&without),
        );
        let n = risers.len() as f32;
        eprintln!(
            "risers ({n} pixels), mean red / blue: exact {:.3e} / {:.3e}, edges {:.3e} / {:.3e}, \
             without {:.3e} / {:.3e}; tops' red {tops_red:.3e}",
            exact_sum.x / n,
            exact_sum.z / n,
            edges_sum.x / n,
            edges_sum.z / n,
            without_sum.x / n,
            without_sum.z / n
        );
        assert!(tops_red > 0.0 && exact_sum.x == 0.0 && exact_sum.z > 0.0);
        // The risers' pixels that no level stands for take the tops' red without edges...
        assert!(
            without_sum.x / n > 0.05 * tops_red,
            "without edges the risers should borrow red: the test does not see the defect"
        );
        // ... and none with them, their blue as the exact splat's (the few pixels that
        // a level does stand for come through the upsample, within its blur).
        assert!(edges_sum.x / n < 0.01 * tops_red, "red on the risers");
        assert!(
            (edges_sum.z / exact_sum.z - 1.0).abs() < 0.15,
            "blue on the risers: {} against {}",
            edges_sum.z,
            exact_sum.z
        );
    });
}

#[test]
fn splatting_a_uniform_field_gives_its_irradiance() {
    // Photons on a jittered grid over a floor carry a uniform irradiance E0; the splat must
    // return ρ/π·E0 (a kernel/normalisation mismatch — πr² with a cone — is a 3× error).
    // Photons leaving the surface (travelling up) add nothing. At 192² a disk's radius is
    // ~12 px: with levels, photons go to the buffer 4× smaller than the frame (3 texels),
    // which must give the same irradiance.
    on_every_backend(|raster| {
        let scene = floor();
        let tris = scene.triangles_at(0.0);
        assert!(tris[0].n[0].y > 0.9, "floor faces up");
        let camera = cloudlight_scenes::Camera {
            position: Vec3::new(0.0, 1.5, 0.01),
            target: Vec3::ZERO,
            up: Vec3::Y,
            fov_y_rad: 1.0,
        };
        let (e0, h) = (2.0f32, 0.02f32);
        let photons = uniform_field(e0, h);
        let (w, hgt) = (192u32, 192u32);
        let layouts = [
            (1, 1, true),
            (2, 1, true),
            (2, 4, true),
            (1, 4, true),
            (2, 4, false),
        ];
        for (downsample, levels, compute) in layouts {
            let frame = unlit_frame(
                raster,
                &scene,
                &tris,
                &camera,
                (w, hgt),
                &photons,
                SplatSettings {
                    downsample,
                    levels,
                    compute,
                    ..Default::default()
                },
            );
            let expect = Vec3::new(e0, e0 * 0.5, e0 * 0.25) * 0.5 / std::f32::consts::PI;
            let inner: Vec<Vec3> = (24..168)
                .flat_map(|y| (24..168).map(move |x| (y, x)))
                .map(|(y, x)| frame.indirect[(y * w + x) as usize])
                .collect();
            let mean = inner.iter().copied().sum::<Vec3>() / inner.len() as f32;
            assert!(
                ((mean / expect) - Vec3::ONE).abs().max_element() < 0.03,
                "downsample {downsample}, levels {levels}, compute {compute}: mean {mean} vs {expect}"
            );
            for v in &inner {
                assert!(
                    ((*v / expect) - Vec3::ONE).abs().max_element() < 0.15,
                    "downsample {downsample}, levels {levels}, compute {compute}: pixel {v} vs {expect}"
                );
            }
            assert!(frame.direct.iter().all(|d| *d == Vec3::ZERO));
        }
    });
}

/// The Cornell box at time 0 seen by its camera at 64², with the path tracer's indirect
/// image (2048 spp) to compare client frames with.
struct CornellView {
    scene: cloudlight_scenes::Scene,
    tris: Vec<cloudlight_scenes::WorldTriangle>,
    bvh: SceneBvh,
    camera: cloudlight_scenes::Camera,
    reference: Vec<Vec3>,
}

const VIEW: u32 = 64;

impl CornellView {
    fn new() -> Self {
        let scene = cloudlight_scenes::builtin("cornell").unwrap();
        let tris = scene.triangles_at(0.0);
        let bvh = SceneBvh::build(tris.clone(), BvhKind::default());
        let camera = scene.cameras[0].camera;
        let settings = crate::reference::RenderSettings {
            width: VIEW,
            height: VIEW,
            camera,
            time_s: 0.0,
            seed: 21,
            max_bounces: 64,
            pixel: Default::default(),
        };
        let reference = crate::reference::render(&scene, &bvh, settings, 2048).indirect();
        CornellView {
            scene,
            tris,
            bvh,
            camera,
            reference,
        }
    }

    /// The client's indirect image of `photons` and its scale-invariant errors.
    fn errors(
        &self,
        raster: &crate::raster::Raster,
        photons: &[crate::photon::Photon],
    ) -> (crate::metrics::ImageErrors, Vec<Vec3>) {
        self.errors_with(raster, photons, SplatSettings::default())
    }

    /// [`Self::errors`] with `splat` settings.
    fn errors_with(
        &self,
        raster: &crate::raster::Raster,
        photons: &[crate::photon::Photon],
        splat: SplatSettings,
    ) -> (crate::metrics::ImageErrors, Vec<Vec3>) {
        let frame = unlit_frame(
            raster,
            &self.scene,
            &self.tris,
            &self.camera,
            (VIEW, VIEW),
            photons,
            splat,
        );
        assert!(frame.indirect.iter().all(|v| v.is_finite()));
        let mask: Vec<bool> = (0..(VIEW * VIEW) as usize)
            .map(|i| frame.gbuffer.covered(i))
            .collect();
        let e = crate::metrics::compare(&frame.indirect, &self.reference, &mask, VIEW, VIEW);
        (e, frame.indirect)
    }
}

#[test]
fn the_photon_client_converges_toward_the_reference_as_the_budget_grows() {
    // Cornell box, indirect only, 64²: relMSE against the path tracer's indirect image must
    // fall as photons per iteration grow (bias and noise both shrink with the radius), and
    // the energy must match, with either receiving rule. Measured by `bench quality` (128²,
    // 1024 spp), 2.5k / 10k / 40k / 160k photons: 0.107 / 0.079 / 0.056 / 0.043 with one
    // radius per iteration and 40 photons per disk; 0.072 / 0.046 / 0.031 / 0.023 with
    // density radii (160 per disk) and the travel direction; 0.091 / 0.052 / 0.039 with the
    // surface normal (no light rounds the box's edges: its corners get less).
    use crate::photon::{PackFormat, PhotonSettings, Receive, trace_iteration};
    let view = CornellView::new();
    on_every_backend(|raster| {
        // (rule, energy lost at most at 2.5k photons, relMSE at 160k at most)
        for (receive, lost, last) in [
            (Receive::Direction, 0.12, 0.04),
            (Receive::Normal, 0.22, 0.05),
        ] {
            let mut errors = Vec::new();
            for photons in [2_500u64, 10_000, 40_000, 160_000] {
                let s = PhotonSettings {
                    receive,
                    ..PhotonSettings::for_budget(&view.scene, photons, 10_000.min(photons as u32))
                };
                let it = trace_iteration(&view.scene, &view.bvh, 0.0, s, 3, PackFormat::Compact12);
                // The scale-invariant figures (what benchmarks report) and, as before, relMSE
                // with an absolute ε (radiance in watts: it reads ~25× lower).
                let (e, indirect) = view.errors(raster, &it.unpacked());
                let absolute = crate::metrics::relmse(
                    &indirect,
                    &view.reference,
                    crate::metrics::REL_MSE_EPSILON,
                );
                eprintln!(
                    "{receive:?}, {photons} photons: {} stored, radius {:.4} m, relMSE {:.4} (absolute ε: {absolute:.5}), energy {:.3}",
                    it.stored, it.radius, e.relmse, e.energy_ratio
                );
                // Disks that reach past a wall's edge lose the light they would put there
                // (the density radii are twice the old uniform radius on open walls).
                assert!(
                    (e.energy_ratio - 1.0).abs() < lost,
                    "{receive:?}, {photons}: {e:?}"
                );
                errors.push((e.relmse, absolute));
            }
            for pair in errors.windows(2) {
                assert!(
                    pair[1].0 < pair[0].0 && pair[1].1 < pair[0].1,
                    "{receive:?}: relMSE must fall with the budget: {errors:?}"
                );
            }
            assert!(errors[3].1 < 0.004, "{receive:?}: {errors:?}");
            assert!(errors[3].0 < last, "{receive:?}: {errors:?}");
        }
    });
}

#[test]
fn the_compute_splat_draws_what_the_raster_splat_draws() {
    // The same photons through both splats (Cornell box, 10k photons, 64²; one level and
    // four): the compute splat's fixed-point sums (stochastic rounding at 2^-12 of a typical
    // photon's peak) and its texel-centre rule must give the rasterised quads' image, up to
    // the rounding (and, on GL llvmpipe, the raster's half-precision accumulation).
    use crate::photon::{PackFormat, PhotonSettings, trace_iteration};
    let view = CornellView::new();
    // Unmerged: 10k photons, so that the sums' rounding (stochastic, zero-mean) adds up to
    // a small share of the light whichever way the set is chunked.
    let s = PhotonSettings {
        merge: 0.0,
        ..PhotonSettings::for_budget(&view.scene, 10_000, 10_000)
    };
    let photons =
        trace_iteration(&view.scene, &view.bvh, 0.0, s, 3, PackFormat::Compact8).unpacked();
    on_every_backend(|raster| {
        assert!(raster.supports_compute(), "{}", raster.describe());
        // A half-precision raster accumulation loses ~2% of the light here (the compute
        // splat's image is the same on every backend).
        let (within, energy) = if raster.formats().accum_is_half() {
            (1e-3, 0.03)
        } else {
            (1e-5, 1e-3)
        };
        // At 64² every disk spans under 3 texels of the finest level: half a texel puts
        // photons on all four.
        for (levels, min_texels) in [(1, 3.0), (4, 0.5)] {
            // Edges (full-resolution sums where no level stands for a pixel) are the
            // compute splat's alone: off here, where the two are compared.
            let image = |compute| {
                let splat = SplatSettings {
                    levels,
                    min_texels,
                    compute,
                    edges: false,
                    ..Default::default()
                };
                view.errors_with(raster, &photons, splat)
            };
            let ((ec, compute), (er, rasterised)) = (image(true), image(false));
            // The same set in dispatches of 1024 photons, each its own binding range (as
            // a set larger than one storage binding goes).
            let (_, chunked) = view.errors_with(
                raster,
                &photons,
                SplatSettings {
                    levels,
                    min_texels,
                    chunk_photons: Some(1024),
                    edges: false,
                    ..Default::default()
                },
            );
            let all: Vec<bool> = compute.iter().map(|v| v.max_element() > 0.0).collect();
            let split = crate::metrics::compare(&chunked, &compute, &all, VIEW, VIEW);
            assert!(split.relmse < 1e-6, "chunks of 1024: {split:?}");
            assert!((split.energy_ratio - 1.0).abs() < 1e-4, "{split:?}");
            let mask: Vec<bool> = rasterised.iter().map(|v| v.max_element() > 0.0).collect();
            let between = crate::metrics::compare(&compute, &rasterised, &mask, VIEW, VIEW);
            eprintln!(
                "levels {levels}: compute relMSE {:.5}, raster {:.5}; between them {:.2e}, energy {:.5}",
                ec.relmse, er.relmse, between.relmse, between.energy_ratio
            );
            assert!(between.relmse < within, "levels {levels}: {between:?}");
            assert!((between.energy_ratio - 1.0).abs() < energy, "{between:?}");
        }
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
            let f = super::photon_frame(
                raster,
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
fn progressive_passes_converge_while_the_light_stands_still() {
    // Cornell box (its light stands still at t = 0), 10k photons an iteration: the client
    // draws a still light's refinement passes together with shrinking radii; its error
    // must fall as passes come and end well below one pass's. Measured (64², 2048 spp,
    // Vulkan/lavapipe, f32 accumulation): relMSE 0.035 / 0.029 / 0.025 / 0.021 / 0.020 at
    // 1 / 2 / 4 / 8 / 16 passes. The compute splat sums in integers; the raster splat into a
    // half-precision buffer (GL llvmpipe) loses light once a pixel sums ~1000 small splats
    // (each below an f16 step of the sum: energy 0.94 / 0.89 / 0.87 at 1 / 4 / 8 passes),
    // so a device without compute shaders is held to the bounds for 4 passes only.
    use crate::photon::stream::{PhotonStream, Retrace};
    use crate::photon::{PackFormat, PhotonSet, PhotonSettings};
    let view = CornellView::new();
    let (scene, bvh) = (&view.scene, &view.bvh);
    on_every_backend(|raster| {
        let photon_settings = PhotonSettings {
            passes: 16,
            ..PhotonSettings::for_budget(scene, 10_000, 10_000)
        };
        let mut stream =
            PhotonStream::new(photon_settings, PackFormat::Compact8, Retrace::Changed, 7);
        let mut set = PhotonSet::new();
        let mut errors = Vec::new();
        let last = if raster.formats().accum_is_half() && !raster.supports_compute() {
            4
        } else {
            16
        };
        for pass in 1..=last {
            let it = stream.iterate(scene, bvh, 0.0);
            for b in &it.batches {
                set.insert(b);
            }
            set.apply_manifest(stream.manifest(0.0));
            let light = *stream.sets().keys().next().unwrap();
            assert_eq!(set.passes_of(light), pass);
            if !pass.is_power_of_two() {
                continue;
            }
            let photons: Vec<_> = set.photons().collect();
            let (e, _) = view.errors(raster, &photons);
            eprintln!(
                "{pass} passes: {} photons, relMSE {:.4}, energy {:.3}",
                photons.len(),
                e.relmse,
                e.energy_ratio
            );
            assert!((e.energy_ratio - 1.0).abs() < 0.12, "{pass}: {e:?}");
            errors.push(e.relmse);
        }
        assert!(
            errors.windows(2).all(|p| p[1] < p[0]),
            "error falls with every doubling of the passes: {errors:?}"
        );
        if last == 16 {
            assert!(errors[4] < errors[0] * 0.7, "{errors:?}");
            // The stream holds 16 passes: it traces nothing more.
            assert!(stream.iterate(scene, bvh, 0.0).batches.is_empty());
        } else {
            assert!(errors[2] < errors[0] * 0.9, "{errors:?}");
        }
    });
}

#[test]
fn a_timed_frame_names_the_splats_steps_and_draws_the_same_image() {
    // `bench client` splits the indirect pass by the steps the pass names: each step is
    // submitted and waited for on its own, which must not change what is drawn; the steps
    // run in order and take no longer, together, than the pass.
    use crate::raster::{FrameInputs, FrameRenderer, Readback};
    on_every_backend(|raster| {
        let scene = floor();
        let tris = scene.triangles_at(0.0);
        let camera = cloudlight_scenes::Camera {
            position: Vec3::new(0.0, 1.5, 1.0),
            target: Vec3::ZERO,
            up: Vec3::Y,
            fov_y_rad: 1.0,
        };
        for settings in [
            SplatSettings::default(),
            SplatSettings {
                edges: true,
                ..Default::default()
            },
            SplatSettings {
                compute: false,
                ..Default::default()
            },
        ] {
            let mut pass = super::PhotonSplatPass::new(raster, settings).unwrap();
            pass.set_photons(raster, &uniform_field(2.0, 0.02)).unwrap();
            let mut frame = FrameRenderer::new(raster, 96, 64, ShadowSettings::default()).unwrap();
            frame.set_geometry(raster, &scene, &tris).unwrap();
            let inputs = FrameInputs {
                camera,
                lights: &[],
                still: None,
            };
            let mut render = |timed| {
                frame
                    .render(raster, &inputs, &mut pass, Readback::Everything, timed)
                    .unwrap()
            };
            let whole = render(false);
            let split = render(true);
            assert!(whole.times.indirect_steps.is_empty(), "{settings:?}");
            let names: Vec<&str> = split.times.indirect_steps.iter().map(|s| s.0).collect();
            let expected: &[&str] = if settings.edges {
                &["guides", "edges", "splat", "resolve", "upsample"]
            } else {
                &["guides", "splat", "resolve", "upsample"]
            };
            assert_eq!(names, expected, "{settings:?}");
            let sum: std::time::Duration = split.times.indirect_steps.iter().map(|s| s.1).sum();
            assert!(
                sum <= split.times.indirect,
                "{settings:?}: {sum:?} > {:?}",
                split.times.indirect
            );
            let (lit, again) = (whole.indirect.unwrap(), split.indirect.unwrap());
            assert!(
                lit.iter().any(|p| p.max_element() > 0.0),
                "{settings:?}: unlit"
            );
            assert_eq!(lit, again, "{settings:?}");
        }
    });
}

#[test]
fn merged_photons_draw_the_image_of_the_photons_they_stand_for() {
    // Cornell box, 10k photons and 4 refinement passes of them drawn together (64²):
    // merging photons within half their radius (the default) splats a fraction of them,
    // keeps the light's energy and moves the image by far less than its own error against
    // the path tracer; a cell of twice the radius moves it more.
    use crate::photon::{PackFormat, PhotonSettings, trace_iteration};
    let view = CornellView::new();
    // The tracer's photons, not merged by the batcher.
    let one = |seed| {
        let s = PhotonSettings {
            merge: 0.0,
            ..PhotonSettings::for_budget(&view.scene, 10_000, 10_000)
        };
        trace_iteration(&view.scene, &view.bvh, 0.0, s, seed, PackFormat::Compact8).unpacked()
    };
    // Four passes as a client draws them: powers divided by 4, radii scaled.
    let scale = crate::photon::progressive_radius_scale(4);
    let four: Vec<_> = (1..=4u64)
        .flat_map(one)
        .map(|p| crate::photon::Photon {
            power: p.power / 4.0,
            radius: p.radius * scale,
            ..p
        })
        .collect();
    on_every_backend(|raster| {
        for (name, photons) in [("one pass", one(3)), ("four passes", four.clone())] {
            let splat = |merge| SplatSettings {
                merge,
                ..Default::default()
            };
            let merged = crate::photon::merge::merge(&photons, 0.5).len();
            let ((plain, unmerged), (e, image)) = (
                view.errors_with(raster, &photons, splat(0.0)),
                view.errors_with(raster, &photons, splat(0.5)),
            );
            let (_, coarse) = view.errors_with(raster, &photons, splat(2.0));
            let mask: Vec<bool> = unmerged.iter().map(|v| v.max_element() > 0.0).collect();
            let moved = crate::metrics::compare(&image, &unmerged, &mask, VIEW, VIEW);
            let moved_coarse = crate::metrics::compare(&coarse, &unmerged, &mask, VIEW, VIEW);
            eprintln!(
                "{name}: {} photons -> {merged}; relMSE {:.4} -> {:.4}; merged against unmerged {:.5} (energy {:.4}), cell 2: {:.5}",
                photons.len(),
                plain.relmse,
                e.relmse,
                moved.relmse,
                moved.energy_ratio,
                moved_coarse.relmse
            );
            assert!(
                merged * 2 < photons.len(),
                "{name}: {merged} of {}",
                photons.len()
            );
            assert!((moved.energy_ratio - 1.0).abs() < 0.01, "{name}: {moved:?}");
            assert!(
                moved.relmse < 0.05 * plain.relmse,
                "{name}: {moved:?} against {plain:?}"
            );
            assert!(
                moved_coarse.relmse > moved.relmse,
                "{name}: {moved_coarse:?}"
            );
            assert!(
                e.relmse < 1.1 * plain.relmse,
                "{name}: {e:?} against {plain:?}"
            );
        }
    });
}
