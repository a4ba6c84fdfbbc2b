//! `cloudlight bench rays`: BVH build and ray casting speed.

use std::process::ExitCode;
use std::time::Instant;

pub fn run(scene: &str, threads: &[usize], rounds: usize) -> ExitCode {
    let t = Instant::now();
    let scene = match cloudlight::scenes::load(scene) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(2);
        }
    };
    eprintln!(
        "{}: {} triangles, generated in {:.2} s",
        scene.name,
        scene.triangle_count(),
        t.elapsed().as_secs_f64()
    );
    let rows = cloudlight::render::raybench::run(&scene, threads, rounds.max(1));
    let mut table = comfy_table::Table::new();
    table
        .load_preset(comfy_table::presets::UTF8_FULL_CONDENSED)
        .set_header([
            "BVH",
            "threads",
            "build s",
            "coherent Mrays/s",
            "incoherent Mrays/s",
        ]);
    let mut json = Vec::new();
    for r in &rows {
        table.add_row([
            format!("{:?}", r.kind),
            r.threads.to_string(),
            format!("{:.3}", r.build_s),
            format!("{:.2}", r.coherent_mrays_s),
            format!("{:.2}", r.incoherent_mrays_s),
        ]);
        json.push(serde_json::json!({
            "bvh": format!("{:?}", r.kind), "threads": r.threads, "build_s": r.build_s,
            "coherent_mrays_s": r.coherent_mrays_s, "incoherent_mrays_s": r.incoherent_mrays_s,
        }));
    }
    println!("{table}");
    println!(
        "{}",
        serde_json::json!({ "scene": scene.name, "triangles": scene.triangle_count(), "rows": json })
    );
    ExitCode::SUCCESS
}
