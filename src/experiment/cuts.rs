//! The cuts each technique offers a placement experiment: where the network cuts its
//! pipeline (CloudLight Figure 1), as a [`StageGraph`] built from the technique's benchmark
//! graph. A graph's stages on `cloud` are shared or per client; its stage `client` on `home`
//! is what each client shows.

use anyhow::Context;

use crate::bench::baseline::{BaselineOptions, PhotonsVideo};
use crate::bench::irradiance::Irradiance;
use crate::bench::photons::Photons;
use crate::bench::voxels::Voxels;
use crate::bench::{CLIENT, Placement, Side, StageGraph, Technique, options_from};

/// What a cut asks of the client's machine (the paper's client classes).
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum ClientClass {
    /// Decodes video and shows it.
    Thin,
    /// Rasterizes the scene with its own direct light and a looked-up indirect term.
    Medium,
    /// Splats photons, or runs the whole technique itself.
    Powerful,
}

impl ClientClass {
    /// Every class, weakest first.
    pub const ALL: [ClientClass; 3] = [
        ClientClass::Thin,
        ClientClass::Medium,
        ClientClass::Powerful,
    ];

    /// Its name.
    pub fn name(self) -> &'static str {
        match self {
            ClientClass::Thin => "thin",
            ClientClass::Medium => "medium",
            ClientClass::Powerful => "powerful",
        }
    }

    /// What a client of the class does, in a few words.
    pub fn about(self) -> &'static str {
        match self {
            ClientClass::Thin => "decode only",
            ClientClass::Medium => "raster",
            ClientClass::Powerful => "splatting, or the whole technique",
        }
    }
}

/// One cut of a technique.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Cut {
    /// Its name in an experiment file.
    pub name: &'static str,
    /// What crosses the network, and what runs where.
    pub about: &'static str,
    /// The least client that can run it.
    pub client: ClientClass,
    /// Whether whole frames cross the network (so the camera, not only the indirect light,
    /// is as late as the link).
    pub frames_cross: bool,
}

const PHOTON_CUTS: &[Cut] = &[
    Cut {
        name: "cloud",
        about: "the batcher traces photons on the cloud; bit-packed photons cross the network to clients that splat them",
        client: ClientClass::Powerful,
        frames_cross: false,
    },
    Cut {
        name: "local",
        about: "each client traces its own photons: nothing crosses the network",
        client: ClientClass::Powerful,
        frames_cross: false,
    },
    Cut {
        name: "video",
        about: "full frames rendered in the cloud per client, H.264 to thin clients (the baseline)",
        client: ClientClass::Thin,
        frames_cross: true,
    },
];

const IRRADIANCE_CUTS: &[Cut] = &[
    Cut {
        name: "h264",
        about: "the gatherer's light map crosses the network as H.264 to clients that look it up",
        client: ClientClass::Medium,
        frames_cross: false,
    },
    Cut {
        name: "raw",
        about: "the light map crosses the network as raw f16 texels",
        client: ClientClass::Medium,
        frames_cross: false,
    },
    Cut {
        name: "local",
        about: "each client gathers its own light map: nothing crosses the network",
        client: ClientClass::Powerful,
        frames_cross: false,
    },
];

const VOXEL_CUTS: &[Cut] = &[
    Cut {
        name: "video",
        about: "GI and each client's frame in the cloud, H.264 to thin clients (the paper's voxel pipeline)",
        client: ClientClass::Thin,
        frames_cross: true,
    },
    Cut {
        name: "deltas",
        about: "Haar voxel deltas cross the network to a frame renderer on each client",
        client: ClientClass::Medium,
        frames_cross: false,
    },
    Cut {
        name: "local",
        about: "each client runs the GI stages and its frame renderer: nothing crosses the network",
        client: ClientClass::Powerful,
        frames_cross: false,
    },
];

/// The techniques an experiment may name.
pub const TECHNIQUES: &[&str] = &[Photons::NAME, Irradiance::NAME, Voxels::NAME];

/// The cuts of `technique`, if it is one.
pub fn cuts(technique: &str) -> Option<&'static [Cut]> {
    match technique {
        Photons::NAME => Some(PHOTON_CUTS),
        Irradiance::NAME => Some(IRRADIANCE_CUTS),
        Voxels::NAME => Some(VOXEL_CUTS),
        _ => None,
    }
}

/// The names of `technique`'s cuts, comma-separated (for messages).
pub fn cut_names(technique: &str) -> String {
    cuts(technique)
        .unwrap_or_default()
        .iter()
        .map(|c| c.name)
        .collect::<Vec<_>>()
        .join(", ")
}

/// Where a technique's time per lighting update is reported: (stage, report key) pairs
/// whose values add up (the first instance of a replicated stage is read).
pub fn update_cost(technique: &str) -> &'static [(&'static str, &'static str)] {
    match technique {
        Photons::NAME => &[("server", "iteration_ms_mean")],
        Irradiance::NAME => &[("gather", "update_ms_mean")],
        Voxels::NAME => &[
            ("inject", "inject_ms_mean"),
            ("filter", "filter_ms_p50"),
            ("cones", "gather_ms_mean"),
        ],
        _ => &[],
    }
}

/// The cut `cut` of `technique`, if it has it.
pub fn find(technique: &str, cut: &str) -> Option<&'static Cut> {
    cuts(technique)?.iter().find(|c| c.name == cut)
}

/// Checks `knobs` against `technique`'s options (the error names the knob and lists them).
pub fn check_knobs(technique: &str, knobs: &toml::Table) -> anyhow::Result<()> {
    match technique {
        Photons::NAME => options_from::<Photons>(knobs).map(drop),
        Irradiance::NAME => options_from::<Irradiance>(knobs).map(drop),
        Voxels::NAME => options_from::<Voxels>(knobs).map(drop),
        other => anyhow::bail!("unknown technique `{other}`"),
    }
}

/// The stage graph of `technique` cut at `cut`, with the technique's `knobs` over its
/// defaults.
pub fn graph(technique: &str, cut: &str, knobs: &toml::Table) -> anyhow::Result<StageGraph> {
    let g = match (technique, cut) {
        (Photons::NAME, "cloud") => Photons::graph(&options_from::<Photons>(knobs)?)?,
        (Photons::NAME, "local") => local(Photons::graph(&options_from::<Photons>(knobs)?)?),
        (Photons::NAME, "video") => PhotonsVideo::graph(&BaselineOptions {
            photons: options_from::<Photons>(knobs)?,
            ..BaselineOptions::default()
        })?,
        (Irradiance::NAME, "h264") => Irradiance::graph(&options_from::<Irradiance>(knobs)?)?,
        (Irradiance::NAME, "raw") => {
            raw_maps(Irradiance::graph(&options_from::<Irradiance>(knobs)?)?)?
        }
        (Irradiance::NAME, "local") => local(raw_maps(Irradiance::graph(&options_from::<
            Irradiance,
        >(knobs)?)?)?),
        (Voxels::NAME, "video") => Voxels::graph(&options_from::<Voxels>(knobs)?)?,
        (Voxels::NAME, "deltas") => deltas(Voxels::graph(&options_from::<Voxels>(knobs)?)?)?,
        (Voxels::NAME, "local") => local(deltas(Voxels::graph(&options_from::<Voxels>(knobs)?)?)?),
        _ => anyhow::bail!(
            "`{technique}` has no cut `{cut}` (its cuts: {})",
            cut_names(technique)
        ),
    };
    Ok(g)
}

/// Every stage on the clients' side, one per client: nothing is shared, nothing crosses.
fn local(mut g: StageGraph) -> StageGraph {
    for s in &mut g.stages {
        s.placement = Placement::PerClient(Side::Home);
    }
    g
}

/// Leaves out stages `names` and their edges.
fn without(mut g: StageGraph, names: &[&str]) -> StageGraph {
    let stage = |end: &str| end.split('.').next().unwrap_or(end).to_string();
    g.stages.retain(|s| !names.contains(&s.name.as_str()));
    g.edges.retain(|(a, b)| {
        !names.contains(&stage(a).as_str()) && !names.contains(&stage(b).as_str())
    });
    g
}

/// The irradiance graph with the H.264 encoder left out: the map goes raw to a
/// `irradiance_raw_reconstructor`.
fn raw_maps(g: StageGraph) -> anyhow::Result<StageGraph> {
    let client = g
        .stages
        .iter()
        .find(|s| s.name == CLIENT)
        .cloned()
        .context("the irradiance graph has no client")?;
    let mut g = without(g, &["encode", CLIENT]);
    g.techniques.retain(|t| t != "video");
    let source = g
        .stages
        .first()
        .map(|s| s.name.clone())
        .context("the irradiance graph has no gatherer")?;
    Ok(g.stage(
        CLIENT,
        "irradiance_raw_reconstructor",
        Placement::PerClient(Side::Home),
        client.params,
    )
    .edge(&source, CLIENT))
}

/// The voxel graph with each client's frame renderer on the client (it becomes the client)
/// and no video.
fn deltas(g: StageGraph) -> anyhow::Result<StageGraph> {
    let mut g = without(g, &["encode", CLIENT]);
    g.techniques.retain(|t| t != "video");
    let render = g
        .stages
        .iter_mut()
        .find(|s| s.name == "render")
        .context("the voxel graph has no frame renderer")?;
    render.name = CLIENT.into();
    render.placement = Placement::PerClient(Side::Home);
    for (from, to) in &mut g.edges {
        for end in [from, to] {
            if end == "render" || end.starts_with("render.") {
                *end = end.replacen("render", CLIENT, 1);
            }
        }
    }
    Ok(g)
}
