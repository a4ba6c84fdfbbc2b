//! Voxel kernels on the Cornell box, each at octree depths 6 and 7: voxelization (static
//! geometry, done once), light injection, the octree filter, the cone-traced gather, and
//! encoding and decoding the gathered irradiance as Haar deltas.
//!
//! `cargo bench -p cloudlight-render --bench voxels`

use cloudlight_render::voxel::{
    ConeSettings, DeltaDecoder, DeltaEncoder, InjectSettings, TransferSettings, VoxelSettings,
    Voxelizer, filter, gather, inject,
};
use cloudlight_render::{BvhKind, SceneBvh};
use criterion::{Criterion, criterion_group, criterion_main};

fn voxels(c: &mut Criterion) {
    let scene = cloudlight_scenes::builtin("cornell").unwrap();
    let bvh = SceneBvh::at(&scene, 0.0, BvhKind::default());
    let mut group = c.benchmark_group("cornell voxels");
    group.sample_size(10);
    for depth in [6u32, 7] {
        let settings = VoxelSettings {
            max_depth: depth,
            ..Default::default()
        };
        group.bench_function(format!("depth {depth}: voxelize"), |b| {
            b.iter(|| Voxelizer::new(&scene, &settings))
        });
        let octree = Voxelizer::new(&scene, &settings).octree_at(&scene, 0.0);
        let inject_settings = InjectSettings::default();
        group.bench_function(format!("depth {depth}: inject"), |b| {
            b.iter(|| inject(&octree, &scene, &bvh, 0.0, None, &inject_settings))
        });
        let injection = inject(&octree, &scene, &bvh, 0.0, None, &inject_settings);
        group.bench_function(format!("depth {depth}: filter"), |b| {
            b.iter(|| filter(&octree, injection.leaves.clone()))
        });
        let levels = filter(&octree, injection.leaves.clone());
        let cone = ConeSettings::default();
        let g = gather(&octree, &levels, &cone);
        eprintln!(
            "depth {depth}: {} leaves, {} voxels gathered, {} samples",
            octree.leaves().len(),
            g.gathered,
            g.samples
        );
        group.bench_function(format!("depth {depth}: gather"), |b| {
            b.iter(|| gather(&octree, &levels, &cone))
        });
        // Transfer: every update a key update (every voxel that differs from its parent).
        let transfer = TransferSettings {
            key_every: 1,
            ..Default::default()
        };
        let mut encoder = DeltaEncoder::new(transfer);
        let update = encoder.encode(&octree, &g, 0.0);
        eprintln!(
            "depth {depth}: a key update is {} B in {} deltas, {} of {} voxels, raw {} B ({:.3})",
            update.bytes,
            update.deltas.len(),
            update.voxels_sent,
            update.voxels,
            update.raw_bytes,
            update.bytes as f64 / update.raw_bytes as f64
        );
        group.bench_function(format!("depth {depth}: encode a key update"), |b| {
            b.iter(|| encoder.encode(&octree, &g, 0.0))
        });
        group.bench_function(format!("depth {depth}: decode a key update"), |b| {
            b.iter(|| {
                let mut decoder = DeltaDecoder::new();
                for d in &update.deltas {
                    decoder.apply(&octree, d).unwrap();
                }
                decoder
            })
        });
    }
    group.finish();
}

criterion_group!(benches, voxels);
criterion_main!(benches);
