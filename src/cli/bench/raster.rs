//! `cloudlight bench raster`: one cold frame of G-buffer + shadow-mapped direct light.

use std::process::ExitCode;
use std::time::Instant;

pub fn run(scene: &str, rounds: usize) -> ExitCode {
    use cloudlight::render::raster::{Raster, ShadowSettings};
    let scene = match cloudlight::scenes::load(scene) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(2);
        }
    };
    let raster = match Raster::new() {
        Ok(r) => r,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::FAILURE;
        }
    };
    let tris = scene.triangles_at(0.0);
    let mut lights: Vec<_> = scene.lights.iter().map(|l| l.at(0.0)).collect();
    lights.extend(scene.surface_light_samples(0.0, 2));
    let camera = scene.cameras[0].at(0.0);
    let mut times = Vec::new();
    for i in 0..=rounds.max(1) {
        let t = Instant::now();
        if let Err(e) = raster.direct(
            &scene,
            &tris,
            &lights,
            &camera,
            1280,
            720,
            ShadowSettings::default(),
        ) {
            eprintln!("error: {e}");
            return ExitCode::FAILURE;
        }
        if i > 0 {
            times.push(t.elapsed().as_secs_f64() * 1000.0);
        }
    }
    times.sort_by(f64::total_cmp);
    let info = raster.adapter();
    println!(
        "{}: {} triangles, {} lights, 1280x720 G-buffer + direct with {}² shadow maps on {} ({:?}): median {:.1} ms per frame (min {:.1}, max {:.1}; includes upload and read-back)",
        scene.name,
        tris.len(),
        lights.len(),
        ShadowSettings::default().size,
        info.name,
        info.backend,
        times[times.len() / 2],
        times[0],
        times[times.len() - 1]
    );
    ExitCode::SUCCESS
}
