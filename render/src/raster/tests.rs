//! The raster G-buffer agrees with ray casting.

use glam::{Vec2, Vec3};

use super::*;
use crate::bvh::{BvhKind, SceneBvh};

#[test]
fn the_gbuffer_of_the_cornell_box_matches_ray_casting() {
    let raster = Raster::new().unwrap_or_else(|e| panic!("{e}"));
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
}

#[test]
fn an_empty_scene_gives_an_empty_gbuffer() {
    let raster = Raster::new().unwrap_or_else(|e| panic!("{e}"));
    let scene = cloudlight_scenes::builtin("cornell").unwrap();
    let g = raster
        .gbuffer(&scene, &[], &scene.cameras[0].camera, 8, 8)
        .unwrap();
    assert!(g.position.iter().all(|p| p.w == 0.0));
    assert_eq!(g.normal.len(), 64);
    assert!(g.albedo.iter().all(|a| *a == Vec3::ZERO));
}
