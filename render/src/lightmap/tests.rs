//! Physics and robustness of the light-map kernels: a furnace converges to its closed form
//! bounce by bounce, a thin wall keeps the dark side dark, the Cornell box bakes like the
//! paper, blends are normalised, results are deterministic, extremes stay finite.

use std::sync::Arc;

use cloudlight_scenes::{Material, Mesh, Motion, Object, Scene};
use glam::Vec3;

use super::*;
use crate::HdrMap;
use crate::test_scenes::{bare, object};

/// The inside of a 1 m cube whose walls all emit `le` and reflect `albedo`.
fn furnace(le: f32, albedo: f32) -> Scene {
    let mut m = Mesh::default();
    m.push_box(Vec3::ZERO, Vec3::ONE);
    let material = Material {
        emission: Vec3::splat(le),
        ..Material::diffuse("glow", Vec3::splat(albedo))
    };
    bare(
        "furnace",
        vec![material],
        vec![object("cube", m.flipped(), 0)],
    )
}

fn mean_valid(map: &HdrMap) -> Vec3 {
    map.mean_valid()
}

#[test]
fn a_furnace_converges_to_its_closed_form_bounce_by_bounce() {
    // Every wall sees emission Le over its whole hemisphere: E_direct = π·Le, and each
    // update adds one bounce: E_n = π·Le·(ρ + ρ² + … + ρⁿ) → π·Le·ρ/(1 − ρ).
    let (le, rho) = (1.0f32, 0.5f32);
    let lm = Arc::new(Lightmap::bake(&furnace(le, rho), &LightmapSettings::default()).unwrap());
    let settings = GatherSettings {
        direct_samples: 16,
        ..Default::default()
    };
    let mut g = Gatherer::new(lm, settings);
    let pi = std::f32::consts::PI;
    let mut means = Vec::new();
    for _ in 0..14 {
        means.push(mean_valid(&g.update(0.0).map).x);
    }
    let first = pi * le * rho;
    assert!(
        (means[0] / first - 1.0).abs() < 0.05,
        "one bounce: {} vs {first}",
        means[0]
    );
    for n in 1..5 {
        let growth = (means[n + 1] - means[n]) / (means[n] - means[n - 1]);
        assert!(
            (growth - rho).abs() < 0.05,
            "bounce {n}: energy grows by {growth}, not ρ = {rho}"
        );
    }
    let limit = pi * le * rho / (1.0 - rho);
    let last = *means.last().unwrap();
    assert!(
        (last / limit - 1.0).abs() < 0.05,
        "converged {last} vs {limit}"
    );
}

/// A 4 × 2 × 2 m closed room split at x = 2 by a 0.1 m wall, a point light on the left.
fn thin_wall() -> Scene {
    let mut room = Mesh::default();
    room.push_box(Vec3::ZERO, Vec3::new(4.0, 2.0, 2.0));
    let mut wall = Mesh::default();
    wall.push_box(Vec3::new(1.95, -0.01, -0.01), Vec3::new(2.05, 2.01, 2.01));
    let mut s = bare(
        "thin-wall",
        vec![Material::diffuse("white", Vec3::splat(0.8))],
        vec![object("room", room.flipped(), 0), object("wall", wall, 0)],
    );
    s.lights.push(cloudlight_scenes::Light {
        name: "bulb".into(),
        kind: cloudlight_scenes::LightKind::Point,
        power_w: Vec3::splat(100.0),
        motion: Motion::Static(glam::Affine3A::from_translation(Vec3::new(1.0, 1.0, 1.0))),
        sun_path: None,
    });
    s
}

#[test]
fn an_update_regathers_only_what_a_moving_object_or_light_reaches_and_matches_a_full_one() {
    // The thin-wall rooms with a 0.3 m box circling in the lit room: the dark room's bases
    // and direct light are kept, and the map equals a full update's.
    let mut scene = thin_wall();
    let mut mover = Mesh::default();
    mover.push_box(Vec3::splat(-0.15), Vec3::splat(0.15));
    scene.objects.push(Object {
        motion: Motion::Orbit {
            center: Vec3::new(1.0, 0.5, 1.0),
            axis: Vec3::Y,
            radius: 0.5,
            period_s: 4.0,
            phase: 0.0,
        },
        ..object("mover", mover, 0)
    });
    let lm = Arc::new(
        Lightmap::bake(
            &scene,
            &LightmapSettings {
                atlas: AtlasSettings {
                    resolution: 256,
                    ..Default::default()
                },
                ..Default::default()
            },
        )
        .unwrap(),
    );
    let settings = |partial| GatherSettings {
        partial,
        ..Default::default()
    };
    let (mut part, mut full) = (
        Gatherer::new(lm.clone(), settings(true)),
        Gatherer::new(lm.clone(), settings(false)),
    );
    let mut kept = 0;
    for i in 0..10 {
        let t = i as f64 * 0.1;
        let (p, f) = (part.update(t), full.update(t));
        assert_eq!(f.regathered, f.gather_points);
        println!(
            "t {t:.1}: partial re-gathered {} of {} bases, direct light of {} of {} texels; full {} ms, partial {} ms",
            p.regathered,
            p.gather_points,
            p.direct_texels,
            lm.texels.valid_count(),
            f.seconds * 1e3,
            p.seconds * 1e3
        );
        if i > 0 {
            assert!(
                p.regathered < p.gather_points,
                "update {i}: {}",
                p.regathered
            );
            assert!(p.direct_texels < lm.texels.valid_count() / 2, "update {i}");
            assert!(p.direct_texels > 0, "the box's own texels and its shadow");
            kept += p.gather_points - p.regathered;
        }
        let (a, b) = (p.map.texels(), f.map.texels());
        let mean = mean_valid(&f.map).element_sum() / 3.0;
        let worst = (0..a.len())
            .filter(|&i| lm.texels.valid[i])
            .map(|i| (a[i] - b[i]).abs().max_element())
            .fold(0.0f32, f32::max);
        // Measured: identical (every change here reaches whole tiles far above the
        // tolerance); the bound is the tolerance's worst case.
        assert!(
            worst <= 1e-3 * std::f32::consts::PI * mean,
            "update {i}: partial and full maps differ by {worst} (mean {mean})"
        );
    }
    assert!(kept > 0);
    // A light that moves changes every texel's light: everything is gathered again.
    let cornell = cloudlight_scenes::builtin("cornell-animated").unwrap();
    let lm = Arc::new(Lightmap::bake(&cornell, &LightmapSettings::default()).unwrap());
    let mut g = Gatherer::new(lm.clone(), GatherSettings::default());
    for i in 0..3 {
        let u = g.update(i as f64 * 0.1);
        assert_eq!(u.regathered, u.gather_points, "update {i}");
        assert_eq!(u.direct_texels, lm.texels.valid_count(), "update {i}");
    }
}

#[test]
fn a_thin_wall_leaves_the_dark_side_dark() {
    let settings = LightmapSettings {
        atlas: AtlasSettings {
            resolution: 128,
            ..Default::default()
        },
        ..Default::default()
    };
    let lm = Arc::new(Lightmap::bake(&thin_wall(), &settings).unwrap());
    assert!(
        lm.texels.buried + lm.texels.moved > 0,
        "the room's surfaces under the wall are moved out or buried"
    );
    let mut g = Gatherer::new(lm.clone(), GatherSettings::default());
    for _ in 0..4 {
        g.update(0.0);
    }
    let map = g.map().clone();
    // Every valid texel by side, the band next to the wall included: the wall's faces sit at
    // x = 1.95 (lit) and 2.05 (dark); texels inside its thickness are buried or outside.
    let (mut lit, mut dark) = ((Vec3::ZERO, 0), (Vec3::ZERO, 0));
    let (mut dark_max, mut near_wall) = (0.0f32, 0);
    for i in 0..map.len() {
        if !map.is_valid(i) {
            continue;
        }
        let x = lm.texels.positions[i].x;
        if x < 1.95 - 1e-3 {
            lit.0 += map.texel(i);
            lit.1 += 1;
        } else if x > 2.05 - 1e-3 {
            dark.0 += map.texel(i);
            dark.1 += 1;
            dark_max = dark_max.max(map.texel(i).max_element());
            near_wall += usize::from(x < 2.15);
        }
    }
    let (lit_mean, dark_mean) = (lit.0 / lit.1.max(1) as f32, dark.0 / dark.1.max(1) as f32);
    println!(
        "thin wall: lit {lit_mean} ({} texels), dark {dark_mean} (max {dark_max}, {} texels, {near_wall} within 10 cm of the wall); moved {} buried {}",
        lit.1, dark.1, lm.texels.moved, lm.texels.buried
    );
    // Both rooms are mapped (the dark one about as densely as the lit one), the band next
    // to the wall too.
    assert!(
        lit.1 > 1000 && dark.1 * 2 > lit.1,
        "{} lit, {} dark texels",
        lit.1,
        dark.1
    );
    assert!(
        near_wall > 50,
        "{near_wall} dark texels within 10 cm of the wall"
    );
    assert!(lit_mean.x > 0.0);
    assert!(
        dark_max <= 1e-3 * lit_mean.x,
        "the brightest dark texel {dark_max} against the lit side's mean {lit_mean}: light leaks through the wall"
    );
}

#[test]
fn the_cornell_box_bakes_near_the_papers_fifty_bases_with_normalised_blends() {
    let scene = cloudlight_scenes::builtin("cornell").unwrap();
    let lm = Lightmap::bake(&scene, &LightmapSettings::default()).unwrap();
    let a = &lm.atlas;
    let valid = lm.texels.valid_count();
    println!(
        "atlas {}×{} charts {} utilisation {:.2} texel {:.4} m unwrap {:.3} s; valid {valid} moved {} buried {}; bases {}; bake {:.3} s",
        a.width,
        a.height,
        a.charts,
        a.utilization,
        1.0 / a.texels_per_m,
        a.unwrap_s,
        lm.texels.moved,
        lm.texels.buried,
        lm.bases.bases.len(),
        lm.bake_s
    );
    assert_eq!((a.width, a.height), (128, 128));
    assert_eq!(a.source, UvSource::Unwrapped);
    assert!(
        (30..=80).contains(&lm.bases.bases.len()),
        "{} bases",
        lm.bases.bases.len()
    );
    assert!(valid > 128 * 128 / 3, "{valid} valid texels");
    assert!(lm.texels.buried > 0, "the floor under the blocks is buried");
    for (i, w) in lm.bases.weights.iter().enumerate() {
        if lm.texels.valid[i] {
            assert!(!w.is_empty() && w.len() <= MAX_BASES_PER_TEXEL);
            let sum: f32 = w.iter().map(|(_, w)| w).sum();
            assert!((sum - 1.0).abs() < 1e-4, "texel {i}: weights sum to {sum}");
            assert!(w.iter().all(|(_, w)| w.is_finite() && *w >= 0.0));
        } else {
            assert!(w.is_empty());
        }
    }
    // Every valid texel belongs to exactly one basis's member list, and it is that basis's.
    let mut seen = vec![0u32; lm.texels.valid.len()];
    for k in 0..lm.bases.bases.len() {
        let members = lm.bases.members_of(k);
        assert_eq!(members.len() as u32, lm.bases.bases[k].members);
        assert!(
            members.contains(&lm.bases.bases[k].texel),
            "basis {k}'s centre"
        );
        for &t in members {
            seen[t as usize] += 1;
        }
    }
    for (i, &n) in seen.iter().enumerate() {
        assert_eq!(n, u32::from(lm.texels.valid[i]), "texel {i}");
    }
    // Seams stay shut: every map texel (padding included) has a finite value after dilation.
    let mut g = Gatherer::new(Arc::new(lm), GatherSettings::default());
    let u = g.update(0.0);
    assert!(
        u.map
            .texels()
            .iter()
            .all(|e| e.is_finite() && e.min_element() >= 0.0)
    );
    assert!(mean_valid(&u.map).x > 0.0);
    println!("update: {} rays, {:.2} ms", u.rays, u.seconds * 1e3);
}

/// The converged map of `lm` with `settings`, as texels.
fn converged(lm: &Arc<Lightmap>, settings: GatherSettings) -> Vec<Vec3> {
    let mut g = Gatherer::new(lm.clone(), settings);
    for _ in 0..24 {
        if g.update(0.0).converged {
            break;
        }
    }
    g.map().texels()
}

#[test]
fn fitted_bases_follow_the_per_texel_map_far_closer_than_one_value_per_basis() {
    // The per-texel gather (the paper's naive server, 256 rays a texel) is the reference
    // in texel space; the same bases carrying one value, a plane and a quadric are scored
    // by the scale-invariant relMSE over valid texels.
    let scene = cloudlight_scenes::builtin("cornell").unwrap();
    let lm = Arc::new(Lightmap::bake(&scene, &LightmapSettings::default()).unwrap());
    let reference = converged(
        &lm,
        GatherSettings {
            mode: GatherMode::Texels,
            rays_per_texel: 256,
            ..Default::default()
        },
    );
    let valid: Vec<usize> = (0..reference.len())
        .filter(|&i| lm.texels.valid[i])
        .collect();
    let mean = valid
        .iter()
        .map(|&i| reference[i].element_sum())
        .sum::<f32>()
        / (3 * valid.len()) as f32;
    let relmse = |map: &[Vec3]| {
        valid
            .iter()
            .map(|&i| {
                let (x, y) = (map[i] / mean, reference[i] / mean);
                ((x - y) * (x - y) / (y * y + Vec3::splat(0.01))).element_sum()
            })
            .sum::<f32>()
            / (3 * valid.len()) as f32
    };
    let error = |fit| {
        relmse(&converged(
            &lm,
            GatherSettings {
                fit,
                ..Default::default()
            },
        ))
    };
    let (constant, linear, quadratic) = (
        error(BasisFit::Constant),
        error(BasisFit::Linear),
        error(BasisFit::Quadratic),
    );
    println!(
        "texel relMSE against per texel: constant {constant:.4}, linear {linear:.4}, quadratic {quadratic:.4}"
    );
    assert!(linear < 0.5 * constant, "{linear} against {constant}");
    assert!(quadratic < 0.8 * linear, "{quadratic} against {linear}");
}

#[test]
fn the_same_seed_gives_the_same_map() {
    let scene = cloudlight_scenes::builtin("cornell").unwrap();
    let a = Arc::new(Lightmap::bake(&scene, &LightmapSettings::default()).unwrap());
    let b = Arc::new(Lightmap::bake(&scene, &LightmapSettings::default()).unwrap());
    assert_eq!(a.bases, b.bases);
    let (mut ga, mut gb) = (
        Gatherer::new(a, GatherSettings::default()),
        Gatherer::new(b, GatherSettings::default()),
    );
    for _ in 0..2 {
        assert_eq!(ga.update(0.5).map, gb.update(0.5).map);
    }
    // The seed matters: another one gives another map (of about the same light).
    let lm = Arc::new(Lightmap::bake(&scene, &LightmapSettings::default()).unwrap());
    let mut other = Gatherer::new(
        lm,
        GatherSettings {
            seed: GatherSettings::default().seed + 1,
            ..Default::default()
        },
    );
    let (one, two) = (ga.update(0.5).map, {
        for _ in 0..2 {
            other.update(0.5);
        }
        other.update(0.5).map
    });
    assert_ne!(one, two, "a different seed gave the same map");
    let (m1, m2) = (one.mean_valid(), two.mean_valid());
    assert!(
        (m1 - m2).abs().max_element() < 0.05 * m1.max_element(),
        "{m1} vs {m2}"
    );
}

#[test]
fn a_static_scene_stops_gathering_once_converged() {
    let lm = Arc::new(Lightmap::bake(&furnace(1.0, 0.3), &LightmapSettings::default()).unwrap());
    let mut g = Gatherer::new(lm, GatherSettings::default());
    let mut updates = 0;
    while !g.update(updates as f64).converged {
        updates += 1;
        assert!(updates < 40, "a static furnace never converged");
    }
    let u = g.update(100.0);
    assert!(u.converged && u.rays == 0 && u.time_s == 100.0);
}

#[test]
fn light_maps_scale_with_the_lights_and_stay_finite_at_extremes() {
    let base = cloudlight_scenes::builtin("cornell").unwrap();
    let mut means = Vec::new();
    for k in [1e-6f32, 1.0, 1e6] {
        let lm = Arc::new(
            Lightmap::bake(&base.with_lights_scaled(k), &LightmapSettings::default()).unwrap(),
        );
        let mut g = Gatherer::new(lm, GatherSettings::default());
        let map = g.update(0.0).map;
        assert!(map.texels().iter().all(|e| e.is_finite()), "scale {k}");
        means.push(mean_valid(&map).x / k);
    }
    assert!(
        (means[0] / means[1] - 1.0).abs() < 1e-3 && (means[2] / means[1] - 1.0).abs() < 1e-3,
        "{means:?}"
    );
}

#[test]
fn scenes_that_cannot_be_parametrised_say_why() {
    let cornell = cloudlight_scenes::builtin("cornell").unwrap();
    let no_unwrap = LightmapSettings {
        atlas: AtlasSettings {
            unwrap_limit_s: 0.0,
            ..Default::default()
        },
        ..Default::default()
    };
    assert_eq!(
        Lightmap::bake(&cornell, &no_unwrap).unwrap_err(),
        NotParametrizable::NoUvsAndNoUnwrap
    );
    let tiny = LightmapSettings {
        atlas: AtlasSettings {
            max_resolution: 32,
            ..Default::default()
        },
        ..Default::default()
    };
    let city = cloudlight_scenes::builtin("city:2000").unwrap();
    let err = Lightmap::bake(&city, &tiny).unwrap_err();
    assert!(
        matches!(
            err,
            NotParametrizable::TooManyCharts { .. } | NotParametrizable::TexelsTooLarge { .. }
        ),
        "{err}"
    );
    println!("city:2000 in 32²: {err}");
    let empty = bare("empty", vec![Material::diffuse("w", Vec3::ONE)], Vec::new());
    assert_eq!(
        Lightmap::bake(&empty, &LightmapSettings::default()).unwrap_err(),
        NotParametrizable::NoSurfaces
    );
}

#[test]
fn one_triangle_bakes_and_gathers_without_nan() {
    let m = Mesh {
        positions: vec![Vec3::ZERO, Vec3::X, Vec3::Z],
        normals: vec![Vec3::Y; 3],
        indices: vec![[0, 2, 1]],
        ..Default::default()
    };
    let mut s = bare(
        "one",
        vec![Material::diffuse("w", Vec3::splat(0.5))],
        vec![object("t", m, 0)],
    );
    s.lights = thin_wall().lights;
    match Lightmap::bake(&s, &LightmapSettings::default()) {
        Ok(lm) => {
            let mut g = Gatherer::new(Arc::new(lm), GatherSettings::default());
            let map = g.update(0.0).map;
            assert!(map.texels().iter().all(|e| e.is_finite()));
            // Nothing to bounce off: no indirect light.
            assert_eq!(mean_valid(&map), Vec3::ZERO);
        }
        Err(e) => panic!("one triangle should bake: {e}"),
    }
}

#[test]
fn a_gathered_cornell_map_survives_h264_within_the_video_bounds() {
    // Measured (quadratic bases, whose fitted maps carry more fine detail for the codec than
    // one value per basis did): 0.79 / 1.38 / 2.36 % mean luminance error, chroma
    // 0.52–0.95 %; the bounds allow half as much again.
    let scene = cloudlight_scenes::builtin("cornell").unwrap();
    let lm = Arc::new(Lightmap::bake(&scene, &LightmapSettings::default()).unwrap());
    let mut g = Gatherer::new(lm, GatherSettings::default());
    for _ in 0..3 {
        g.update(0.0);
    }
    let img = g.map().clone();
    for (qp, bound) in [(12u8, 0.012), (20, 0.021), (28, 0.035)] {
        let f =
            crate::video::measure::hdr_codec(&img, crate::video::RateControl::FixedQp(qp)).unwrap();
        println!(
            "QP {qp}: luminance error {:.4}, chroma {:.4}, key frame {} B, next {} B",
            f.key.luminance_mean, f.key.chroma_mean, f.key_bytes, f.next_bytes
        );
        assert!(f.key.luminance_mean <= bound, "QP {qp}: {:?}", f.key);
        assert!(f.key.chroma_mean <= 0.014, "QP {qp}: {:?}", f.key);
    }
}

#[test]
fn the_bake_cache_tells_scenes_apart_by_name_and_texture_contents() {
    let cornell = cloudlight_scenes::builtin("cornell").unwrap();
    let settings = LightmapSettings::default();
    let key = |s: &Scene| fingerprint(s, &settings);
    assert_eq!(key(&cornell), key(&cornell.clone()));
    let mut renamed = cornell.clone();
    renamed.name = "another box".into();
    assert_ne!(key(&renamed), key(&cornell));
    // Two textures of one size that differ in one texel.
    let textured = |c: Vec3| {
        let mut s = cornell.clone();
        s.materials[0].texture = Some(cloudlight_scenes::model::Texture {
            width: 2,
            height: 2,
            texels: vec![Vec3::ONE, Vec3::ONE, Vec3::ONE, c],
        });
        s
    };
    assert_ne!(key(&textured(Vec3::ONE)), key(&textured(Vec3::splat(0.5))));
    assert_ne!(key(&textured(Vec3::ONE)), key(&cornell));
    // And the cache hands each its own bake.
    let (a, b) = (textured(Vec3::ONE), textured(Vec3::splat(0.5)));
    let (la, lb) = (
        Lightmap::cached(&a, &settings).unwrap(),
        Lightmap::cached(&b, &settings).unwrap(),
    );
    assert!(!Arc::ptr_eq(&la, &lb));
    assert!(Arc::ptr_eq(&la, &Lightmap::cached(&a, &settings).unwrap()));
}

#[test]
fn the_gather_traces_each_point_s_sample_set_in_coherent_order() {
    // The same Hammersley set, reordered: consecutive samples are neighbours on the square.
    let n = 512;
    let s: Vec<(f32, f32)> = gather::coherent_samples(n)
        .iter()
        .map(|s| (s[0], s[1]))
        .collect();
    let mut plain: Vec<(f32, f32)> = (0..n).map(|i| texels::hammersley(i, n)).collect();
    let mut sorted = s.clone();
    let key = |p: &(f32, f32)| (p.0.to_bits(), p.1.to_bits());
    plain.sort_by_key(key);
    sorted.sort_by_key(key);
    assert_eq!(plain, sorted);
    let step = |v: &[(f32, f32)]| {
        v.windows(2)
            .map(|w| ((w[1].0 - w[0].0).powi(2) + (w[1].1 - w[0].1).powi(2)).sqrt())
            .sum::<f32>()
            / (v.len() - 1) as f32
    };
    let index_order: Vec<(f32, f32)> = (0..n).map(|i| texels::hammersley(i, n)).collect();
    let (coherent, plain) = (step(&s), step(&index_order));
    assert!(
        coherent * 4.0 < plain,
        "mean step {coherent} against {plain} in index order"
    );
}

#[test]
fn direct_light_cast_in_batches_is_what_each_texel_computes_alone() {
    // The Cornell box with two point lights besides its emitter, so each texel's estimate
    // has several terms, some shadowed; the batch casts them light by light and must hand
    // each result back to its own texel, sample and term.
    let mut scene = cloudlight_scenes::builtin("cornell").unwrap();
    let (lo, hi) = scene.bounds_at(0.0);
    for (i, at) in [Vec3::new(0.2, 0.3, 0.2), Vec3::new(0.8, 0.15, 0.7)]
        .into_iter()
        .enumerate()
    {
        scene.lights.push(cloudlight_scenes::Light {
            name: format!("lamp{i}"),
            kind: cloudlight_scenes::LightKind::Point,
            power_w: Vec3::new(5.0, 4.0, 3.0),
            motion: Motion::Static(glam::Affine3A::from_translation(lo + (hi - lo) * at)),
            sun_path: None,
        });
    }
    let lm = Lightmap::bake(&scene, &LightmapSettings::default()).unwrap();
    let bvh = SceneBvh::at(&scene, 0.0, crate::BvhKind::default());
    let frame = lm.texels.frame_at(bvh.triangles());
    let s = GatherSettings::default();
    let (e, _, texels) = super::gather::direct_map(&lm, &bvh, &frame, 0.0, &s, 3, None);
    assert_eq!(texels, lm.texels.valid_count());
    let light = crate::direct_light::DirectLight::new(&scene, &bvh, 0.0);
    let eps = light.eps().max(lm.texels.texel_m * 1e-3);
    let seed = s.seed ^ 3u64.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    let mut lit = 0;
    for (i, got) in e.iter().enumerate() {
        if !lm.texels.valid[i] {
            assert_eq!(*got, Vec3::ZERO);
            continue;
        }
        let (x, n) = (frame.0[i], frame.1[i]);
        let mut rng = crate::sampling::Rng::new(seed, i as u64);
        let sum: Vec3 = (0..s.direct_samples)
            .map(|_| light.irradiance(x + n * eps, n, &mut rng))
            .sum();
        let alone = (sum / s.direct_samples as f32).max(Vec3::ZERO);
        assert_eq!(*got, alone, "texel {i}");
        lit += usize::from(alone.max_element() > 0.0);
    }
    assert!(lit > texels / 4, "{lit} of {texels} texels lit");
}
