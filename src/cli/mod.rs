//! The command line: one module per subcommand, each parsing its options and printing what
//! the libraries compute.

use std::process::ExitCode;

use clap::{Parser, Subcommand};

mod bench;
mod deploy;
mod experiment;
mod kinds;
mod plan;
mod ranges;
mod reference;
mod run;
mod validate;

/// CloudLight-rs: indirect lighting computed on cloud nodes and streamed to clients.
///
/// Logs go to stderr; set RUST_LOG (e.g. RUST_LOG=debug) to change what is shown.
#[derive(Parser)]
#[command(version, about, long_about)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Check a topology file and print where each stage runs and which edges are cut.
    ///
    /// Exits 0 when the file is valid; otherwise prints every problem found, each with file,
    /// line and key, and exits 2.
    Validate(validate::Args),
    /// Run every node of a topology in this process, then print per-stage and per-edge
    /// metrics and write them to OUT/metrics.json.
    ///
    /// Without TOPOLOGY a built-in default runs (see the README). Ctrl-C stops the run
    /// cleanly: sources stop, queued messages are handled, metrics are written.
    Run(run::RunCommand),
    /// Run only the stages placed on one node of a topology (one process per node).
    Node(run::NodeCommand),
    /// List the stage kinds topology files may name, with their ports and message types.
    Kinds,
    /// Describe a scene (triangles, bounds, lights, emitted watts) and what each technique
    /// would allocate for it with its default settings: photon batches per light, occupied
    /// voxels per octree level, light-map texels and bases.
    Plan(plan::Args),
    /// Render the reference images of a scene with the path tracer: full, direct-only and
    /// indirect-only radiance as OpenEXR, plus tone-mapped PNGs.
    Reference(reference::Args),
    /// Run a placement experiment (techniques × cuts × link profiles × added latency ×
    /// client counts) in this process, resuming where an earlier run of it stopped, and
    /// write its report with a recommended cut per link profile and client class; or, with
    /// --emit DIR, only write one topology file per run.
    ///
    /// Exits 2 with every problem of the file (file, line, key) when it is not valid.
    Experiment(experiment::Args),
    /// Generate what an orchestrator needs to run a topology (Kubernetes manifests).
    Deploy {
        #[command(subcommand)]
        to: deploy::DeployCommand,
    },
    /// Measure parts of the system.
    Bench {
        #[command(subcommand)]
        what: bench::BenchCommand,
    },
}

impl Cli {
    /// What is logged unless `RUST_LOG` says: the runtime's progress, except for a sweep of
    /// many runs (`experiment`), which shows a progress bar and a line per run instead.
    pub fn default_log_filter(&self) -> &'static str {
        match self.command {
            Command::Experiment(_) => "warn",
            _ => "warn,cloudlight=info,cloudlight_runtime=info,cloudlight_actors=info",
        }
    }

    /// Runs the command; the exit code says how it went (0 ok, 2 bad input, 3 a stage
    /// failed, 4 a transport bench found damage, 5 the network failed, 1 anything else).
    pub fn run(self) -> ExitCode {
        match self.command {
            Command::Validate(a) => validate::run(a),
            Command::Run(a) => run::run(a),
            Command::Node(a) => run::node(a),
            Command::Kinds => kinds::run(),
            Command::Plan(a) => plan::run(a),
            Command::Reference(a) => reference::run(a),
            Command::Experiment(a) => experiment::run(a),
            Command::Deploy { to } => deploy::run(to),
            Command::Bench { what } => bench::run(what),
        }
    }
}

/// A table in the CLI's one style with this header.
fn table<const N: usize>(header: [&str; N]) -> comfy_table::Table {
    let mut t = comfy_table::Table::new();
    t.load_preset(comfy_table::presets::UTF8_FULL_CONDENSED)
        .set_header(header);
    t
}

/// Prints an error with its causes and exits 1.
fn report_error(e: anyhow::Error) -> ExitCode {
    eprintln!("error: {e:#}");
    ExitCode::FAILURE
}

/// The multi-threaded tokio runtime every command runs on.
fn async_runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(|e| anyhow::anyhow!("cannot start the async runtime: {e}"))
}

/// Loads a scene, or says why not (exit 2: the input is at fault).
fn load_scene(spec: &str) -> Result<cloudlight::scenes::Scene, ExitCode> {
    cloudlight::scenes::load(spec).map_err(|e| {
        eprintln!("error: {e}");
        ExitCode::from(2)
    })
}
