//! `cloudlight plan SCENE`: what a scene is and what each technique would allocate for it.

use std::process::ExitCode;

use cloudlight::runtime::stage::show_number;

/// Options of `plan`.
#[derive(clap::Args)]
pub struct Args {
    /// Scene: `cornell`, `cornell-animated`, `city:N` or a .gltf/.glb file.
    scene: String,
}

pub fn run(args: Args) -> ExitCode {
    use cloudlight::render::plan::{PlanSettings, plan};
    let scene = match super::load_scene(&args.scene) {
        Ok(s) => s,
        Err(code) => return code,
    };
    let settings = PlanSettings::default();
    let p = plan(&scene, &settings);
    let (lo, hi) = p.bounds;
    println!(
        "scene {}: {} triangles, {:.3} m² of surface{}",
        scene.name,
        p.triangles,
        p.area_m2,
        if p.animated { ", animated" } else { "" }
    );
    println!(
        "bounds [{:.3}, {:.3}, {:.3}] .. [{:.3}, {:.3}, {:.3}] m",
        lo.x, lo.y, lo.z, hi.x, hi.y, hi.z
    );
    println!(
        "emitted power (lights and emissive surfaces, directional excluded): {:.4} / {:.4} / {:.4} W (R/G/B)",
        p.emitted_w.x, p.emitted_w.y, p.emitted_w.z
    );
    for l in &scene.lights {
        println!(
            "  light {}: {:?}, {:.4} W",
            l.name,
            l.kind,
            l.power_w.element_sum()
        );
    }
    let mut t = crate::cli::table([
        "photons: light",
        "W (sum of channels)",
        "photons",
        "batches",
    ]);
    for l in &p.lights {
        t.add_row([
            l.name.clone(),
            format!("{:.4}", l.power_w),
            l.photons.to_string(),
            l.batches.to_string(),
        ]);
    }
    let total: u64 = p.lights.iter().map(|l| l.photons).sum();
    println!(
        "photons ({total} an iteration, the batcher's default: {} per W, at most {} per batch):\n{t}",
        show_number(three_digits(p.photons_per_watt)),
        settings.batch_size
    );
    let mut v = crate::cli::table(["voxels: level", "grid", "occupied", "of grid", "MiB"]);
    let per_voxel = cloudlight::render::voxel::BYTES_PER_VOXEL;
    for (l, n) in p.voxels_per_level.iter().enumerate() {
        let cells = 1u64 << (3 * l);
        v.add_row([
            l.to_string(),
            format!("{0}³", 1u64 << l),
            n.to_string(),
            format!("{:.3}%", *n as f64 / cells as f64 * 100.0),
            format!("{:.2}", (*n * per_voxel) as f64 / (1 << 20) as f64),
        ]);
    }
    let total: u64 = p.voxels_per_level.iter().sum();
    println!(
        "voxels (leaf {:.4} m; {per_voxel} bytes a voxel of surface, {:.1} MiB in all):\n{v}",
        p.leaf_voxel_m,
        (total * per_voxel) as f64 / (1 << 20) as f64
    );
    print_lightmap(&scene, &p, &settings);
    ExitCode::SUCCESS
}

/// The light map the irradiance technique would bake with its defaults, or why it cannot
/// (the paper's "n/a").
fn print_lightmap(
    scene: &cloudlight::scenes::Scene,
    p: &cloudlight::render::plan::ScenePlan,
    settings: &cloudlight::render::plan::PlanSettings,
) {
    use cloudlight::render::lightmap::{Lightmap, LightmapSettings};
    let estimate = format!(
        "{} texels at {:.0} per m²",
        p.lightmap_texels, settings.texels_per_m2
    );
    match Lightmap::bake(scene, &LightmapSettings::default()) {
        Ok(lm) => {
            let a = &lm.atlas;
            println!(
                "irradiance maps: {}×{} atlas ({:?} UVs), {} charts, {:.0}% of the map covered, texels {:.4} m, unwrap {:.3} s; \
                 {} valid texels ({} moved out from under geometry, {} buried), {} bases, bake {:.3} s (estimate from the area: {estimate})",
                a.width,
                a.height,
                a.source,
                a.charts,
                a.utilization * 100.0,
                1.0 / a.texels_per_m,
                a.unwrap_s,
                lm.texels.valid_count(),
                lm.texels.moved,
                lm.texels.buried,
                lm.bases.bases.len(),
                lm.bake_s
            );
        }
        Err(e) => println!("irradiance maps: n/a: {e} (estimate from the area: {estimate})"),
    }
}

/// `v` rounded to three significant digits.
fn three_digits(v: f64) -> f64 {
    if v == 0.0 || !v.is_finite() {
        return v;
    }
    let scale = 10f64.powi(2 - v.abs().log10().floor() as i32);
    (v * scale).round() / scale
}
