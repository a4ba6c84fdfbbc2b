//! The scene model (meshes, diffuse materials, lights in watts, cameras, animation as a
//! function of scene time), glTF import, the built-in Cornell box and procedural `city:N`.
//!
//! Nothing is implemented yet: this crate is filled by the scenes/render issue. It never
//! knows about actors, queues or sockets.
