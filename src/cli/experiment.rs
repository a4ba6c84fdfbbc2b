//! `cloudlight experiment FILE [--out DIR] [--emit DIR | --print]`.

use std::path::PathBuf;
use std::process::ExitCode;

use cloudlight::experiment::reference::References;
use cloudlight::experiment::run::{RunSettings, line};
use cloudlight::experiment::{Experiment, cuts, report};

/// Options of `experiment`.
#[derive(clap::Args)]
pub struct Args {
    /// The experiment file (TOML): scene, techniques and their cuts, link profiles, client
    /// counts, duration.
    file: PathBuf,
    /// Output folder: `results.jsonl` (one line per run, appended as each ends), the report
    /// (`report.md`, `report.html`, PNG plots), each run's topology, metrics, samples and
    /// recording. Default: `runs/experiment-<name>`.
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Run each run for this many seconds instead of the file's `duration_s`.
    #[arg(long, value_name = "SECONDS")]
    duration: Option<f64>,
    /// Forget the results already in the output folder and run every run again (by default
    /// runs already measured with the same topology and settings are not run again).
    #[arg(long)]
    fresh: bool,
    /// Only write one topology file per run into DIR (`<technique>-<cut>-<link>-<N>c.toml`),
    /// each checked as `cloudlight validate` would; run any of them with `cloudlight run`.
    #[arg(long, value_name = "DIR", conflicts_with = "print")]
    emit: Option<PathBuf>,
    /// Only print each run's topology.
    #[arg(long)]
    print: bool,
}

pub fn run(args: Args) -> ExitCode {
    let mut experiment = match Experiment::load(&args.file) {
        Ok(e) => e,
        Err(errors) => {
            eprintln!("{errors}");
            return ExitCode::from(2);
        }
    };
    if let Some(d) = args.duration {
        if !(d > 0.0 && d <= cloudlight::experiment::MAX_DURATION_S) {
            eprintln!(
                "error: --duration {d} is out of range: (0, {}] s",
                cloudlight::experiment::MAX_DURATION_S
            );
            return ExitCode::from(2);
        }
        experiment.duration_s = d;
    }
    let runs = experiment.runs();
    eprintln!(
        "experiment `{}`: {} runs of {} s on `{}`",
        experiment.name,
        runs.len(),
        experiment.duration_s,
        experiment.scene
    );
    if args.emit.is_some() || args.print {
        return emit(&experiment, args.emit.as_deref());
    }
    let out = args
        .out
        .unwrap_or_else(|| PathBuf::from("runs").join(format!("experiment-{}", experiment.name)));
    let settings = RunSettings {
        fresh: args.fresh,
        progress: true,
    };
    let outcome = match cloudlight::experiment::run::run(&experiment, &out, &settings) {
        Ok(o) => o,
        Err(e) => return super::report_error(e),
    };
    let report = match report::write(&experiment, &outcome.results, &out) {
        Ok(r) => r,
        Err(e) => return super::report_error(e),
    };
    println!(
        "{} runs: {} run now, {} reused from {}",
        outcome.results.len(),
        outcome.ran,
        outcome.reused,
        out.join(cloudlight::experiment::run::RESULTS).display()
    );
    for r in &outcome.results {
        println!("  {}", line(r));
    }
    println!("recommendation:");
    for r in &report.recommendations {
        println!(
            "  {} / {} client: {} — {}",
            r.link,
            r.client.name(),
            r.choice.as_deref().unwrap_or("none"),
            r.reason
        );
    }
    println!(
        "report: {} and {}",
        report.markdown.display(),
        report.html.display()
    );
    let failed = outcome.results.iter().filter(|r| !r.ok()).count();
    if failed > 0 {
        eprintln!("error: {failed} run(s) failed (see the report); run again to retry them");
        return ExitCode::FAILURE;
    }
    ExitCode::SUCCESS
}

/// Writes (or prints) each run's topology, with the exposure the experiment would use.
fn emit(experiment: &Experiment, dir: Option<&std::path::Path>) -> ExitCode {
    if let Some(dir) = dir
        && let Err(e) = std::fs::create_dir_all(dir)
    {
        eprintln!("error: cannot create {}: {e}", dir.display());
        return ExitCode::FAILURE;
    }
    let scene = match cloudlight::scenes::load(&experiment.scene) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(2);
        }
    };
    let exposure = References::new(scene, &experiment.measure, 0.0).exposure;
    let registry = cloudlight::actors::registry();
    for run in &experiment.runs() {
        let about = cuts::find(&run.technique, &run.cut).map_or("", |c| c.about);
        let spec = match experiment.topology(run, Some(exposure)) {
            Ok(s) => s,
            Err(e) => {
                eprintln!("error: {}: {e:#}", run.id());
                return ExitCode::FAILURE;
            }
        };
        let name = format!("{}.toml", run.id());
        let text = format!(
            "# {}: {} ({} over `{}`, {} clients)\n{}",
            run.id(),
            about,
            run.technique,
            run.link,
            run.clients,
            spec.to_toml()
        );
        let shown = dir.map_or(name.clone(), |d| d.join(&name).display().to_string());
        if let Err(errors) = cloudlight::runtime::Plan::from_str(&shown, &text, &registry) {
            eprintln!(
                "error: the topology of {} is not valid:\n{errors}",
                run.id()
            );
            return ExitCode::FAILURE;
        }
        match dir {
            Some(d) => {
                if let Err(e) = std::fs::write(d.join(&name), text) {
                    eprintln!("error: cannot write {shown}: {e}");
                    return ExitCode::FAILURE;
                }
                println!("  {shown}");
            }
            None => println!("{text}"),
        }
    }
    ExitCode::SUCCESS
}
