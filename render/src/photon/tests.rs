//! Checks of photon tracing, batching, packing and the client's photon set.

use cloudlight_scenes::{Light, LightKind, Material, Mesh, Motion, Object, Scene};
use glam::Vec3;

use super::pack::BatchHeader;
use super::store::Inserted;
use super::*;
use crate::bvh::BvhKind;
use crate::sampling::Rng;

/// A closed unit cube of albedo `a` (inside faces) with a point light of `watts` per
/// channel at its centre.
fn closed_box(a: f32, watts: f32) -> Scene {
    let mut mesh = Mesh::default();
    mesh.push_box(Vec3::ZERO, Vec3::ONE);
    Scene {
        name: "closed box".into(),
        materials: vec![Material::diffuse("wall", Vec3::splat(a))],
        objects: vec![Object {
            name: "box".into(),
            mesh: mesh.flipped(),
            material: 0,
            motion: Motion::identity(),
        }],
        lights: vec![Light {
            name: "bulb".into(),
            kind: LightKind::Point,
            power_w: Vec3::splat(watts),
            motion: Motion::Static(glam::Affine3A::from_translation(Vec3::splat(0.5))),
            sun_path: None,
        }],
        cameras: Vec::new(),
    }
}

/// Traces one whole iteration; returns (photons, plan, radius).
fn iteration(scene: &Scene, settings: PhotonSettings, seed: u64) -> (Vec<Photon>, BatchPlan) {
    let bvh = SceneBvh::at(scene, 0.0, BvhKind::default());
    let lights = photon_lights(scene, 0.0);
    let plan = BatchPlan::new(&lights, &settings);
    let tracer = PhotonTracer::new(scene, &bvh, settings, &plan, seed);
    let mut out = Vec::new();
    for l in &lights {
        let slots = plan.batches_of(l.id);
        for s in 0..slots {
            out.extend(tracer.trace_batch(l, s, slots, 0));
        }
    }
    (out, plan)
}

fn total_power(photons: &[Photon]) -> Vec3 {
    photons.iter().map(|p| p.power).sum()
}

#[test]
fn stored_power_is_the_emitted_power_times_the_bounce_albedo() {
    // Closed box: every photon hits a wall; the power reaching hit k ≥ 2 is Φ·a^(k−1), and
    // hits 2 ..= bounces + 1 are stored: Σ_{k=1}^{B} Φ·a^k.
    let (a, watts, bounces) = (0.5f32, 2.0f32, 10u32);
    let scene = closed_box(a, watts);
    let settings = PhotonSettings {
        photons_per_watt: 200_000.0 / (3.0 * watts as f64),
        batch_size: 50_000,
        bounces,
        ..Default::default()
    };
    let (photons, plan) = iteration(&scene, settings, 3);
    assert_eq!(
        plan.batches,
        vec![LightBatches {
            id: 0,
            batches: 4,
            photons: 50_000
        }]
    );
    let expect: f32 = (1..=bounces).map(|k| watts * a.powi(k as i32)).sum();
    let got = total_power(&photons);
    for c in got.to_array() {
        assert!(
            (c / expect - 1.0).abs() < 0.02,
            "stored {got}, expected {expect}"
        );
    }
    // Double counting guard: nothing is stored at the first hit, so with one bounce the
    // stored power is Φ·a, not Φ·(1 + a).
    let one = PhotonSettings {
        bounces: 1,
        ..settings
    };
    let got = total_power(&iteration(&scene, one, 3).0).x;
    assert!((got / (watts * a) - 1.0).abs() < 0.02, "{got}");
    // Every photon lies on the box and travels into a wall.
    for p in photons.iter().take(5000) {
        let d = p.position.min(Vec3::ONE - p.position).min_element();
        assert!(d.abs() < 1e-3, "{}", p.position);
        assert!(p.power.is_finite() && p.radius > 0.0);
    }
}

#[test]
fn an_iteration_counts_the_photons_each_light_stored_per_photon_emitted() {
    // Closed box: every path goes on until roulette ends it (survival a) or it reaches the
    // bounce cap, and is stored at hits 2 ..= bounces + 1: Σ_{k=1}^{B} a^k per emitted.
    let (a, bounces) = (0.6f32, 8u32);
    let scene = closed_box(a, 1.0);
    let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
    let settings = PhotonSettings {
        bounces,
        ..PhotonSettings::for_budget(&scene, 40_000, 10_000)
    };
    let it = stream::trace_iteration(&scene, &bvh, 0.0, settings, 5, PackFormat::Compact12);
    assert_eq!(it.lights.len(), 1);
    let bulb = &it.lights[0];
    assert_eq!((bulb.name.as_str(), bulb.kind.as_str()), ("bulb", "point"));
    assert_eq!(bulb.emitted, it.plan.total_photons());
    assert_eq!(bulb.stored, it.stored as u64);
    let expect: f64 = (1..=bounces).map(|k| f64::from(a).powi(k as i32)).sum();
    let got = bulb.stored_per_emitted();
    assert!((got / expect - 1.0).abs() < 0.03, "{got} vs {expect}");
}

#[test]
fn each_light_budget_follows_its_power_and_batches_are_deterministic() {
    let scene = cloudlight_scenes::builtin("city:2000").unwrap();
    let mut lights = photon_lights(&scene, 0.0);
    assert!(lights.len() >= 5, "{} lights", lights.len());
    // A light with a negligible share: no batch at all, rather than a whole one.
    let mut faint = lights[1].clone();
    faint.id = 999;
    faint.power_w *= 1e-9;
    lights.push(faint);
    let settings = PhotonSettings {
        photons_per_watt: 0.05,
        batch_size: 1000,
        ..Default::default()
    };
    let plan = BatchPlan::new(&lights, &settings);
    assert_eq!(plan.batches.len(), lights.len() - 1);
    assert_eq!(plan.batches_of(999), 0);
    for (l, b) in lights.iter().zip(&plan.batches) {
        assert_eq!(l.id, b.id);
        let want = (l.watts() * 0.05).round() as u64;
        assert!(
            b.batches >= 1 && b.photons >= 1 && b.photons <= 1000,
            "{b:?}"
        );
        assert_eq!(b.batches as u64, want.div_ceil(1000), "{}", l.name);
        // Split evenly: the light's photons within half a photon per batch.
        let got = plan.photons_of(l.id);
        assert!(
            got.abs_diff(want) <= b.batches as u64,
            "{}: {got} vs {want}",
            l.name
        );
    }
    // The street lamps' few watts buy a proportionate batch, far below a whole one.
    let lamp = lights.iter().find(|l| l.name.starts_with("lamp")).unwrap();
    assert!(plan.photons_per_batch(lamp.id) < 100, "{plan:?}");
    let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
    let tracer = PhotonTracer::new(&scene, &bvh, settings, &plan, 11);
    let a = tracer.trace_batch(&lights[0], 0, 2, 5);
    let b = tracer.trace_batch(&lights[0], 0, 2, 5);
    let c = tracer.trace_batch(&lights[0], 1, 2, 5);
    assert_eq!(a, b);
    assert_ne!(a, c);
    assert!(
        tracer
            .trace_batch(&lights[lights.len() - 1], 0, 1, 5)
            .is_empty()
    );
}

#[test]
fn density_radii_are_smaller_in_a_dense_corner_than_on_open_walls() {
    // A closed unit box with its lamp near one corner: photons crowd into that corner (its
    // three walls face each other a few centimetres away) and thin out on the far walls.
    // The corner's disks must be the smaller; the Cornell box's radii stay in their range.
    let mut scene = closed_box(0.7, 1.0);
    scene.lights[0].motion = Motion::Static(glam::Affine3A::from_translation(Vec3::splat(0.12)));
    let settings = PhotonSettings::for_budget(&scene, 40_000, 10_000);
    let (photons, _) = iteration(&scene, settings, 5);
    let mean = |f: &dyn Fn(Vec3) -> bool| -> (f32, usize) {
        let r: Vec<f32> = photons
            .iter()
            .filter(|p| f(p.position))
            .map(|p| p.radius)
            .collect();
        (r.iter().sum::<f32>() / r.len().max(1) as f32, r.len())
    };
    let (corner, n_corner) = mean(&|x| x.max_element() < 0.15);
    // The middles of the three far walls.
    let (open, n_open) = mean(&|x| {
        x.max_element() > 0.99
            && x.to_array()
                .iter()
                .filter(|c| (**c - 0.5).abs() < 0.25)
                .count()
                == 2
    });
    eprintln!("corner {corner} m ({n_corner}), far walls {open} m ({n_open})");
    assert!(n_corner > 200 && n_open > 200, "{n_corner} {n_open}");
    assert!(
        corner < 0.6 * open,
        "the lamp's corner {corner} m vs the far walls {open} m"
    );

    let scene = cloudlight_scenes::builtin("cornell").unwrap();
    let settings = PhotonSettings::for_budget(&scene, 40_000, 10_000);
    let (photons, plan) = iteration(&scene, settings, 5);
    let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
    let reference = PhotonTracer::new(&scene, &bvh, settings, &plan, 5).radius();
    let (lo_r, hi_r) = DENSITY_RADIUS_RANGE;
    let (smallest, largest) = photons.iter().fold((f32::MAX, 0.0f32), |(a, b), p| {
        (a.min(p.radius), b.max(p.radius))
    });
    assert!(smallest >= reference * lo_r * 0.999 && largest <= reference * hi_r * 1.001);
    assert!(
        smallest < 0.7 * largest,
        "the radii adapt: {smallest} to {largest} m"
    );
    // Without density radii every photon has the reference radius.
    let uniform = PhotonSettings {
        density_radius: false,
        ..settings
    };
    let (photons, _) = iteration(&scene, uniform, 5);
    assert!(photons.iter().all(|p| p.radius == reference));
}

/// A 1 m cube at the origin and a 1 cm one 30 m away (bounds of ~50 m), lit by a sun
/// travelling along `direction` with 1000 W/m² per channel.
fn small_scene_in_large_bounds(direction: Vec3) -> Scene {
    let mut near = Mesh::default();
    near.push_box(Vec3::ZERO, Vec3::ONE);
    let mut far = Mesh::default();
    far.push_box(Vec3::splat(30.0), Vec3::splat(30.01));
    let object = |name: &str, mesh: Mesh| Object {
        name: name.into(),
        mesh,
        material: 0,
        motion: Motion::identity(),
    };
    Scene {
        name: "small scene, large bounds".into(),
        materials: vec![Material::diffuse("grey", Vec3::splat(0.5))],
        objects: vec![object("cube", near), object("speck", far)],
        lights: vec![Light {
            name: "sun".into(),
            kind: LightKind::Directional {
                irradiance_w_m2: Vec3::splat(1000.0),
            },
            power_w: Vec3::ZERO,
            motion: Motion::identity(),
            sun_path: Some(cloudlight_scenes::SunPath::fixed(direction)),
        }],
        cameras: Vec::new(),
    }
}

#[test]
fn a_sun_spends_its_photons_on_geometry_and_its_power_on_what_it_lights() {
    for direction in [
        Vec3::NEG_Y,
        Vec3::new(0.4, -1.0, 0.7),
        Vec3::new(-1.0, -0.2, 0.1),
    ] {
        let direction = direction.normalize();
        let scene = small_scene_in_large_bounds(direction);
        let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
        let lights = photon_lights(&scene, 0.0);
        assert_eq!(lights.len(), 1);
        let Emitter::Directional(footprint) = &lights[0].emitter else {
            panic!("{:?}", lights[0].emitter);
        };
        // Emitted photons that hit something, and the power they carry.
        let n = 20_000;
        let mut rng = Rng::new(9, 1);
        let per_photon = lights[0].power_w.x / n as f32;
        let mut hits = 0;
        for _ in 0..n {
            let (o, d) = emit_uniform(&lights[0].emitter, &mut rng, 1e-4).unwrap();
            assert!((d - direction).length() < 1e-5);
            hits += bvh.closest_hit(o, d, f32::INFINITY).is_some() as u32;
        }
        let share = hits as f32 / n as f32;
        eprintln!("{direction}: {share} of the photons hit geometry");
        assert!(
            share >= 0.9,
            "{direction}: {share} of the photons hit geometry"
        );
        // The power reaching the scene is the irradiance times the cubes' shadow area
        // (|dx| + |dy| + |dz| m² for a unit cube), whatever the grid.
        let shadow = 1000.0 * direction.abs().element_sum() * (1.0 + 1e-4);
        let got = hits as f32 * per_photon;
        assert!(
            (got / shadow - 1.0).abs() < 0.02,
            "{direction}: {got} W vs {shadow} W"
        );
        assert!(footprint.area_m2() < 2.0 * direction.abs().element_sum());
    }
    // A sun over no geometry emits nothing.
    let mut empty = small_scene_in_large_bounds(Vec3::NEG_Y);
    empty.objects.clear();
    assert!(photon_lights(&empty, 0.0).is_empty());
}

#[test]
fn the_cornell_box_defaults_match_the_paper_budget() {
    let scene = cloudlight_scenes::builtin("cornell").unwrap();
    let (photons, plan) = iteration(&scene, PhotonSettings::default(), 1);
    assert_eq!(plan.batches.len(), 1);
    // Each light's budget is its watts' share, to the photon: 10k to within 0.1%.
    assert!(
        plan.total_photons().abs_diff(10_000) <= 10,
        "{}",
        plan.total_photons()
    );
    // The paper stores 3.4k of 10k; with more bounces we keep more, but the count must be
    // of that order and the power below the emitted power.
    assert!(
        (2_000..20_000).contains(&photons.len()),
        "{}",
        photons.len()
    );
    let emitted = scene.emitted_power_w();
    let stored = total_power(&photons);
    assert!(
        stored.x < emitted.x * 1.5 && stored.x > 0.0,
        "{stored} vs {emitted}"
    );
}

fn random_photons(n: usize, seed: u64) -> Vec<Photon> {
    let mut rng = Rng::new(seed, 0);
    (0..n)
        .map(|_| Photon {
            position: Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 2.0
                - Vec3::splat(0.3),
            direction: crate::sampling::uniform_sphere(rng.next_f32(), rng.next_f32()),
            power: Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32())
                * 10f32.powf(-3.0 * rng.next_f32())
                * 1e-4,
            radius: 0.02 + 0.03 * rng.next_f32(),
            receive: Default::default(),
        })
        .collect()
}

fn header() -> BatchHeader {
    BatchHeader {
        light: 3,
        slot: 1,
        slots: 4,
        generation: 9,
        pass: 0,
        scene_time_s: 1.25,
        emitted: 1000,
        receive: Default::default(),
    }
}

/// One photon per 5 cm cell of a 28³ grid, jittered ±1 cm around the cell's centre (so a
/// decoded photon, within a few mm of where it was, names its cell: Compact8 reorders).
fn grid_photons(seed: u64) -> Vec<Photon> {
    let mut rng = Rng::new(seed, 0);
    let mut photons = random_photons(28 * 28 * 28, seed);
    for (i, p) in photons.iter_mut().enumerate() {
        let cell = Vec3::new((i % 28) as f32, (i / 28 % 28) as f32, (i / 784) as f32);
        let jitter = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 0.02 - 0.01;
        p.position = (cell + Vec3::splat(0.5)) * 0.05 + jitter - Vec3::splat(0.3);
    }
    photons
}

fn grid_cell(p: Vec3) -> usize {
    let c = ((p + Vec3::splat(0.3)) / 0.05).floor().as_uvec3();
    (c.x + 28 * c.y + 784 * c.z) as usize
}

#[test]
fn packing_round_trips_within_the_stated_bounds() {
    let photons = grid_photons(4);
    // (format, position tolerance per axis (Compact8: per radius, the decoded one), power
    // tolerance as a fraction of the photon's largest channel, degrees, radius bits).
    for (format, pos_tol, power_frac, max_deg, radius_bits) in [
        (PackFormat::Compact12, None, 1.0 / 127.0, 1.0f32, 6u32),
        (PackFormat::Wide20, Some(1e-7), 1.0 / 511.0, 0.06, 8),
        (
            PackFormat::Compact8,
            Some(0.5 / compact8::STEPS_PER_RADIUS),
            2.0 / 63.0,
            8.0,
            5,
        ),
    ] {
        let b = PackedBatch::pack(header(), &photons, format);
        let per = b.bytes_per_photon();
        assert!(
            per <= format.bytes_per_photon() as f64,
            "{format:?}: {per} B"
        );
        if format != PackFormat::Compact8 {
            assert_eq!(b.data.len(), photons.len() * format.bytes_per_photon());
        }
        let back = b.unpack().unwrap();
        assert_eq!(back.len(), photons.len());
        let extent = Vec3::from_array(b.extent);
        let [r0, r1] = b.radius_range;
        let mut worst_deg = 0.0f32;
        let mut seen = vec![false; photons.len()];
        for q in &back {
            let i = grid_cell(q.position);
            assert!(
                !std::mem::replace(&mut seen[i], true),
                "{format:?}: cell twice"
            );
            let p = &photons[i];
            let tol = match pos_tol {
                Some(t) if format == PackFormat::Compact8 => Vec3::splat(t * q.radius + 1e-6),
                Some(t) => Vec3::splat(t + 1e-6),
                None => extent / 65535.0 * 0.5 + Vec3::splat(1e-6),
            };
            assert!(
                ((p.position - q.position).abs() - tol).max_element() <= 0.0,
                "{format:?} position {} vs {}",
                p.position,
                q.position
            );
            let m = p.power.max_element();
            let ptol = m * power_frac + b.power_scale * 2f32.powi(-15);
            assert!(
                (p.power - q.power).abs().max_element() <= ptol * 1.001,
                "{format:?} power {} vs {}",
                p.power,
                q.power
            );
            worst_deg = worst_deg.max(p.direction.angle_between(q.direction).to_degrees());
            let rtol = (r1 / r0).ln() / ((1u32 << radius_bits) - 1) as f32 * 0.5 + 1e-5;
            assert!(
                (q.radius / p.radius).ln().abs() <= rtol,
                "{format:?} radius"
            );
        }
        assert!(worst_deg <= max_deg, "{format:?}: {worst_deg}°");
        // Power is kept in total (Compact8's dithered rounding adds no bias).
        let (sum_p, sum_q) = (total_power(&photons), total_power(&back));
        let drift = ((sum_q - sum_p) / sum_p).abs().max_element();
        assert!(drift < 2e-3, "{format:?}: total power off by {drift}");
        eprintln!(
            "{format:?}: {per:.2} B/photon, worst direction {worst_deg:.2}°, power drift {drift:.1e}"
        );
    }
}

#[test]
fn compact8_codes_each_position_as_finely_as_its_own_radius() {
    // The same photons (a 28³ grid of 5 cm cells) at one radius, then with every other one
    // 16× wider: each comes back within half a cell of its own radius's grid (the wide
    // ones beyond the narrow ones' bound), and the stream is shorter.
    let half_cell = 0.5 / compact8::STEPS_PER_RADIUS;
    let narrow = grid_photons(9)
        .into_iter()
        .map(|p| Photon { radius: 0.01, ..p })
        .collect::<Vec<_>>();
    let mixed: Vec<Photon> = narrow
        .iter()
        .enumerate()
        .map(|(i, p)| Photon {
            radius: if i % 2 == 1 { 0.16 } else { 0.01 },
            ..*p
        })
        .collect();
    let (fine, coarse) = (
        PackedBatch::pack(header(), &narrow, PackFormat::Compact8),
        PackedBatch::pack(header(), &mixed, PackFormat::Compact8),
    );
    let mut widest = [0.0f32; 2];
    for q in coarse.unpack().unwrap() {
        let p = &mixed[grid_cell(q.position)];
        let off = (p.position - q.position).abs().max_element();
        let wide = usize::from(p.radius > 0.1);
        assert!(
            off <= p.radius * half_cell * 1.01 + 1e-6,
            "{} off by {off}",
            p.radius
        );
        widest[wide] = widest[wide].max(off);
    }
    assert!(
        widest[1] > 0.01 * half_cell,
        "wide photons as fine as narrow ones: {widest:?}"
    );
    let (b_fine, b_coarse) = (fine.bytes_per_photon(), coarse.bytes_per_photon());
    eprintln!("{b_fine:.2} → {b_coarse:.2} B/photon; off by at most {widest:?} m");
    // The wide half saves about 4 bits an axis; the radius costs 5 bits more each.
    assert!(b_coarse < b_fine, "{b_fine} → {b_coarse}");
}

#[test]
fn compact8_is_smaller_than_eight_bytes_on_traced_batches_and_keeps_their_power() {
    // Photons as the tracer stores them (on surfaces, density radii) and as the batcher
    // sends them (merged, ~2.8× fewer of varied power): the Cornell box at 2.5k and 10k
    // photons a batch keep their total through the dithered mantissas within four standard
    // deviations of stochastic rounding (a step is at most 2/63 of a photon's largest
    // channel and rounds with a variance of at most step² / 4, so the sum's σ is at most
    // √Σ max² / 63: a few large merged photons hold most of it), and so do photons of equal
    // power (a first bounce), within 1e-3.
    let scene = cloudlight_scenes::builtin("cornell").unwrap();
    let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
    for (photons, merge) in [(2_500u64, 0.0), (10_000, 0.0), (2_500, 0.5), (10_000, 0.5)] {
        let s = PhotonSettings {
            merge,
            ..PhotonSettings::for_budget(&scene, photons, photons as u32)
        };
        // Wide20 keeps positions exact: its photons stand for the tracer's.
        let traced = trace_iteration(&scene, &bvh, 0.0, s, 5, PackFormat::Wide20).unpacked();
        let eight = PackedBatch::pack(header(), &traced, PackFormat::Compact8);
        let b8 = eight.bytes_per_photon();
        let (p, q) = (total_power(&traced), total_power(&eight.unpack().unwrap()));
        let sigma = traced
            .iter()
            .map(|p| f64::from(p.power.max_element()).powi(2))
            .sum::<f64>()
            .sqrt()
            / 63.0;
        let off = (q - p).abs().max_element();
        eprintln!(
            "{photons} photons, merge {merge}: {} sent, {b8:.2} B/photon, power off by {:.1e} \
             of its total, {:.1} σ",
            traced.len(),
            ((q - p) / p).abs().max_element(),
            f64::from(off) / sigma
        );
        assert!(b8 <= 8.0, "{photons}: {b8}");
        assert!(
            f64::from(off) <= 4.0 * sigma,
            "{photons}, merge {merge}: {q} vs {p} (σ {sigma:.1e})"
        );
    }
    let mut equal = random_photons(1000, 8);
    for p in &mut equal {
        p.power = Vec3::new(0.7, 0.55, 0.31) * 1e-3;
    }
    let b = PackedBatch::pack(header(), &equal, PackFormat::Compact8);
    let (sum_p, sum_q) = (total_power(&equal), total_power(&b.unpack().unwrap()));
    assert!(
        ((sum_q - sum_p) / sum_p).abs().max_element() < 1e-3,
        "{sum_q} vs {sum_p}"
    );
}

#[test]
fn garbage_batches_are_rejected_never_panic() {
    for format in [PackFormat::Compact12, PackFormat::Compact8] {
        garbage_is_rejected(format);
    }
}

fn garbage_is_rejected(format: PackFormat) {
    let photons = random_photons(100, 5);
    let good = PackedBatch::pack(header(), &photons, format);
    let mut rng = Rng::new(6, 0);
    // Flipped bits in the data, truncated data, forged headers.
    let mut flipped = good.clone();
    flipped.data[17] ^= 0x10;
    assert_eq!(flipped.unpack(), Err(PackError::Checksum));
    let mut short = good.clone();
    short.data.pop();
    match format {
        // A stream's length varies: the checksum catches a lost byte, and a sender that
        // seals a cut or padded stream is caught by the decoder.
        PackFormat::Compact8 => {
            assert_eq!(short.unpack(), Err(PackError::Checksum));
            short.seal();
            assert!(matches!(short.unpack(), Err(PackError::Stream(_))));
            let mut long = good.clone();
            long.data.push(0);
            long.seal();
            assert!(matches!(long.unpack(), Err(PackError::Stream(_))));
            let mut huge = good.clone();
            huge.data.resize(100 * 25, 0);
            huge.seal();
            assert!(matches!(huge.unpack(), Err(PackError::Length { .. })));
        }
        _ => assert!(matches!(short.unpack(), Err(PackError::Length { .. }))),
    }
    let mut forged = good.clone();
    forged.header.slot = 7;
    assert!(forged.unpack().is_err());
    // Random bytes of the right length, with and without a matching checksum.
    let mut decoded = 0;
    for i in 0..400 {
        let mut b = good.clone();
        for x in &mut b.data {
            *x = rng.next_u64() as u8;
        }
        if i % 2 == 0 {
            assert_eq!(b.unpack(), Err(PackError::Checksum));
        } else {
            // A sender that packs garbage deliberately: decodes to finite photons or errors.
            if i % 4 == 1 {
                b.power_scale = f32::from_bits(rng.next_u64() as u32);
                b.origin[0] = f32::from_bits(rng.next_u64() as u32);
            }
            b.seal();
            if let Ok(photons) = b.unpack() {
                decoded += 1;
                assert!(photons.len() == 100 && photons.iter().all(|p| p.position.is_finite()));
            }
        }
    }
    if format == PackFormat::Compact12 {
        assert!(
            decoded > 0,
            "sealed garbage of a fixed layout decodes to something"
        );
    }
}

#[test]
fn extremes_are_finite() {
    // 1e-6 W and 1e6 W lights: power scales linearly and stays finite through packing.
    let base = closed_box(0.5, 1.0);
    let settings = PhotonSettings {
        photons_per_watt: 2000.0 / 3.0,
        batch_size: 2000,
        ..Default::default()
    };
    let (reference, _) = iteration(&base, settings, 2);
    let ref_power = total_power(&reference).x;
    for watts in [1e-6f32, 1e6] {
        let scene = closed_box(0.5, watts);
        let s = PhotonSettings {
            photons_per_watt: 2000.0 / (3.0 * watts as f64),
            ..settings
        };
        let (photons, plan) = iteration(&scene, s, 2);
        assert_eq!(plan.total_photons(), 2000);
        let p = total_power(&photons).x;
        assert!(((p / watts) / ref_power - 1.0).abs() < 1e-3, "{watts}: {p}");
        let packed = PackedBatch::pack(header(), &photons, PackFormat::Compact12);
        let back = packed.unpack().unwrap();
        let q: f32 = back.iter().map(|p| p.power.x).sum();
        assert!(
            q.is_finite() && ((q / p) - 1.0).abs() < 0.01,
            "{watts}: {q} vs {p}"
        );
    }
    // No lights: nothing to emit, nothing stored.
    let mut dark = base.clone();
    dark.lights.clear();
    let (photons, plan) = iteration(&dark, settings, 2);
    assert!(photons.is_empty() && plan.batches.is_empty());
    // Batch sizes 1 and 1,000,000.
    for batch_size in [1u32, 1_000_000] {
        let s = PhotonSettings {
            photons_per_watt: batch_size as f64 / 3.0,
            batch_size,
            ..settings
        };
        let (photons, plan) = iteration(&base, s, 2);
        assert_eq!(plan.total_photons(), batch_size as u64);
        assert!(
            photons
                .iter()
                .all(|p| p.power.is_finite() && p.position.is_finite())
        );
        let b = PackedBatch::pack(header(), &photons, PackFormat::Compact12);
        assert_eq!(b.unpack().unwrap().len(), photons.len());
    }
    // An empty batch packs and unpacks.
    let empty = PackedBatch::pack(header(), &[], PackFormat::Wide20);
    assert_eq!(empty.unpack().unwrap(), Vec::new());
}

fn batch(light: u32, slot: u32, slots: u32, generation: u64, t: f64) -> PackedBatch {
    pass_batch(light, slot, slots, generation, 0, t)
}

fn pass_batch(
    light: u32,
    slot: u32,
    slots: u32,
    generation: u64,
    pass: u32,
    t: f64,
) -> PackedBatch {
    PackedBatch::pack(
        BatchHeader {
            light,
            slot,
            slots,
            generation,
            pass,
            scene_time_s: t,
            emitted: 10,
            receive: Default::default(),
        },
        &random_photons(10, generation * 100 + pass as u64 * 10 + slot as u64),
        PackFormat::Compact12,
    )
}

#[test]
fn a_set_draws_a_still_lights_passes_together_and_a_change_resets_only_that_light() {
    let mut set = PhotonSet::new();
    let power = |set: &PhotonSet, light: u32| -> f32 {
        // Photons are drawn light by light (10 per batch, 2 batches per pass).
        let all: Vec<Photon> = set.photons().collect();
        let mut out = 0.0;
        let mut k = 0;
        for (l, count) in [(1u32, set.passes_of(1) * 20), (2u32, set.passes_of(2) * 20)] {
            let slice = &all[k..k + count as usize];
            if l == light {
                out = slice.iter().map(|p| p.power.x).sum();
            }
            k += count as usize;
        }
        out
    };
    // Two lights, two slots each; light 1 gets passes 0..3, light 2 passes 0..1.
    for pass in 0..4 {
        for slot in 0..2 {
            set.insert(&pass_batch(1, slot, 2, 1, pass, 0.0));
        }
    }
    for pass in 0..2 {
        for slot in 0..2 {
            set.insert(&pass_batch(2, slot, 2, 1, pass, 0.0));
        }
    }
    assert_eq!((set.passes_of(1), set.passes_of(2)), (4, 2));
    // Each pass carries its light's whole power: drawn together, the power is one pass's
    // on average, and radii shrink by the progressive scale.
    let mean_pass: f32 = (0..4)
        .flat_map(|pass| (0..2).map(move |s| (pass, s)))
        .flat_map(|(pass, s)| pass_batch(1, s, 2, 1, pass, 0.0).unpack().unwrap())
        .map(|p| p.power.x)
        .sum::<f32>()
        / 4.0;
    let drawn = power(&set, 1);
    assert!(
        (drawn / mean_pass - 1.0).abs() < 1e-4,
        "{drawn} vs {mean_pass}"
    );
    let radius_first = pass_batch(1, 0, 2, 1, 0, 0.0).unpack().unwrap()[0].radius;
    let radius_drawn = set.photons().next().unwrap().radius;
    assert!(
        (radius_drawn / radius_first - progressive_radius_scale(4)).abs() < 1e-4,
        "{radius_drawn} vs {radius_first}"
    );
    assert!(progressive_radius_scale(4) < 0.85 && progressive_radius_scale(1) == 1.0);
    // An incomplete pass is not drawn until its last slot arrives.
    set.insert(&pass_batch(2, 0, 2, 1, 2, 0.0));
    assert_eq!(set.passes_of(2), 2);
    set.insert(&pass_batch(2, 1, 2, 1, 2, 0.0));
    assert_eq!(set.passes_of(2), 3);
    // Light 1 moves (generation 2): its refinement passes go at once, its first pass is
    // replaced slot by slot (never dark); light 2 keeps its three passes.
    set.insert(&pass_batch(1, 0, 2, 2, 0, 1.0));
    assert_eq!((set.passes_of(1), set.passes_of(2)), (1, 3));
    assert_eq!(set.photons().count(), 20 + 3 * 20);
    // A late pass of the old generation is stale.
    assert_eq!(set.insert(&pass_batch(1, 0, 2, 1, 3, 0.0)), Inserted::Stale);
    // A manifest listing fewer passes drops the rest.
    set.apply_manifest(Manifest {
        iteration: 9,
        scene_time_s: 1.0,
        lights: vec![
            ManifestLight {
                light: 1,
                generation: 2,
                slots: 2,
                passes: 1,
            },
            ManifestLight {
                light: 2,
                generation: 1,
                slots: 2,
                passes: 2,
            },
        ],
    });
    assert_eq!(set.passes_of(2), 2);
}

fn manifest(iteration: u64, t: f64, lights: &[(u32, u64, u32)]) -> Manifest {
    Manifest {
        iteration,
        scene_time_s: t,
        lights: lights
            .iter()
            .map(|&(light, generation, slots)| ManifestLight {
                light,
                generation,
                slots,
                passes: 1,
            })
            .collect(),
    }
}

#[test]
fn the_set_keeps_the_newest_batch_per_slot() {
    let mut set = PhotonSet::new();
    assert_eq!(set.insert(&batch(0, 0, 2, 1, 0.0)), Inserted::New);
    assert_eq!(set.insert(&batch(0, 1, 2, 1, 0.0)), Inserted::New);
    assert_eq!(set.valid_as_of(), None);
    set.apply_manifest(manifest(1, 0.0, &[(0, 1, 2)]));
    assert_eq!(set.valid_as_of(), Some(0.0));
    assert_eq!(set.photon_count(), 20);
    // The same batch sent again (`resend_s`) changes nothing, not even the set's version.
    let version = set.version();
    assert_eq!(set.insert(&batch(0, 1, 2, 1, 0.0)), Inserted::Replaced);
    assert_eq!(set.version(), version);
    // The light moves: generation 2 replaces slot 0; the set is not complete for the new
    // manifest until slot 1 arrives too.
    assert_eq!(set.insert(&batch(0, 0, 2, 2, 0.5)), Inserted::Replaced);
    set.apply_manifest(manifest(2, 0.5, &[(0, 2, 2)]));
    assert_eq!(set.valid_as_of(), Some(0.0));
    // A late batch of generation 1 is stale.
    assert_eq!(set.insert(&batch(0, 1, 2, 1, 0.0)), Inserted::Stale);
    assert_eq!(set.insert(&batch(0, 1, 2, 2, 0.5)), Inserted::Replaced);
    assert_eq!(set.valid_as_of(), Some(0.5));
    // The light now has one batch: slot 1 goes.
    assert_eq!(set.insert(&batch(0, 0, 1, 3, 0.7)), Inserted::Replaced);
    assert_eq!(set.batch_count(), 1);
    // A second light appears; then the first goes dark (not listed).
    set.insert(&batch(5, 0, 1, 1, 0.8));
    set.apply_manifest(manifest(3, 0.8, &[(0, 3, 1), (5, 1, 1)]));
    assert_eq!(set.valid_as_of(), Some(0.8));
    set.apply_manifest(manifest(4, 0.9, &[(5, 1, 1)]));
    assert_eq!(set.batch_count(), 1);
    assert_eq!(set.valid_as_of(), Some(0.9));
    // An old manifest is ignored; a garbage batch is counted.
    set.apply_manifest(manifest(2, 0.5, &[(0, 2, 2)]));
    assert_eq!(set.batch_count(), 1);
    let mut bad = batch(5, 0, 1, 9, 1.0);
    bad.data[0] ^= 1;
    assert!(matches!(set.insert(&bad), Inserted::Rejected(_)));
    let stats = set.stats();
    assert_eq!((stats.rejected, stats.stale), (1, 1));
}

#[test]
fn a_stream_traces_again_only_the_lights_that_changed() {
    use super::stream::{PhotonStream, Retrace};
    let mut scene = cloudlight_scenes::builtin("cornell").unwrap();
    let lamp = |x: f32| Light {
        name: "lamp".into(),
        kind: LightKind::Point,
        power_w: Vec3::splat(0.5),
        motion: Motion::Static(glam::Affine3A::from_translation(Vec3::new(x, 0.3, 0.3))),
        sun_path: None,
    };
    scene.lights.push(lamp(0.2));
    let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
    let settings = PhotonSettings {
        passes: 3,
        ..PhotonSettings::for_budget(&scene, 4000, 1000)
    };
    let mut stream = PhotonStream::new(settings, PackFormat::Compact12, Retrace::Changed, 3);
    let first = stream.iterate(&scene, &bvh, 0.0);
    assert_eq!(first.batches.len() as u64, first.plan.total_batches());
    assert_eq!(stream.sets().len(), 2);
    // Each light's photons are counted: the lamp and the ceiling's emitter.
    let kinds: Vec<&str> = first.lights.iter().map(|l| l.kind.as_str()).collect();
    assert_eq!(kinds, vec!["point", "surface"]);
    for l in &first.lights {
        assert_eq!(l.emitted, first.plan.photons_of(l.id), "{l:?}");
    }
    let stored: u64 = first.lights.iter().map(|l| l.stored).sum();
    assert_eq!(stored, first.stored as u64);
    assert!(stream.sets().values().all(|s| s.generation == 1));
    // Nothing changed: a refinement pass of every light per iteration (fresh photons, same
    // generation and budget), until each holds `passes`; then nothing is traced.
    for pass in 1..3u32 {
        let refined = stream.iterate(&scene, &bvh, 0.5);
        assert_eq!(refined.batches.len(), first.batches.len());
        assert!(
            refined
                .batches
                .iter()
                .all(|b| b.header.pass == pass && b.header.generation == 1)
        );
        assert_ne!(
            refined.batches[0].data, first.batches[0].data,
            "fresh photons"
        );
    }
    let idle = stream.iterate(&scene, &bvh, 0.5);
    assert!(idle.batches.is_empty());
    assert_eq!(stream.batch_count() as u64, 3 * first.plan.total_batches());
    // The lamp moves: only its batches, at generation 2, pass 0; the other keeps its passes.
    scene.lights[0] = lamp(0.35);
    let moved = stream.iterate(&scene, &bvh, 1.0);
    let lamp_id = 0;
    assert!(!moved.batches.is_empty());
    let traced: Vec<u32> = moved.lights.iter().map(|l| l.id).collect();
    assert_eq!(traced, vec![lamp_id], "only the lamp was traced");
    assert!(
        moved
            .batches
            .iter()
            .all(|b| b.header.light == lamp_id && b.header.generation == 2 && b.header.pass == 0)
    );
    let generations: Vec<(u64, usize)> = stream
        .sets()
        .values()
        .map(|s| (s.generation, s.passes.len()))
        .collect();
    assert_eq!(generations, vec![(2, 1), (1, 3)]);
    let manifest = stream.manifest(1.0);
    assert_eq!(manifest.lights.len(), 2);
    let passes: Vec<u32> = manifest.lights.iter().map(|l| l.passes).collect();
    assert_eq!(passes, vec![1, 3]);
    // Re-sending: nothing is due before the period, everything after it, then not again.
    let now = std::time::Instant::now();
    assert!(
        stream
            .due_for_resend(std::time::Duration::from_secs(60), now)
            .is_empty()
    );
    let later = now + std::time::Duration::from_secs(61);
    let due = stream.due_for_resend(std::time::Duration::from_secs(60), later);
    assert_eq!(due.len(), stream.batch_count());
    assert!(
        stream
            .due_for_resend(std::time::Duration::from_secs(60), later)
            .is_empty()
    );
    // Retrace::Always traces every light every time, with fresh generations.
    let mut always = PhotonStream::new(settings, PackFormat::Compact12, Retrace::Always, 3);
    always.iterate(&scene, &bvh, 0.0);
    let again = always.iterate(&scene, &bvh, 0.0);
    assert_eq!(again.batches.len() as u64, again.plan.total_batches());
    assert!(again.batches.iter().all(|b| b.header.generation == 2));
}

/// Two 1 m cubes 40 m apart (on a floor if `floor`) under a sun along `direction`
/// (1000 W/m² per channel), and a camera 5 m from the far one looking at it.
fn two_cubes_and_a_view(direction: Vec3, floor: bool) -> (Scene, View) {
    let mut scene = small_scene_in_large_bounds(direction);
    let mut far = Mesh::default();
    far.push_box(Vec3::new(40.0, 0.0, 0.0), Vec3::new(41.0, 1.0, 1.0));
    if floor {
        far.push_box(Vec3::new(-5.0, -0.1, -5.0), Vec3::new(46.0, 0.0, 6.0));
    }
    scene.objects[1].mesh = far;
    let view = View {
        camera: cloudlight_scenes::Camera {
            position: Vec3::new(40.5, 3.0, 6.0),
            target: Vec3::new(40.5, 0.5, 0.5),
            up: Vec3::Y,
            fov_y_rad: 0.8,
        },
        aspect: 1.0,
    };
    (scene, view)
}

#[test]
fn a_guided_sun_sends_its_photons_where_clients_look_and_keeps_each_surfaces_power() {
    let direction = Vec3::new(0.3, -1.0, 0.2).normalize();
    let (scene, view) = two_cubes_and_a_view(direction, false);
    let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
    let lights = photon_lights(&scene, 0.0);
    let Emitter::Directional(footprint) = &lights[0].emitter else {
        panic!("{:?}", lights[0].emitter);
    };
    let points = view_points(&bvh, &[view]);
    assert!(points.len() > 60, "{} points", points.len());
    assert!(
        points.iter().all(|p| p.x > 39.0),
        "the view sees the far cube only"
    );
    let share = 0.8;
    let guide = footprint.guide(&points, 2.0, share).expect("a guide");
    // Power reaching each cube, per photon emitted: unguided and guided, and how many
    // guided photons reach the far cube.
    let n = 40_000;
    let per_photon = lights[0].power_w.x / n as f32;
    let mut power = [[0.0f64; 2]; 2];
    let mut far_hits = 0;
    for (g, guide) in [None, Some(&guide)].into_iter().enumerate() {
        let mut rng = Rng::new(11, g as u64);
        for _ in 0..n {
            let (o, d, w) = emit(&lights[0].emitter, guide, &mut rng, 1e-4).unwrap();
            let Some(hit) = bvh.closest_hit(o, d, f32::INFINITY) else {
                continue;
            };
            let far = (o + d * hit.t).x > 20.0;
            power[g][far as usize] += (w * per_photon) as f64;
            if g == 1 && far {
                far_hits += 1;
            }
        }
    }
    // Each cube gets the irradiance times its shadow area, guided or not.
    let shadow = 1000.0 * direction.abs().element_sum() as f64;
    for (g, p) in power.iter().enumerate() {
        for (cube, w) in p.iter().enumerate() {
            assert!(
                (w / shadow - 1.0).abs() < 0.04,
                "guided {g}, cube {cube}: {w} W against {shadow} W"
            );
        }
    }
    // The guide sends `share` of the photons (plus the uniform part's half) to the cube
    // in view: 0.8 + 0.2 / 2 = 90%, against 50% unguided.
    let far_share = far_hits as f64 / n as f64;
    assert!(
        far_share > 0.85,
        "{far_share} of the photons reach the cube in view"
    );
    // Unguided photons on the cube out of view carry 1 / (1 − share) of the power.
    let mut rng = Rng::new(5, 5);
    let weights: Vec<f32> = (0..2000)
        .map(|_| footprint.sample_guided(&guide, rng.next_f32(), rng.next_f32(), rng.next_f32()))
        .filter(|(o, _)| o.x < 20.0)
        .map(|(_, w)| w)
        .collect();
    assert!(!weights.is_empty());
    assert!(
        weights.iter().all(|w| (w - 5.0).abs() < 1e-3),
        "{weights:?}"
    );
    // No point near the footprint, or no share: no guide.
    assert!(footprint.guide(&[Vec3::splat(1e4)], 2.0, share).is_none());
    assert!(footprint.guide(&points, 2.0, 0.0).is_none());
    assert!(footprint.guide(&[], 2.0, share).is_none());
}

#[test]
fn a_stream_guides_toward_views_and_traces_again_only_when_they_move() {
    use super::stream::{PhotonStream, Retrace};
    let (scene, view) = two_cubes_and_a_view(Vec3::NEG_Y, true);
    let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
    let settings = PhotonSettings {
        guide_share: 0.8,
        ..PhotonSettings::for_budget(&scene, 4000, 4000)
    };
    let mut stream = PhotonStream::new(settings, PackFormat::Compact12, Retrace::Changed, 3);
    let far_share = |it: &Iteration| {
        let photons = it.unpacked();
        photons.iter().filter(|p| p.position.x > 20.0).count() as f64 / photons.len() as f64
    };
    let generation = |s: &PhotonStream| s.sets().values().next().unwrap().generation;
    let unguided = stream.iterate(&scene, &bvh, 0.0);
    assert!(far_share(&unguided) < 0.6, "{}", far_share(&unguided));
    // A client's view arrives: the sun is traced again, toward it.
    stream.set_views(vec![view]);
    let guided = stream.iterate(&scene, &bvh, 0.0);
    assert!(!guided.batches.is_empty());
    assert_eq!(generation(&stream), 2);
    assert!(far_share(&guided) > 0.8, "{}", far_share(&guided));
    // Invalid views are ignored; a small move keeps the set.
    let mut nudged = view;
    nudged.camera.position.x += 0.01;
    let mut broken = view;
    broken.camera.fov_y_rad = f32::NAN;
    stream.set_views(vec![nudged, broken]);
    assert_eq!(stream.views().len(), 1);
    assert!(stream.iterate(&scene, &bvh, 0.0).batches.is_empty());
    // Turning to the near cube traces again; so does the client leaving.
    let mut turned = view;
    turned.camera.target = Vec3::new(0.5, 0.5, 0.5);
    stream.set_views(vec![turned]);
    assert!(!stream.iterate(&scene, &bvh, 0.0).batches.is_empty());
    assert_eq!(generation(&stream), 3);
    stream.set_views(Vec::new());
    assert!(!stream.iterate(&scene, &bvh, 0.0).batches.is_empty());
    assert_eq!(generation(&stream), 4);
}

#[test]
fn no_photon_is_stored_behind_an_area_light() {
    // The Cornell box's light hangs 0.8 mm under the ceiling. A photon that slips into that
    // slit bounces between the ceiling and the light's back, stored at every bounce with
    // disks of millimetres (its neighbours are its own bounces): a light's back is its
    // fixture, not a reflector, so it absorbs. Before, 162 of these 418k photons lay in
    // the slit; photons on the light's front (travelling up) are legitimate.
    let scene = cloudlight_scenes::builtin("cornell").unwrap();
    let settings = PhotonSettings {
        receive: Receive::Direction,
        ..PhotonSettings::for_budget(&scene, 400_000, 10_000)
    };
    let (photons, _) = iteration(&scene, settings, 3);
    // The light's box, widened by 1 mm up to the ceiling.
    let (lo, hi) = scene
        .triangles_at(0.0)
        .iter()
        .filter(|t| scene.materials[t.material as usize].emission.max_element() > 0.0)
        .flat_map(|t| t.v)
        .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    let (lo, hi) = (
        lo - Vec3::new(0.0, 1e-5, 0.0),
        hi + Vec3::new(0.0, 1e-3, 0.0),
    );
    let light_y = lo.y;
    let in_box: Vec<&Photon> = photons
        .iter()
        .filter(|p| p.position.cmpge(lo).all() && p.position.cmple(hi).all())
        .collect();
    let on_plane = |p: &&&Photon| p.position.y <= light_y + 2e-5;
    // On the light's front: arrived travelling up. On its back: travelling down.
    let front = in_box
        .iter()
        .filter(on_plane)
        .filter(|p| p.direction.y > 0.0);
    let back = in_box
        .iter()
        .filter(on_plane)
        .filter(|p| p.direction.y < 0.0);
    // On the ceiling over the light: where a photon entering the slit lands first (then
    // it is absorbed); before, ~80 of each were there, bouncing to and fro.
    let ceiling = in_box.iter().filter(|p| !on_plane(p));
    assert!(front.count() > 1000, "photons on the light's front");
    assert_eq!(back.count(), 0, "photons stored on the light's back");
    let ceiling = ceiling.count();
    assert!(ceiling <= 40, "{ceiling} photons stored over the light");
}

#[test]
fn a_suns_first_bounce_stores_the_power_its_hits_reflect_onto_geometry() {
    // A sun over a grey floor with a cube on it, one stored bounce: the stored power must
    // be the sun's power × albedo × the share of cosine bounces from its first hits that
    // reach geometry (the floor's bounces that reach the cube, the cube's that reach the
    // floor), estimated here on its own. A sun's photons skip roulette at the first hit and
    // carry power × albedo: dropping either factor, or roulette's 1/q with it, is 2× off.
    let direction = Vec3::new(0.3, -1.0, 0.2).normalize();
    let mut scene = small_scene_in_large_bounds(direction);
    let mut floor = Mesh::default();
    floor.push_box(Vec3::new(-4.0, -0.1, -4.0), Vec3::new(5.0, 0.0, 5.0));
    scene.objects.truncate(1);
    scene.objects.push(Object {
        name: "floor".into(),
        mesh: floor,
        material: 0,
        motion: Motion::identity(),
    });
    let albedo = 0.5;
    let settings = PhotonSettings {
        bounces: 1,
        density_radius: false,
        ..PhotonSettings::for_budget(&scene, 200_000, 10_000)
    };
    let (photons, _) = iteration(&scene, settings, 4);
    let stored = total_power(&photons).x;
    let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
    let lights = photon_lights(&scene, 0.0);
    let n = 100_000;
    let mut rng = Rng::new(77, 3);
    let mut reflected = 0u32;
    for _ in 0..n {
        let (o, d) = emit_uniform(&lights[0].emitter, &mut rng, 1e-4).unwrap();
        let Some(hit) = bvh.closest_hit(o, d, f32::INFINITY) else {
            continue;
        };
        let mut ng = bvh.geometric_normal(hit.triangle);
        if ng.dot(d) > 0.0 {
            ng = -ng;
        }
        let (t, b) = crate::sampling::basis(ng);
        let l = crate::sampling::cosine_hemisphere(rng.next_f32(), rng.next_f32());
        let bounce = (t * l.x + b * l.y + ng * l.z).normalize();
        let x = o + d * hit.t + ng * 1e-4;
        reflected += bvh.closest_hit(x, bounce, f32::INFINITY).is_some() as u32;
    }
    let expected = lights[0].power_w.x * albedo * reflected as f32 / n as f32;
    assert!(reflected > 2000, "{reflected} bounces reach geometry");
    assert!(
        (stored / expected - 1.0).abs() < 0.05,
        "stored {stored} W against {expected} W"
    );
}

/// The distance from each photon to its nearest neighbour on a surface of the same
/// orientation (brute force; photons carrying their normal).
fn nearest_distances(photons: &[Photon]) -> Vec<f32> {
    photons
        .iter()
        .enumerate()
        .map(|(i, p)| {
            photons
                .iter()
                .enumerate()
                .filter(|(j, q)| *j != i && q.direction.dot(p.direction) > 0.99)
                .map(|(_, q)| (p.position - q.position).length())
                .fold(f32::INFINITY, f32::min)
        })
        .collect()
}

#[test]
fn relaxation_spreads_photons_evenly_on_their_surfaces_and_keeps_their_power() {
    // The Cornell box (its boxes' edges and the walls' corners included): the same photons
    // traced without and with relaxation. Relaxed, each keeps its power and direction and
    // still lies on a surface facing the way it did (most move: those pushed over an edge
    // or into a wall stay); clumps thin out (the closest pairs
    // part: the 5th percentile of the distance to the nearest photon on a surface of the same
    // orientation grows by more than a third — 1.58× at this seed — while the density's
    // shape stays.
    let scene = cloudlight_scenes::builtin("cornell").unwrap();
    let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
    let lights = photon_lights(&scene, 0.0);
    let base = PhotonSettings {
        density_radius: false,
        ..PhotonSettings::for_budget(&scene, 4000, 4000)
    };
    let plan = BatchPlan::new(&lights, &base);
    let trace = |relax: u32| {
        PhotonTracer::new(&scene, &bvh, PhotonSettings { relax, ..base }, &plan, 3)
            .trace_batch(&lights[0], 0, 1, 0)
    };
    let landed = trace(0);
    let relaxed = trace(6);
    // Refinement passes of a still light are left as they land (they converge by number).
    let pass = |relax: u32| {
        PhotonTracer::new(&scene, &bvh, PhotonSettings { relax, ..base }, &plan, 3)
            .trace_pass(&lights[0], 0, 1, 0, 1)
    };
    assert_eq!(pass(6), pass(0));
    assert_eq!(landed.len(), relaxed.len());
    assert!(landed.len() > 3000, "{} photons stored", landed.len());
    let mut moved = 0;
    for (a, b) in landed.iter().zip(&relaxed) {
        assert_eq!(
            (a.power, a.direction, a.radius),
            (b.power, b.direction, b.radius)
        );
        if a.position != b.position {
            moved += 1;
        }
        // `receive = normal`: the direction is the surface's normal reversed. A ray from
        // just off the surface back along it meets a face right there.
        let lift = 1e-3;
        let hit = bvh
            .closest_hit(b.position - b.direction * lift, b.direction, 4.0 * lift)
            .unwrap_or_else(|| panic!("photon at {} left its surface", b.position));
        assert!(
            (hit.t - lift).abs() < 2e-4,
            "{} off its surface by {}",
            b.position,
            hit.t - lift
        );
        assert!(bvh.geometric_normal(hit.triangle).dot(b.direction).abs() > 0.99);
    }
    assert!(
        moved * 4 > landed.len() * 3,
        "only {moved} of {} moved",
        landed.len()
    );
    let percentile = |mut d: Vec<f32>, q: f32| {
        d.sort_by(f32::total_cmp);
        d[((d.len() - 1) as f32 * q) as usize]
    };
    let (before, after) = (nearest_distances(&landed), nearest_distances(&relaxed));
    let (low_before, low_after) = (
        percentile(before.clone(), 0.05),
        percentile(after.clone(), 0.05),
    );
    assert!(
        low_after > 1.35 * low_before,
        "5th percentile {low_before} -> {low_after}"
    );
    // Blue rather than white noise: the typical spacing grows toward an even spread's, not
    // beyond (the median of a Poisson spread is about 0.47/√density, a hexagonal grid's
    // 1.07/√density).
    let (mid_before, mid_after) = (percentile(before, 0.5), percentile(after, 0.5));
    assert!(
        mid_after > mid_before && mid_after < 2.0 * mid_before,
        "median {mid_before} -> {mid_after}"
    );
    // The density, and so the light, keeps its shape at the scale of a few disks: photons
    // counted in 15 cm cells (per surface orientation; ~50 a cell) move between cells by
    // under 10%.
    let cells = |photons: &[Photon]| {
        let mut count = std::collections::BTreeMap::new();
        for p in photons {
            let key = (
                (p.position / 0.15).floor().as_ivec3().to_array(),
                p.direction.round().as_ivec3().to_array(),
            );
            *count.entry(key).or_insert(0i64) += 1;
        }
        count
    };
    let (a, b) = (cells(&landed), cells(&relaxed));
    let keys: std::collections::BTreeSet<_> = a.keys().chain(b.keys()).collect();
    let moved_between: i64 = keys
        .iter()
        .map(|k| (a.get(*k).unwrap_or(&0) - b.get(*k).unwrap_or(&0)).abs())
        .sum();
    assert!(
        (moved_between as f64) / 2.0 < 0.1 * landed.len() as f64,
        "{moved_between} of {} changed cells",
        landed.len()
    );
}

#[test]
fn relaxation_of_few_photons_or_none_changes_nothing() {
    let scene = cloudlight_scenes::builtin("cornell").unwrap();
    let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
    let mut photons: Vec<Photon> = (0..relax::NEIGHBOURS)
        .map(|i| Photon {
            position: Vec3::new(0.1 * i as f32, 0.0, 0.2),
            direction: Vec3::NEG_Y,
            power: Vec3::ONE,
            radius: 0.1,
            receive: Receive::Normal,
        })
        .collect();
    let normals = vec![Vec3::Y; photons.len()];
    let before = photons.clone();
    relax::relax(&mut photons, &normals, &bvh, 6, 1e-5);
    assert_eq!(photons, before);
    relax::relax(&mut [], &[], &bvh, 6, 1e-5);
}

#[test]
fn a_stream_stops_disks_at_a_wall_past_which_its_client_sees_darkness() {
    use super::stream::{PhotonStream, Retrace};
    // A lamp on one side of a 3 m wall standing on a floor that runs on under it: the far
    // side's floor gets no light. A client looks at that floor from the far side.
    let mut mesh = Mesh::default();
    mesh.push_box(Vec3::new(-6.0, -0.1, -6.0), Vec3::new(6.0, 0.0, 6.0));
    mesh.push_box(Vec3::new(0.0, 0.0, -6.0), Vec3::new(0.02, 3.0, 6.0));
    let scene = Scene {
        name: "wall".into(),
        materials: vec![Material::diffuse("grey", Vec3::splat(0.6))],
        objects: vec![Object {
            name: "floor and wall".into(),
            mesh,
            material: 0,
            motion: Motion::identity(),
        }],
        lights: vec![Light {
            name: "lamp".into(),
            kind: LightKind::Point,
            power_w: Vec3::splat(10.0),
            motion: Motion::Static(glam::Affine3A::from_translation(Vec3::new(-1.0, 1.0, 0.0))),
            sun_path: None,
        }],
        cameras: Vec::new(),
    };
    let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
    let view = View {
        camera: cloudlight_scenes::Camera {
            position: Vec3::new(4.0, 2.0, 0.0),
            target: Vec3::new(0.5, 0.0, 0.0),
            up: Vec3::Y,
            fov_y_rad: 1.0,
        },
        aspect: 1.0,
    };
    let settings = PhotonSettings::for_budget(&scene, 20_000, 20_000);
    // Floor photons within 20 cm of the wall's lit face, in the client's view: their radii
    // above what reaches the wall (the nearest of 8 rays along the floor is within 22.5°
    // of the wall's normal) or the batch's smallest radius (the packing's floor).
    let overreach = |views: Vec<View>| {
        let mut stream = PhotonStream::new(settings, PackFormat::Compact12, Retrace::Always, 5);
        stream.set_views(views);
        let photons = stream.iterate(&scene, &bvh, 0.0).unpacked();
        let least = photons
            .iter()
            .map(|p| p.radius)
            .fold(f32::INFINITY, f32::min);
        let near: Vec<f32> = photons
            .iter()
            .filter(|p| p.position.y.abs() < 0.01 && p.position.z.abs() < 1.0)
            .filter(|p| p.position.x > -0.2 && p.position.x < 0.0)
            .map(|p| p.radius - (-p.position.x / 22.5f32.to_radians().cos()).max(least))
            .collect();
        assert!(near.len() > 10, "{} photons by the wall", near.len());
        near.into_iter().fold(f32::NEG_INFINITY, f32::max)
    };
    let (unseen, seen) = (overreach(Vec::new()), overreach(vec![view]));
    assert!(
        unseen > 0.1,
        "without a view, disks overreach by {unseen} m"
    );
    assert!(seen < 1e-3, "seen, disks overreach by {seen} m");
}

#[test]
fn the_batcher_sends_merged_photons_with_their_power_and_refinement_passes_finer() {
    // The Cornell box, 10k photons in one batch: merged (the default) the batch carries
    // well under half the photons stored, the same paths stored and the same power (up to
    // Wide20's 9-bit mantissas, shared with the largest channel; the merge itself keeps
    // power exactly, `merge::tests`); a still light's refinement pass, drawn with
    // radii shrunk by its last pass's scale, is merged in cells shrunk alike: fewer of its
    // photons merge than of the first pass.
    use super::stream::{PhotonStream, Retrace};
    let scene = cloudlight_scenes::builtin("cornell").unwrap();
    let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
    let base = PhotonSettings::for_budget(&scene, 10_000, 10_000);
    let iteration = |merge| {
        let s = PhotonSettings { merge, ..base };
        trace_iteration(&scene, &bvh, 0.0, s, 5, PackFormat::Wide20)
    };
    let (plain, merged) = (iteration(0.0), iteration(0.5));
    assert_eq!(plain.stored, merged.stored, "the same paths");
    assert_eq!(plain.sent, plain.stored);
    assert_eq!(merged.sent, merged.unpacked().len());
    assert!(
        merged.sent * 2 < merged.stored,
        "{} of {}",
        merged.sent,
        merged.stored
    );
    let (p, q) = (
        total_power(&plain.unpacked()),
        total_power(&merged.unpacked()),
    );
    assert!(((q - p) / p).abs().max_element() < 3e-3, "{q} vs {p}");
    let mut stream = PhotonStream::new(
        PhotonSettings { passes: 32, ..base },
        PackFormat::Wide20,
        Retrace::Changed,
        5,
    );
    let first = stream.iterate(&scene, &bvh, 0.0);
    let second = stream.iterate(&scene, &bvh, 0.0);
    assert_eq!(second.batches[0].header.pass, 1);
    let kept = |it: &Iteration| it.sent as f64 / it.stored as f64;
    eprintln!(
        "sent / stored: first pass {:.3}, a refinement pass {:.3}",
        kept(&first),
        kept(&second)
    );
    assert!(kept(&second) > 1.5 * kept(&first) && kept(&second) < 1.0);
}

#[test]
fn a_moving_lights_window_draws_its_last_generations_together_until_it_stands_still() {
    // A window of 3 over a light of two slots that changes every iteration: after four
    // generations the set draws the last three (the newest and two complete older ones),
    // each photon's power a third and its radius scaled as three passes'; the total power
    // is one generation's. A manifest that lists the light at the generation before drops
    // the older ones: it stands still.
    let mut set = PhotonSet::with_window(3);
    let total = |set: &PhotonSet| set.photons().map(|p| p.power.x as f64).sum::<f64>();
    for g in 1..=4u64 {
        let t = g as f64 * 0.1;
        set.insert(&batch(0, 0, 2, g, t));
        set.insert(&batch(0, 1, 2, g, t));
        set.apply_manifest(manifest(g, t, &[(0, g, 2)]));
        assert_eq!(set.generations_of(0), g.min(3) as u32, "generation {g}");
    }
    let newest: Vec<Photon> = [batch(0, 0, 2, 4, 0.4), batch(0, 1, 2, 4, 0.4)]
        .iter()
        .flat_map(|b| b.unpack().unwrap())
        .collect();
    let drawn: Vec<Photon> = set.photons().collect();
    assert_eq!(drawn.len(), 3 * newest.len());
    let one: f64 = newest.iter().map(|p| p.power.x as f64).sum();
    let older: f64 = [2u64, 3]
        .iter()
        .flat_map(|&g| [batch(0, 0, 2, g, 0.0), batch(0, 1, 2, g, 0.0)])
        .flat_map(|b| b.unpack().unwrap())
        .map(|p| p.power.x as f64)
        .sum();
    assert!((total(&set) - (one + older) / 3.0).abs() < 1e-6 * one);
    let scale = crate::photon::progressive_radius_scale(3);
    assert!((drawn[0].radius - newest[0].radius * scale).abs() < 1e-6);
    // Half of generation 5 arrived: generation 4 joins the older ones, 2 leaves; until
    // the rest arrives, the newest generation's other half is generation 4's (drawn twice,
    // so the light keeps its power).
    set.insert(&batch(0, 0, 2, 5, 0.5));
    assert_eq!(set.generations_of(0), 3);
    assert_eq!(set.photons().count(), 3 * newest.len());
    set.insert(&batch(0, 1, 2, 5, 0.5));
    set.apply_manifest(manifest(5, 0.5, &[(0, 5, 2)]));
    // The light stands still: the next manifest lists generation 5 again.
    set.apply_manifest(manifest(6, 0.6, &[(0, 5, 2)]));
    assert_eq!(set.generations_of(0), 1);
    assert_eq!(set.photons().count(), newest.len());
    // Without a window, one generation.
    let mut plain = PhotonSet::new();
    for g in 1..=3u64 {
        plain.insert(&batch(0, 0, 1, g, 0.0));
        plain.apply_manifest(manifest(g, g as f64, &[(0, g, 1)]));
    }
    assert_eq!(plain.generations_of(0), 1);
}
