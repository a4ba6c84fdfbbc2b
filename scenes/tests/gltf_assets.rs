//! glTF import against real files brought by `scenes/fetch-assets.sh` (CI runs it first):
//! the castle-game-engine dungeon level and assimp's glTF 2.0 test models, the deliberately
//! broken ones included.

use std::path::{Path, PathBuf};

use cloudlight_scenes::{LightKind, SceneError, gltf_import};

fn assets() -> PathBuf {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets");
    assert!(
        dir.join("gltf2/.complete").exists() && dir.join("dungeon/.complete").exists(),
        "test assets missing: run scenes/fetch-assets.sh first"
    );
    dir
}

#[test]
fn the_dungeon_level_loads_with_its_triangles_textures_and_lights() {
    let s = gltf_import::load(&assets().join("dungeon/level-dungeon.gltf")).unwrap();
    let tris = s.triangle_count();
    eprintln!(
        "dungeon: {tris} triangles, {} materials, {} lights",
        s.materials.len(),
        s.lights.len()
    );
    assert!((25_000..40_000).contains(&tris), "{tris} triangles");
    let textured = s.materials.iter().filter(|m| m.texture.is_some()).count();
    assert!(textured >= 10, "{textured} textured materials");
    // Two light definitions (a point light and a sun), each placed by two nodes.
    let mut names: Vec<_> = s.lights.iter().map(|l| l.name.as_str()).collect();
    names.dedup();
    assert_eq!(names.len(), 2, "{:?}", s.lights);
    assert_eq!(s.lights.len(), 4);
    let punctual: Vec<_> = s
        .lights
        .iter()
        .filter(|l| !matches!(l.kind, LightKind::Directional { .. }))
        .collect();
    assert_eq!(punctual.len(), 2);
    assert!(
        punctual
            .iter()
            .all(|l| l.power_w.max_element() > 0.0 && l.power_w.is_finite())
    );
    let (lo, hi) = s.bounds_at(0.0);
    assert!(lo.is_finite() && hi.is_finite() && (hi - lo).length() > 1.0);
}

#[test]
fn every_broken_test_file_is_an_error_naming_the_file_never_a_panic() {
    let dir = assets().join("gltf2");
    let broken = [
        "IndexOutOfRange/IndexOutOfRange.gltf",
        "IndexOutOfRange/AllIndicesOutOfRange.gltf",
        "MissingBin/BoxTextured.gltf",
        "wrongTypes/badNumber.gltf",
        "wrongTypes/badExtension.gltf",
        "wrongTypes/badObject.gltf",
        "wrongTypes/badUint.gltf",
        "wrongTypes/badArray.gltf",
        "wrongTypes/badString.gltf",
        "BoxWithInfinites-glTF-Binary/BoxWithInfinites.glb",
        "SchemaFailures/sceneWrongType.gltf",
        "IncorrectVertexArrays/Cube.gltf",
        "RecursiveNodes/RecursiveNodes.gltf",
        "TestNoRootNode/NoScene.gltf",
    ];
    for f in broken {
        let path = dir.join(f);
        assert!(path.exists(), "{f} missing");
        match gltf_import::load(&path) {
            Err(SceneError::Gltf { file, message }) => {
                eprintln!("{f}: {message}");
                assert!(file.ends_with(f), "{file}");
                assert!(!message.is_empty());
            }
            Ok(s) => panic!(
                "{f} loaded ({} triangles) but is broken",
                s.triangle_count()
            ),
            Err(other) => panic!("{f}: unexpected error {other}"),
        }
    }
}

#[test]
fn valid_test_models_load() {
    let dir = assets().join("gltf2");
    for f in [
        "BoxTextured-glTF/BoxTextured.gltf",
        "BoxTextured-glTF-Binary/BoxTextured.glb",
        "BoxTextured-glTF-Embedded/BoxTextured.gltf",
    ] {
        let s = gltf_import::load(&dir.join(f)).unwrap_or_else(|e| panic!("{f}: {e}"));
        assert_eq!(s.triangle_count(), 12, "{f}");
        assert!(
            s.materials.iter().any(|m| m.texture.is_some()),
            "{f}: texture"
        );
        assert!(!s.cameras.is_empty());
    }
}
