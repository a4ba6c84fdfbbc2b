//! Placement experiments: an experiment file names a scene, techniques and the cuts of each
//! to try ([`cuts`]), link profiles and client counts; it expands into one topology per
//! (technique, cut, link, clients), each a file `cloudlight run` or `cloudlight node` runs
//! alone.
//!
//! ```toml
//! scene = "cornell-animated"
//! duration_s = 5.0
//! seed = 1
//! clients = [1, 2]
//! links = ["home-wifi", "campus", "city"]
//! extra_latency_ms = [0, 250]    # added to each link's one-way latency (the paper's latency video)
//!
//! [[technique]]
//! name = "photons"
//! cuts = ["cloud", "local", "video"]
//! set = { photons = 10000 }      # the technique's knobs, as `bench --set`
//! ```
//!
//! The file is validated like a topology: every problem at once, each with file, line and
//! key (an unknown technique, cut or profile names the known ones).

pub mod cuts;
pub mod reference;
pub mod report;
pub mod run;

use std::path::Path;

use cloudlight_runtime::TopologyErrors;
use cloudlight_runtime::topology::TopologySpec;
use cloudlight_runtime::topology::reader::{Tbl, Walker, kind, plain};
use cloudlight_transport::LinkProfile;

use cloudlight_actors::client::MAX_FRAME_PX;

use crate::bench::{CLIENT, ClusterOptions, StageGraph};

/// Longest run an experiment asks for, seconds.
pub const MAX_DURATION_S: f64 = 3600.0;
/// Most clients in one run.
pub const MAX_CLIENTS: u64 = 1000;
/// Most latency an experiment adds to a link, ms.
pub const MAX_EXTRA_LATENCY_MS: f64 = 10_000.0;

/// How an experiment's clients show and sample what they show, and how the reference is
/// made: the same for every run, so that runs compare.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Measure {
    /// Client frame width, pixels.
    pub width: u32,
    /// Client frame height, pixels.
    pub height: u32,
    /// Client frames per second.
    pub fps: f64,
    /// A client frame is compared with the reference every this many seconds of scene time.
    pub sample_every_s: f64,
    /// Samples before this scene time are left out (the pipeline filling).
    pub warmup_s: f64,
    /// Reference samples per pixel.
    pub reference_spp: u32,
    /// Frames per second of the reference's video of the camera path.
    pub reference_fps: f64,
}

impl Default for Measure {
    fn default() -> Self {
        Measure {
            width: 256,
            height: 144,
            fps: 10.0,
            sample_every_s: 1.0,
            warmup_s: 1.5,
            reference_spp: 128,
            reference_fps: 4.0,
        }
    }
}

/// One technique of an experiment and the cuts of it to try.
#[derive(Clone, Debug, PartialEq)]
pub struct TechniqueCuts {
    /// The technique.
    pub name: String,
    /// Its cuts to try, in the file's order.
    pub cuts: Vec<String>,
    /// Its knobs over its defaults.
    pub knobs: toml::Table,
}

/// A placement experiment.
#[derive(Clone, Debug, PartialEq)]
pub struct Experiment {
    /// Its name (the file's stem unless it says).
    pub name: String,
    /// Scene spec.
    pub scene: String,
    /// Seconds each run lasts.
    pub duration_s: f64,
    /// Run seed.
    pub seed: u64,
    /// Client counts.
    pub clients: Vec<usize>,
    /// Link profiles between the cloud and the clients, by name.
    pub links: Vec<String>,
    /// Latencies added to each link's one-way latency, ms (the paper's injected latency:
    /// with the direct light on the client, what crosses is the indirect light).
    pub extra_latency_ms: Vec<f64>,
    /// The techniques and their cuts.
    pub techniques: Vec<TechniqueCuts>,
    /// How clients are sampled and compared with the reference.
    pub measure: Measure,
}

/// One run of an experiment.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Run {
    /// Technique.
    pub technique: String,
    /// Its cut.
    pub cut: String,
    /// Link profile.
    pub link: String,
    /// Latency added to the link's, ms.
    pub extra_latency_ms: u32,
    /// Clients.
    pub clients: usize,
}

impl Run {
    /// A name for the run's files: `photons-cloud-campus-2c`, and `-250ms` with added
    /// latency.
    pub fn id(&self) -> String {
        let extra = if self.extra_latency_ms > 0 {
            format!("-{}ms", self.extra_latency_ms)
        } else {
            String::new()
        };
        format!(
            "{}-{}-{}{extra}-{}c",
            self.technique, self.cut, self.link, self.clients
        )
    }
}

impl Experiment {
    /// Reads and validates the experiment file at `path`.
    pub fn load(path: &Path) -> Result<Experiment, TopologyErrors> {
        let file = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| {
            let mut w = Walker::new(&file, "");
            w.err(&(0..0), "<file>", format!("cannot read it: {e}"));
            TopologyErrors(w.diags)
        })?;
        let stem = path
            .file_stem()
            .map_or("experiment".into(), |s| s.to_string_lossy().into_owned());
        Experiment::parse(&file, &text, &stem)
    }

    /// Parses and validates `text` (named `file` in diagnostics; `stem` names the
    /// experiment unless it says).
    pub fn parse(file: &str, text: &str, stem: &str) -> Result<Experiment, TopologyErrors> {
        let mut w = Walker::new(file, text);
        let Some(root) = w.document(text) else {
            return Err(TopologyErrors(w.diags));
        };
        let mut top = Tbl::new(root.get_ref(), root.span(), String::new());
        let mut e = Experiment {
            name: stem.to_string(),
            scene: "cornell-animated".into(),
            duration_s: 5.0,
            seed: 0,
            clients: vec![1],
            links: vec!["campus".into()],
            extra_latency_ms: vec![0.0],
            techniques: Vec::new(),
            measure: Measure::default(),
        };
        if let Some(name) = top.string(&mut w, "name") {
            cloudlight_runtime::topology::reader::check_name(&mut w, &name, "name");
            e.name = name.into_inner();
        }
        if let Some(scene) = top.string(&mut w, "scene") {
            e.scene = scene.into_inner();
        }
        if let Some(d) = top.float(&mut w, "duration_s") {
            if *d.get_ref() > 0.0 && *d.get_ref() <= MAX_DURATION_S {
                e.duration_s = d.into_inner();
            } else {
                w.err(
                    &d.span(),
                    "duration_s",
                    format!(
                        "{} is out of range: must be in (0, {MAX_DURATION_S}] s",
                        d.get_ref()
                    ),
                );
            }
        }
        let m = &mut e.measure;
        let size = |w: &mut Walker, top: &mut Tbl, key: &'static str, into: &mut u32| {
            if let Some(v) = top.uint(w, key) {
                match u32::try_from(*v.get_ref()) {
                    Ok(px) if (16..=MAX_FRAME_PX).contains(&px) && px % 2 == 0 => *into = px,
                    _ => w.err(
                        &v.span(),
                        key,
                        format!(
                            "{} is out of range: an even number of pixels, 16 to {MAX_FRAME_PX}",
                            v.get_ref()
                        ),
                    ),
                }
            }
        };
        size(&mut w, &mut top, "width", &mut m.width);
        size(&mut w, &mut top, "height", &mut m.height);
        let float = |w: &mut Walker,
                     top: &mut Tbl,
                     key: &'static str,
                     range: (f64, f64),
                     into: &mut f64| {
            if let Some(v) = top.float(w, key) {
                if (range.0..=range.1).contains(v.get_ref()) {
                    *into = v.into_inner();
                } else {
                    w.err(
                        &v.span(),
                        key,
                        format!(
                            "{} is out of range: {} to {}",
                            v.get_ref(),
                            range.0,
                            range.1
                        ),
                    );
                }
            }
        };
        float(&mut w, &mut top, "fps", (1.0, 120.0), &mut m.fps);
        float(
            &mut w,
            &mut top,
            "sample_every_s",
            (0.05, 60.0),
            &mut m.sample_every_s,
        );
        float(&mut w, &mut top, "warmup_s", (0.0, 60.0), &mut m.warmup_s);
        float(
            &mut w,
            &mut top,
            "reference_fps",
            (0.1, 60.0),
            &mut m.reference_fps,
        );
        if let Some(v) = top.uint(&mut w, "reference_spp") {
            match u32::try_from(*v.get_ref()) {
                Ok(spp) if (1..=1 << 16).contains(&spp) => m.reference_spp = spp,
                _ => w.err(
                    &v.span(),
                    "reference_spp",
                    "out of range: 1 to 65536 samples per pixel",
                ),
            }
        }
        if let Some(seed) = top.uint(&mut w, "seed") {
            e.seed = seed.into_inner();
        }
        if let Some(v) = top.get("clients") {
            match v.get_ref() {
                toml::de::DeValue::Array(items) if !items.is_empty() => {
                    e.clients.clear();
                    for (i, item) in items.iter().enumerate() {
                        match plain(item.get_ref()).and_then(|p| p.as_integer()) {
                            Some(n) if (0..=MAX_CLIENTS as i64).contains(&n) => {
                                e.clients.push(n as usize)
                            }
                            _ => w.err(
                                &item.span(),
                                &format!("clients[{i}]"),
                                format!("expected a client count 0 to {MAX_CLIENTS}"),
                            ),
                        }
                    }
                }
                other => w.err(
                    &v.span(),
                    "clients",
                    format!(
                        "expected a non-empty array of client counts, found {}",
                        kind(other)
                    ),
                ),
            }
        }
        if let Some(links) = top.strings(&mut w, "links") {
            if links.is_empty() {
                let span = top.table.get("links").map(|v| v.span()).unwrap_or_default();
                w.err(&span, "links", "names no link profile");
            }
            e.links.clear();
            for (i, l) in links.into_iter().enumerate() {
                if LinkProfile::named(l.get_ref()).is_none() {
                    w.err(
                        &l.span(),
                        &format!("links[{i}]"),
                        format!(
                            "unknown link profile `{}` (known: {})",
                            l.get_ref(),
                            LinkProfile::names()
                        ),
                    );
                }
                e.links.push(l.into_inner());
            }
        }
        if let Some(v) = top.get("extra_latency_ms") {
            match v.get_ref() {
                toml::de::DeValue::Array(items) if !items.is_empty() => {
                    e.extra_latency_ms.clear();
                    for (i, item) in items.iter().enumerate() {
                        let ms = plain(item.get_ref()).and_then(|p| {
                            p.as_float().or_else(|| p.as_integer().map(|i| i as f64))
                        });
                        match ms {
                            Some(ms) if (0.0..=MAX_EXTRA_LATENCY_MS).contains(&ms) => {
                                e.extra_latency_ms.push(ms.round())
                            }
                            _ => w.err(
                                &item.span(),
                                &format!("extra_latency_ms[{i}]"),
                                format!("expected milliseconds, 0 to {MAX_EXTRA_LATENCY_MS}"),
                            ),
                        }
                    }
                }
                other => w.err(
                    &v.span(),
                    "extra_latency_ms",
                    format!(
                        "expected a non-empty array of milliseconds, found {}",
                        kind(other)
                    ),
                ),
            }
        }
        let tables = top.tables(&mut w, "technique");
        if tables.is_empty() && top.table.get("technique").is_none() {
            w.err(
                &(0..0),
                "technique",
                "missing: name at least one `[[technique]]` with its `cuts`",
            );
        }
        for (mut t, span) in tables {
            let name = t.req_string(&mut w, "name");
            let cut_list = t.strings(&mut w, "cuts");
            let mut knobs = toml::Table::new();
            if let Some(set) = t.table(&mut w, "set") {
                for (k, v) in set.table.iter() {
                    if let Some(value) = plain(v.get_ref()) {
                        knobs.insert(k.get_ref().to_string(), value);
                    }
                }
            }
            t.finish(&mut w, &["name", "cuts", "set"]);
            let Some(name) = name else { continue };
            let Some(known) = cuts::cuts(name.get_ref()) else {
                w.err(
                    &name.span(),
                    &t.key("name"),
                    format!(
                        "unknown technique `{}` (one of: {})",
                        name.get_ref(),
                        cuts::TECHNIQUES.join(", ")
                    ),
                );
                continue;
            };
            if let Err(err) = cuts::check_knobs(name.get_ref(), &knobs) {
                let span = t.table.get("set").map(|v| v.span()).unwrap_or(span.clone());
                w.err(&span, &t.key("set"), format!("{err:#}"));
            }
            let cut_list = match cut_list {
                Some(list) if !list.is_empty() => list,
                Some(_) | None => {
                    w.err(
                        &span,
                        &t.key("cuts"),
                        format!(
                            "name the cuts to try (of `{}`: {})",
                            name.get_ref(),
                            cuts::cut_names(name.get_ref())
                        ),
                    );
                    continue;
                }
            };
            let mut chosen = Vec::new();
            for (i, c) in cut_list.into_iter().enumerate() {
                if !known.iter().any(|k| k.name == c.get_ref()) {
                    w.err(
                        &c.span(),
                        &format!("{}[{i}]", t.key("cuts")),
                        format!(
                            "`{}` has no cut `{}` (its cuts: {})",
                            name.get_ref(),
                            c.get_ref(),
                            cuts::cut_names(name.get_ref())
                        ),
                    );
                } else if chosen.contains(c.get_ref()) {
                    w.err(
                        &c.span(),
                        &format!("{}[{i}]", t.key("cuts")),
                        format!("cut `{}` is named twice", c.get_ref()),
                    );
                } else {
                    chosen.push(c.into_inner());
                }
            }
            e.techniques.push(TechniqueCuts {
                name: name.into_inner(),
                cuts: chosen,
                knobs,
            });
        }
        top.finish(
            &mut w,
            &[
                "name",
                "scene",
                "duration_s",
                "seed",
                "clients",
                "links",
                "extra_latency_ms",
                "technique",
                "width",
                "height",
                "fps",
                "sample_every_s",
                "warmup_s",
                "reference_spp",
                "reference_fps",
            ],
        );
        w.finish().map(|()| e)
    }

    /// Every run, technique by technique, cut by cut, link by link, added latency by added
    /// latency, client count by client count.
    pub fn runs(&self) -> Vec<Run> {
        let mut out = Vec::new();
        for t in &self.techniques {
            for cut in &t.cuts {
                for link in &self.links {
                    for &extra in &self.extra_latency_ms {
                        for &clients in &self.clients {
                            out.push(Run {
                                technique: t.name.clone(),
                                cut: cut.clone(),
                                link: link.clone(),
                                extra_latency_ms: extra as u32,
                                clients,
                            });
                        }
                    }
                }
            }
        }
        out
    }

    /// The topology of `run`: the cut's graph with `run.clients` clients on `home`, the link
    /// profile between `cloud` and `home`. Every stage that shows frames (a client, or a
    /// frame renderer in the cloud) renders at the experiment's size and rate with exposure
    /// `exposure` (chosen from the first frame when `None`); each client records
    /// [`RECORDING`] and writes a sample every `sample_every_s`.
    pub fn topology(&self, run: &Run, exposure: Option<f32>) -> anyhow::Result<TopologySpec> {
        let knobs = self
            .techniques
            .iter()
            .find(|t| t.name == run.technique)
            .map(|t| t.knobs.clone())
            .unwrap_or_default();
        let mut link = LinkProfile::named(&run.link)
            .ok_or_else(|| anyhow::anyhow!("unknown link profile `{}`", run.link))?;
        link.latency_ms += f64::from(run.extra_latency_ms);
        let cluster = ClusterOptions {
            scene: self.scene.clone(),
            seconds: self.duration_s,
            link: Some(link),
            seed: self.seed,
        };
        let mut graph = cuts::graph(&run.technique, &run.cut, &knobs)?;
        self.set_clients(&mut graph, exposure);
        let mut spec = graph.topology(&run.id(), &cluster, run.clients)?;
        spec.cluster = format!("{}-{}", self.name, run.id());
        Ok(spec)
    }

    /// Sets the shell keys of every stage of `graph` that shows frames, and the video
    /// encoders' rate.
    fn set_clients(&self, graph: &mut StageGraph, exposure: Option<f32>) {
        let registry = cloudlight_actors::registry();
        let frames = cloudlight_actors::client::FRAMES.name();
        let m = &self.measure;
        for stage in &mut graph.stages {
            let Some(kind) = registry.get(&stage.kind) else {
                continue;
            };
            let p = &mut stage.params;
            if kind.name == "video_encoder" {
                p.insert("fps".into(), m.fps.into());
            }
            if !kind.outputs.iter().any(|o| o.name == frames) {
                continue;
            }
            p.insert("width".into(), i64::from(m.width).into());
            p.insert("height".into(), i64::from(m.height).into());
            p.insert("fps".into(), m.fps.into());
            p.insert("render".into(), true.into());
            // Every cut shows frames as they come: a client accumulating a still view's
            // frames (`accumulate`) would gain on the cuts whose frames are rendered in the
            // cloud, and more the sooner its light arrived (a longer link would read worse
            // for how long the view had been still, not for its light).
            p.insert("accumulate".into(), false.into());
            match exposure {
                Some(stops) => p.insert("exposure_stops".into(), f64::from(stops).into()),
                None => p.remove("exposure_stops"),
            };
            if stage.name == CLIENT {
                p.insert("sample_every_s".into(), m.sample_every_s.into());
                p.insert("record".into(), RECORDING.into());
            }
        }
    }
}

/// The MP4 each client of an experiment records, in its folder of the run's output.
pub const RECORDING: &str = "client.mp4";
