//! The quality benchmark's errors are scale-invariant: multiplying every light of the scene
//! by 1e-6 or 1e6 (a change of unit) changes no reported error.

use cloudlight::bench::photons::{QualityOptions, QualityRow, QualityView};
use cloudlight::render::raster::Raster;

fn close(a: f64, b: f64, tol: f64) -> bool {
    (a - b).abs() <= tol * a.abs().max(b.abs()).max(1e-12)
}

#[test]
fn photon_quality_errors_do_not_change_when_every_light_is_scaled() {
    let raster = Raster::new().unwrap_or_else(|e| panic!("{e}"));
    let o = QualityOptions {
        budgets: vec![4000],
        batch_size: 4000,
        camera: "0".into(),
        spp: 32,
        width: 32,
        height: 32,
        rate_hz: 30.0,
        seed: 5,
        photons_per_disk: cloudlight::render::photon::PhotonSettings::default().photons_per_disk,
        density_radius: true,
        receive: Default::default(),
        downsample: 2,
        levels: 4,
        min_texels: 3.0,
        compute: true,
        edges: true,
        splat_merge: 0.5,
        merge: 0.5,
        passes: 1,
        guide: 0.5,
        guide_reach: 0.05,
        relax: 0,
        fit: cloudlight::render::photon::PhotonSettings::default().fit,
        window: 1,
        // Two jittered frames of the still view averaged (their clamp scales with the light).
        still_frames: 2,
    };
    let base = cloudlight::scenes::builtin("cornell").unwrap();
    let rows: Vec<QualityRow> = [1.0f32, 1e-6, 1e6]
        .iter()
        .map(|&k| {
            let view = QualityView::new(
                base.with_lights_scaled(k),
                &o.camera,
                o.width,
                o.height,
                o.spp,
            )
            .unwrap_or_else(|e| panic!("{e}"));
            view.row(&raster, 4000, &o)
                .unwrap_or_else(|e| panic!("{e}"))
                .0
        })
        .collect();
    let unit = &rows[0];
    eprintln!("{:?}", unit.eight.errors);
    assert!(unit.eight.errors.relmse > 0.01, "{:?}", unit.eight.errors);
    for (k, r) in [1e-6, 1e6].iter().zip(&rows[1..]) {
        for (a, b) in [
            (&r.eight, &unit.eight),
            (&r.twelve, &unit.twelve),
            (&r.twenty, &unit.twenty),
        ] {
            let (e, u) = (a.errors, b.errors);
            assert!(close(e.relmse, u.relmse, 1e-2), "{k}: {e:?} vs {u:?}");
            assert!(
                close(e.energy_ratio, u.energy_ratio, 1e-3),
                "{k}: {e:?} vs {u:?}"
            );
            assert!((e.flip - u.flip).abs() < 5e-3, "{k}: {e:?} vs {u:?}");
            assert_eq!(e.pixels, u.pixels);
            assert_eq!(a.stored, b.stored, "same photon paths");
        }
    }
}
