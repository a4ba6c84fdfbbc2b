//! Pipeline stages, one module per stage kind, and the wire message types of every edge.
//!
//! A stage is a thin shell over a kernel of `cloudlight-render`: receive → compute → send.
//! Stages never open sockets or look at placement; the runtime moves their messages.
//! Techniques: `photons` (photon_batcher → photon_reconstructor), `irradiance`
//! (basis_gatherer → video_encoder → irradiance_reconstructor, or basis_gatherer →
//! irradiance_raw_reconstructor for the raw f16 map), `voxels` (light_injector →
//! octree_filter → cone_tracer → frame_renderer, whose frames go through a video_encoder to a
//! video_client), `video` (video_encoder:
//! pictures to H.264 access units; video_client: decode and show) and `probe`, the diagnostic used to qualify topologies and
//! links. Every technique's client runs on the shared client
//! shell ([`client`]).

pub mod basis_gatherer;
pub mod client;
pub mod cone_tracer;
pub mod frame_renderer;
pub mod irradiance_reconstructor;
pub mod light_injector;
pub mod octree_filter;
pub mod photon_batcher;
pub mod photon_reconstructor;
pub mod probe;
pub mod video_client;
pub mod video_encoder;
pub mod wire;

use cloudlight_runtime::{AnyScene, StageRegistry};
use cloudlight_scenes::Scene;

/// The scene a stage kind's scene check is given (`validate` passes the loaded [`Scene`]).
pub(crate) fn the_scene(scene: &AnyScene) -> Result<&Scene, String> {
    scene
        .downcast_ref::<Scene>()
        .ok_or_else(|| "the scene check was given something other than a scene".to_string())
}

/// Every stage kind this build knows, for topology files to name.
pub fn registry() -> StageRegistry {
    let mut r = StageRegistry::new();
    basis_gatherer::register(&mut r);
    cone_tracer::register(&mut r);
    frame_renderer::register(&mut r);
    light_injector::register(&mut r);
    octree_filter::register(&mut r);
    irradiance_reconstructor::register(&mut r);
    photon_batcher::register(&mut r);
    photon_reconstructor::register(&mut r);
    probe::register(&mut r);
    video_encoder::register(&mut r);
    video_client::register(&mut r);
    r
}
