//! Photon kernels on the Cornell box at the paper's budget (10k photons, one batch): tracing
//! a batch (plain, relaxed, and with disks not fitted to their surfaces), packing it (12 and 20 bytes per photon), unpacking it; and
//! tracing a batch on city:250000, where the BVH no longer fits the caches; merging a batch,
//! and 32 batches drawn together as a still light's refinement passes, before a client
//! splats them.
//!
//! `cargo bench -p cloudlight-render --bench photons`

use cloudlight_render::photon::{
    BatchPlan, PackFormat, PackedBatch, PhotonLight, PhotonSettings, PhotonTracer,
    pack::BatchHeader, photon_lights,
};
use cloudlight_render::{BvhKind, SceneBvh};
use cloudlight_scenes::Scene;
use criterion::{Criterion, criterion_group, criterion_main};

/// A scene at time 0 with what its photon tracer needs.
struct Setup {
    scene: Scene,
    bvh: SceneBvh,
    settings: PhotonSettings,
    lights: Vec<PhotonLight>,
    plan: BatchPlan,
}

fn setup(spec: &str) -> Setup {
    let scene = cloudlight_scenes::builtin(spec).unwrap();
    let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
    let settings = PhotonSettings::default();
    let lights = photon_lights(&scene, 0.0);
    let plan = BatchPlan::new(&lights, &settings);
    Setup {
        scene,
        bvh,
        settings,
        lights,
        plan,
    }
}

/// Benchmarks tracing one batch of each light.
fn trace(c: &mut Criterion, name: &str, tracer: &PhotonTracer, lights: &[PhotonLight]) {
    let mut generation = 0;
    c.bench_function(name, |b| {
        b.iter(|| {
            generation += 1;
            lights
                .iter()
                .map(|l| tracer.trace_batch(l, 0, 1, generation).len())
                .sum::<usize>()
        })
    });
}

fn photons(c: &mut Criterion) {
    let Setup {
        scene,
        bvh,
        settings,
        lights,
        plan,
    } = setup("cornell");
    let tracer = PhotonTracer::new(&scene, &bvh, settings, &plan, 1);
    trace(c, "cornell: trace one 10k-photon batch", &tracer, &lights);
    let relaxed = PhotonSettings {
        relax: 6,
        ..settings
    };
    let tracer_relaxed = PhotonTracer::new(&scene, &bvh, relaxed, &plan, 1);
    trace(
        c,
        "cornell: trace one 10k-photon batch, 6 rounds of relaxation",
        &tracer_relaxed,
        &lights,
    );
    let unfitted = PhotonSettings { fit: 0, ..settings };
    trace(
        c,
        "cornell: trace one 10k-photon batch, disks not fitted to their surfaces",
        &PhotonTracer::new(&scene, &bvh, unfitted, &plan, 1),
        &lights,
    );
    let stored = tracer.trace_batch(&lights[0], 0, 1, 0);
    let header = BatchHeader {
        light: 0,
        slot: 0,
        slots: 1,
        generation: 0,
        pass: 0,
        scene_time_s: 0.0,
        emitted: settings.batch_size,
        receive: Default::default(),
    };
    for format in [
        PackFormat::Compact8,
        PackFormat::Compact12,
        PackFormat::Wide20,
    ] {
        c.bench_function(
            &format!("cornell: pack {} photons, {format:?}", stored.len()),
            |b| b.iter(|| PackedBatch::pack(header, &stored, format)),
        );
        let packed = PackedBatch::pack(header, &stored, format);
        c.bench_function(
            &format!("cornell: unpack {} photons, {format:?}", stored.len()),
            |b| b.iter(|| packed.unpack().unwrap()),
        );
    }
    let cell = cloudlight_render::photon::splat::SplatSettings::default().merge;
    c.bench_function(&format!("cornell: merge {} photons", stored.len()), |b| {
        b.iter(|| cloudlight_render::photon::merge::merge(&stored, cell).len())
    });
    // 32 passes as a client draws them: each its own photons, powers / 32, radii scaled.
    let scale = cloudlight_render::photon::progressive_radius_scale(32);
    let passes: Vec<_> = (0..32)
        .flat_map(|g| tracer.trace_batch(&lights[0], 0, 1, 100 + g))
        .map(|p| cloudlight_render::photon::Photon {
            power: p.power / 32.0,
            radius: p.radius * scale,
            ..p
        })
        .collect();
    let mut group = c.benchmark_group("merge");
    group.sample_size(10);
    group.bench_function(
        format!("cornell: merge 32 passes, {} photons", passes.len()),
        |b| b.iter(|| cloudlight_render::photon::merge::merge(&passes, cell).len()),
    );
    group.finish();
}

fn city(c: &mut Criterion) {
    let s = setup("city:250000");
    let tracer = PhotonTracer::new(&s.scene, &s.bvh, s.settings, &s.plan, 1);
    trace(
        c,
        "city:250000: trace one 10k-photon batch of each light",
        &tracer,
        &s.lights,
    );
}

criterion_group!(benches, photons, city);
criterion_main!(benches);
