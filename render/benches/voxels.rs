//! Voxel kernels on the Cornell box, each at octree depths 6 and 7: voxelization (static
//! geometry, done once), light injection, the octree filter and the cone-traced gather.
//!
//! `cargo bench -p cloudlight-render --bench voxels`

use cloudlight_render::voxel::{
    ConeSettings, InjectSettings, VoxelSettings, Voxelizer, filter, gather, inject,
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
    }
    group.finish();
}

criterion_group!(benches, voxels);
criterion_main!(benches);
