//! Photon kernels on the Cornell box at the paper's budget (10k photons, one batch): tracing
//! a batch, packing it (12 and 20 bytes per photon), unpacking it; and tracing a batch on
//! city:250000, where the BVH no longer fits the caches.
//!
//! `cargo bench -p cloudlight-render --bench photons`

use cloudlight_render::photon::{
    BatchPlan, PackFormat, PackedBatch, PhotonSettings, PhotonTracer, pack::BatchHeader,
    photon_lights,
};
use cloudlight_render::{BvhKind, SceneBvh};
use criterion::{Criterion, criterion_group, criterion_main};

fn photons(c: &mut Criterion) {
    let scene = cloudlight_scenes::builtin("cornell").unwrap();
    let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
    let settings = PhotonSettings::default();
    let lights = photon_lights(&scene, 0.0);
    let plan = BatchPlan::new(&lights, &settings);
    let tracer = PhotonTracer::new(&scene, &bvh, settings, &plan, 1);
    let mut generation = 0;
    c.bench_function("cornell: trace one 10k-photon batch", |b| {
        b.iter(|| {
            generation += 1;
            tracer.trace_batch(&lights[0], 0, 1, generation)
        })
    });
    let stored = tracer.trace_batch(&lights[0], 0, 1, 0);
    let header = BatchHeader {
        light: 0,
        slot: 0,
        slots: 1,
        generation: 0,
        scene_time_s: 0.0,
        emitted: settings.batch_size,
    };
    for format in [PackFormat::Compact12, PackFormat::Wide20] {
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
}

fn city(c: &mut Criterion) {
    let scene = cloudlight_scenes::builtin("city:250000").unwrap();
    let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
    let settings = PhotonSettings::default();
    let lights = photon_lights(&scene, 0.0);
    let plan = BatchPlan::new(&lights, &settings);
    let tracer = PhotonTracer::new(&scene, &bvh, settings, &plan, 1);
    let mut generation = 0;
    c.bench_function(
        "city:250000: trace one 10k-photon batch of each light",
        |b| {
            b.iter(|| {
                generation += 1;
                lights
                    .iter()
                    .map(|l| tracer.trace_batch(l, 0, 1, generation).len())
                    .sum::<usize>()
            })
        },
    );
}

criterion_group!(benches, photons, city);
criterion_main!(benches);
