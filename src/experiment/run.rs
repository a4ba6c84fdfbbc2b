//! Running an experiment: each run's topology in this process over real sockets and the link
//! emulator, its figures read from the stage reports, its client's samples compared with the
//! reference, one JSON line appended to `results.jsonl` as each run ends. A run already in
//! `results.jsonl` with the same fingerprint (its topology and the measurement settings) is
//! not run again, so an interrupted sweep resumes where it stopped.
//!
//! Output folder:
//! - `results.jsonl`: one [`RunResult`] per line, in the order the runs ended;
//! - `topologies/<run>.toml`: each run's topology (`cloudlight run` runs it alone);
//! - `runs/<run>/`: its `metrics.json` and each client's folder (`frames.csv`, `samples.csv`,
//!   `sample_*.png`, `client.mp4`);
//! - `reference/`: the reference pictures of the sample times and `reference.mp4`.

use std::collections::HashMap;
use std::io::{BufRead, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::Context;
use cloudlight_runtime::RunOptions;
use cloudlight_runtime::metrics::MetricsSnapshot;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use super::cuts::{self, ClientClass};
use super::reference::References;
use super::{Experiment, RECORDING, Run};
use crate::bench::{CLIENT, replica_name};

/// Changes whenever how a run is measured changes, so that no result measured otherwise is
/// reused.
pub const MEASURE_VERSION: u32 = 3;

/// Name of the results file in an experiment's output folder.
pub const RESULTS: &str = "results.jsonl";

/// One sample of what client 0 showed, against the reference at its scene time.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SampleError {
    /// Scene time, s.
    pub time_s: f64,
    /// Age of the indirect light shown then, ms.
    pub age_ms: Option<f64>,
    /// Scale-invariant relMSE.
    pub relmse: f64,
    /// LDR-FLIP of the pictures.
    pub flip: f64,
    /// Light shown over the reference's.
    pub energy_ratio: f64,
    /// The client's picture, relative to the output folder.
    pub picture: String,
    /// The reference's, relative to the output folder.
    pub reference: String,
}

/// What one run measured.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RunResult {
    /// The run (`photons-cloud-campus-1c`).
    pub id: String,
    /// Hash of its topology and the measurement settings: a result is reused only while
    /// this matches.
    pub fingerprint: String,
    /// Technique.
    pub technique: String,
    /// Cut.
    pub cut: String,
    /// Link profile.
    pub link: String,
    /// Latency added to the link's one way, ms.
    pub extra_latency_ms: u32,
    /// Clients.
    pub clients: usize,
    /// The least client that runs the cut.
    pub client_class: Option<ClientClass>,
    /// Whether whole frames crossed the network.
    pub frames_cross: bool,
    /// Seconds it ran.
    pub duration_s: f64,
    /// Why it failed, when it did (a failed run is run again on resume).
    pub error: Option<String>,
    /// Age of the indirect light shown, p50 averaged over clients, ms.
    pub age_ms_p50: f64,
    /// Worst client's p99, ms.
    pub age_ms_p99: f64,
    /// Time per lighting update of the technique's shared stages (on the client in a
    /// local cut), mean, ms.
    pub server_update_ms: Option<f64>,
    /// Frame rendered and encoded in the cloud per client (video cuts), p50, ms.
    pub cloud_frame_ms: Option<f64>,
    /// Client time per frame (render; or decode and show, each p50), p50 averaged over
    /// clients, ms.
    pub client_frame_ms_p50: f64,
    /// Worst client's p99, ms.
    pub client_frame_ms_p99: f64,
    /// Frames per second a client showed, mean over clients.
    pub fps: f64,
    /// Wire megabits per second leaving the cloud, per client.
    pub mbps_per_client: f64,
    /// In total.
    pub mbps_total: f64,
    /// Mean relMSE of the samples (`None`: no sample after the warm-up).
    pub relmse: Option<f64>,
    /// Mean FLIP of the samples.
    pub flip: Option<f64>,
    /// Mean energy ratio of the samples.
    pub energy_ratio: Option<f64>,
    /// The samples compared (after the warm-up, with indirect light shown).
    pub samples: Vec<SampleError>,
    /// Samples after the warm-up taken before any indirect light was shown (the pipeline
    /// still starting: with a long link it takes a few round trips), left out.
    #[serde(default)]
    pub samples_before_light: usize,
    /// Client 0's recording, relative to the output folder.
    pub recording: Option<String>,
    /// Wall seconds the run took, start-up and measurement in.
    pub wall_s: f64,
}

impl RunResult {
    /// Whether it ran and was measured.
    pub fn ok(&self) -> bool {
        self.error.is_none()
    }

    /// Mean relMSE of its samples at `times` (scene seconds; `None` when it has none of
    /// them).
    pub fn relmse_at(&self, times: &[f64]) -> Option<f64> {
        let at: Vec<f64> = self
            .samples
            .iter()
            .filter(|s| times.iter().any(|t| (s.time_s - t).abs() < 1e-6))
            .map(|s| s.relmse)
            .collect();
        (!at.is_empty()).then(|| at.iter().sum::<f64>() / at.len() as f64)
    }
}

/// The sample times every one of `runs` has: runs with longer links start showing light
/// later, and a moving light makes some moments harder than others, so runs compare over
/// the same moments.
pub fn common_times(runs: &[&RunResult]) -> Vec<f64> {
    let Some(first) = runs.first() else {
        return Vec::new();
    };
    first
        .samples
        .iter()
        .map(|s| s.time_s)
        .filter(|t| {
            runs.iter()
                .all(|r| r.samples.iter().any(|s| (s.time_s - t).abs() < 1e-6))
        })
        .collect()
}

/// How to run an experiment.
#[derive(Clone, Debug, Default)]
pub struct RunSettings {
    /// Forget earlier results and run everything.
    pub fresh: bool,
    /// Show a progress bar (on a terminal).
    pub progress: bool,
}

/// What [`run`] did.
#[derive(Clone, Debug, Default)]
pub struct Outcome {
    /// Every run's result, in the experiment's order.
    pub results: Vec<RunResult>,
    /// Runs done now.
    pub ran: usize,
    /// Runs whose results were reused.
    pub reused: usize,
}

/// The results in `out`'s `results.jsonl`, the last line of each run winning (none when the
/// file is missing; a line that does not parse, such as one cut short, is skipped).
pub fn read_results(out: &Path) -> anyhow::Result<HashMap<String, RunResult>> {
    let path = out.join(RESULTS);
    let file = match std::fs::File::open(&path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(HashMap::new()),
        Err(e) => return Err(e).with_context(|| format!("reading {}", path.display())),
    };
    let mut map = HashMap::new();
    for line in std::io::BufReader::new(file).lines() {
        let line = line.with_context(|| format!("reading {}", path.display()))?;
        match serde_json::from_str::<RunResult>(&line) {
            Ok(r) => {
                map.insert(r.id.clone(), r);
            }
            Err(e) if !line.trim().is_empty() => {
                tracing::warn!(
                    "{}: a line that is not a result is skipped: {e}",
                    path.display()
                )
            }
            Err(_) => {}
        }
    }
    Ok(map)
}

/// Appends `result` to `out`'s `results.jsonl` as one line, flushed to disk.
fn append(out: &Path, result: &RunResult) -> anyhow::Result<()> {
    let path = out.join(RESULTS);
    let mut file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&path)
        .with_context(|| format!("opening {}", path.display()))?;
    // A line cut short by an interrupted write is ended first, so that this one parses.
    let cut_short = std::fs::read(&path).is_ok_and(|b| b.last().is_some_and(|c| *c != b'\n'));
    let mut line = if cut_short {
        "\n".to_string()
    } else {
        String::new()
    };
    line += &serde_json::to_string(result)?;
    line.push('\n');
    file.write_all(line.as_bytes())
        .and_then(|()| file.sync_data())
        .with_context(|| format!("writing {}", path.display()))
}

impl Experiment {
    /// The fingerprint of `run`: its topology (without the exposure, which is measured) and
    /// the measurement settings.
    pub fn fingerprint(&self, run: &Run) -> anyhow::Result<String> {
        let spec = self.topology(run, None)?;
        let mut h = Sha256::new();
        h.update(spec.to_toml().as_bytes());
        h.update(serde_json::to_string(&self.measure)?.as_bytes());
        h.update(MEASURE_VERSION.to_le_bytes());
        Ok(h.finalize()[..8]
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect())
    }
}

/// The folder of replica `i`'s output in a run with `clients` clients.
fn client_dir(run_dir: &Path, i: usize, clients: usize) -> PathBuf {
    let name = replica_name(CLIENT, i, clients).replace(['[', ']'], "-");
    run_dir.join(name.trim_end_matches('-'))
}

/// What every client report holds, as the experiment reads it.
#[derive(Deserialize)]
struct Shown {
    frames: u64,
    frame_ms_p50: f64,
    frame_ms_p99: f64,
    age_ms_p50: f64,
    age_ms_p99: f64,
    /// A video client's decode time per picture, p50 (beside `frame_ms_p50`, the showing).
    #[serde(default)]
    decode_ms_p50: Option<f64>,
}

/// The report of stage `name` (or of its first replica).
fn report_of<'m>(m: &'m MetricsSnapshot, name: &str) -> Option<&'m serde_json::Value> {
    let first = format!("{name}[0]");
    m.stages
        .iter()
        .find(|s| s.name == name || s.name == first)
        .and_then(|s| s.report.as_ref())
}

fn number(v: &serde_json::Value, key: &str) -> Option<f64> {
    v.get(key).and_then(serde_json::Value::as_f64)
}

/// Runs every run of `experiment` not already in `out`'s results, appending each result as
/// it ends; then returns every run's result.
pub fn run(experiment: &Experiment, out: &Path, settings: &RunSettings) -> anyhow::Result<Outcome> {
    let topologies = out.join("topologies");
    for dir in [out.to_path_buf(), topologies.clone(), out.join("reference")] {
        std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    if settings.fresh {
        match std::fs::remove_file(out.join(RESULTS)) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                return Err(e).context("removing the earlier results");
            }
            _ => {}
        }
    }
    let earlier = read_results(out)?;
    let runs = experiment.runs();
    let mut pending = Vec::new();
    let mut done: HashMap<String, RunResult> = HashMap::new();
    for run in &runs {
        let fingerprint = experiment.fingerprint(run)?;
        match earlier.get(&run.id()) {
            Some(r) if r.ok() && r.fingerprint == fingerprint => {
                done.insert(run.id(), r.clone());
            }
            _ => pending.push((run.clone(), fingerprint)),
        }
    }
    let reused = done.len();
    let scene = cloudlight_scenes::load(&experiment.scene)?;
    let mut references = References::new(scene, &experiment.measure, 0.0);
    if !pending.is_empty() {
        let bar = progress_bar(settings.progress, pending.len(), experiment.duration_s);
        if reused > 0 {
            say(
                &bar,
                format!(
                    "{reused} of {} runs already measured in {} (reused)",
                    runs.len(),
                    out.join(RESULTS).display()
                ),
            );
        }
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()
            .context("starting the async runtime")?;
        for (run, fingerprint) in pending.iter() {
            bar.set_message(run.id());
            let started = Instant::now();
            let result = match measure(
                experiment,
                run,
                fingerprint,
                out,
                &runtime,
                &mut references,
                &bar,
            ) {
                Ok(r) => r,
                Err(e) => RunResult {
                    id: run.id(),
                    fingerprint: fingerprint.clone(),
                    technique: run.technique.clone(),
                    cut: run.cut.clone(),
                    link: run.link.clone(),
                    extra_latency_ms: run.extra_latency_ms,
                    clients: run.clients,
                    error: Some(format!("{e:#}")),
                    wall_s: started.elapsed().as_secs_f64(),
                    ..RunResult::default()
                },
            };
            say(&bar, line(&result));
            append(out, &result)?;
            done.insert(run.id(), result);
            bar.inc(1);
        }
        bar.finish_and_clear();
    }
    let video = out.join(super::report::REFERENCE_VIDEO);
    if !pending.is_empty() || !video.exists() {
        let bar = if settings.progress {
            indicatif::ProgressBar::new(0).with_style(
                indicatif::ProgressStyle::with_template(
                    "[{elapsed_precise}] {bar:30} {pos}/{len} reference frames of the camera path",
                )
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
            )
        } else {
            indicatif::ProgressBar::hidden()
        };
        references.video(experiment.duration_s, &video, |i, n| {
            bar.set_length(n as u64);
            bar.set_position(i as u64);
        })?;
        bar.finish_and_clear();
    }
    let results: Vec<RunResult> = runs.iter().filter_map(|r| done.remove(&r.id())).collect();
    Ok(Outcome {
        ran: pending.len(),
        reused,
        results,
    })
}

/// Prints `text` above the progress bar (or on stderr without one, e.g. into a log file).
fn say(bar: &indicatif::ProgressBar, text: String) {
    if bar.is_hidden() {
        eprintln!("{text}");
    } else {
        bar.println(text);
    }
}

fn progress_bar(show: bool, runs: usize, duration_s: f64) -> indicatif::ProgressBar {
    if !show {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new(runs as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template(&format!(
            "{{spinner}} [{{elapsed_precise}}] {{bar:30}} {{pos}}/{{len}} runs of {duration_s} s · eta {{eta}} · {{msg}}"
        ))
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    bar.enable_steady_tick(Duration::from_millis(250));
    bar
}

/// One line for people about a finished run.
pub fn line(r: &RunResult) -> String {
    if let Some(e) = &r.error {
        return format!("{}: FAILED: {e}", r.id);
    }
    let err = match (r.relmse, r.flip) {
        (Some(e), Some(f)) => format!("relMSE {e:.3}, FLIP {f:.3}"),
        _ => "no sample after the warm-up".into(),
    };
    format!(
        "{}: {err}, age p50 {:.0} ms, {:.2} Mbit/s per client, client frame {:.0} ms ({:.1} fps)",
        r.id, r.age_ms_p50, r.mbps_per_client, r.client_frame_ms_p50, r.fps
    )
}

/// Runs `run` and measures it.
fn measure(
    experiment: &Experiment,
    run: &Run,
    fingerprint: &str,
    out: &Path,
    runtime: &tokio::runtime::Runtime,
    references: &mut References,
    bar: &indicatif::ProgressBar,
) -> anyhow::Result<RunResult> {
    let started = Instant::now();
    let spec = experiment.topology(run, Some(references.exposure))?;
    let file = out.join("topologies").join(format!("{}.toml", run.id()));
    let text = spec.to_toml();
    std::fs::write(&file, &text).with_context(|| format!("writing {}", file.display()))?;
    let registry = cloudlight_actors::registry();
    let plan = cloudlight_runtime::Plan::from_str(&file.display().to_string(), &text, &registry)
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let run_dir = out.join("runs").join(run.id());
    if run_dir.exists() {
        std::fs::remove_dir_all(&run_dir)
            .with_context(|| format!("clearing {}", run_dir.display()))?;
    }
    let report = runtime
        .block_on(cloudlight_runtime::run(
            &plan,
            &registry,
            RunOptions {
                duration: Some(Duration::from_secs_f64(experiment.duration_s)),
                out_dir: Some(run_dir.clone()),
                ..RunOptions::default()
            },
            std::future::pending(),
        ))
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    if report.end == cloudlight_runtime::EndReason::Failed {
        anyhow::bail!(
            "a stage failed (its error is in the log above; metrics in {})",
            run_dir.display()
        );
    }
    let m = &report.metrics;
    let shown: Vec<Shown> = (0..run.clients)
        .map(|i| {
            let name = replica_name(CLIENT, i, run.clients);
            crate::bench::stage_report(m, &name)
        })
        .collect::<anyhow::Result<_>>()?;
    let n = shown.len().max(1) as f64;
    let mean = |f: fn(&Shown) -> f64| shown.iter().map(f).sum::<f64>() / n;
    let max = |f: fn(&Shown) -> f64| shown.iter().map(f).fold(0.0, f64::max);
    let update: Option<f64> = cuts::update_cost(&run.technique)
        .iter()
        .map(|(stage, key)| report_of(m, stage).and_then(|r| number(r, key)))
        .sum();
    let cut = cuts::find(&run.technique, &run.cut);
    let frames_cross = cut.is_some_and(|c| c.frames_cross);
    let cloud_frame_ms = frames_cross
        .then(|| {
            Some(
                number(report_of(m, "render")?, "frame_ms_p50")?
                    + number(report_of(m, "encode")?, "encode_ms_p50")?,
            )
        })
        .flatten();
    let total = crate::bench::wire_mbps(m);
    let mut result = RunResult {
        id: run.id(),
        fingerprint: fingerprint.to_string(),
        technique: run.technique.clone(),
        cut: run.cut.clone(),
        link: run.link.clone(),
        extra_latency_ms: run.extra_latency_ms,
        clients: run.clients,
        client_class: cut.map(|c| c.client),
        frames_cross,
        duration_s: experiment.duration_s,
        error: None,
        age_ms_p50: mean(|s| s.age_ms_p50),
        age_ms_p99: max(|s| s.age_ms_p99),
        server_update_ms: update,
        cloud_frame_ms,
        client_frame_ms_p50: mean(|s| s.frame_ms_p50 + s.decode_ms_p50.unwrap_or(0.0)),
        client_frame_ms_p99: max(|s| s.frame_ms_p99),
        fps: mean(|s| s.frames as f64) / experiment.duration_s,
        mbps_per_client: total / run.clients.max(1) as f64,
        mbps_total: total,
        ..RunResult::default()
    };
    if run.clients > 0 {
        let dir = client_dir(&run_dir, 0, run.clients);
        let recording = dir.join(RECORDING);
        if recording.exists() {
            result.recording = Some(relative(out, &recording));
        }
        bar.set_message(format!("{}: comparing with the reference", run.id()));
        result.samples = samples(
            experiment,
            out,
            &dir,
            references,
            &mut result.samples_before_light,
        )?;
    }
    let k = result.samples.len();
    if k > 0 {
        let avg = |f: fn(&SampleError) -> f64| result.samples.iter().map(f).sum::<f64>() / k as f64;
        result.relmse = Some(avg(|s| s.relmse));
        result.flip = Some(avg(|s| s.flip));
        result.energy_ratio = Some(avg(|s| s.energy_ratio));
    }
    result.wall_s = started.elapsed().as_secs_f64();
    Ok(result)
}

/// `path` relative to `base` (as given when it is not under it).
fn relative(base: &Path, path: &Path) -> String {
    path.strip_prefix(base)
        .unwrap_or(path)
        .display()
        .to_string()
}

/// The errors of the samples client folder `dir` holds, after the warm-up and the first
/// indirect light (samples before it are counted in `dark`).
fn samples(
    experiment: &Experiment,
    out: &Path,
    dir: &Path,
    references: &mut References,
    dark: &mut usize,
) -> anyhow::Result<Vec<SampleError>> {
    let csv = dir.join("samples.csv");
    let text = std::fs::read_to_string(&csv)
        .with_context(|| format!("reading the client's samples {}", csv.display()))?;
    let ref_dir = out.join("reference");
    let mut errors = Vec::new();
    for row in text.lines().skip(1) {
        let cells: Vec<&str> = row.split(',').collect();
        let [_, time, _, age, file] = cells[..] else {
            anyhow::bail!("{}: a line that is not a sample: {row}", csv.display());
        };
        let time_s: f64 = time
            .parse()
            .with_context(|| format!("{}: a time that is not a number: {row}", csv.display()))?;
        if time_s + 1e-9 < experiment.measure.warmup_s || time_s > experiment.duration_s {
            continue;
        }
        let Ok(age_ms) = age.parse::<f64>() else {
            // No indirect light shown yet: the pipeline is still starting (it takes a few
            // round trips), which is not the staleness the experiment measures.
            *dark += 1;
            continue;
        };
        let path = dir.join(file);
        let picture = image::open(&path)
            .with_context(|| format!("reading {}", path.display()))?
            .into_rgb8();
        let e = references.compare(picture.as_raw(), time_s)?;
        let reference = references.picture(time_s, &ref_dir)?;
        errors.push(SampleError {
            time_s,
            age_ms: Some(age_ms),
            relmse: e.relmse,
            flip: e.flip as f64,
            energy_ratio: e.energy_ratio,
            picture: relative(out, &path),
            reference: relative(out, &reference),
        });
    }
    Ok(errors)
}
