//! `cloudlight experiment FILE --emit DIR`.

use std::path::PathBuf;
use std::process::ExitCode;

use cloudlight::experiment::{Experiment, cuts};

/// Options of `experiment`.
#[derive(clap::Args)]
pub struct Args {
    /// The experiment file (TOML): scene, techniques and their cuts, link profiles, client
    /// counts, duration.
    file: PathBuf,
    /// Write one topology file per run into DIR (`<technique>-<cut>-<link>-<N>c.toml`), each
    /// checked as `cloudlight validate` would; run any of them with `cloudlight run`.
    #[arg(long, value_name = "DIR")]
    emit: PathBuf,
}

pub fn run(args: Args) -> ExitCode {
    let experiment = match Experiment::load(&args.file) {
        Ok(e) => e,
        Err(errors) => {
            eprintln!("{errors}");
            return ExitCode::from(2);
        }
    };
    if let Err(e) = std::fs::create_dir_all(&args.emit) {
        eprintln!("error: cannot create {}: {e}", args.emit.display());
        return ExitCode::FAILURE;
    }
    let registry = cloudlight::actors::registry();
    let runs = experiment.runs();
    println!(
        "experiment `{}`: {} runs of {} s on `{}`",
        experiment.name,
        runs.len(),
        experiment.duration_s,
        experiment.scene
    );
    for run in &runs {
        let about = cuts::cuts(&run.technique)
            .and_then(|c| c.iter().find(|c| c.name == run.cut))
            .map_or("", |c| c.about);
        let spec = match experiment.topology(run) {
            Ok(s) => s,
            Err(e) => {
                eprintln!("error: {}: {e:#}", run.id());
                return ExitCode::FAILURE;
            }
        };
        let path = args.emit.join(format!("{}.toml", run.id()));
        let text = format!(
            "# {}: {} ({} over `{}`, {} clients)\n{}",
            run.id(),
            about,
            run.technique,
            run.link,
            run.clients,
            spec.to_toml()
        );
        if let Err(errors) =
            cloudlight::runtime::Plan::from_str(&path.display().to_string(), &text, &registry)
        {
            eprintln!(
                "error: the topology of {} is not valid:\n{errors}",
                run.id()
            );
            return ExitCode::FAILURE;
        }
        if let Err(e) = std::fs::write(&path, text) {
            eprintln!("error: cannot write {}: {e}", path.display());
            return ExitCode::FAILURE;
        }
        println!("  {}", path.display());
    }
    ExitCode::SUCCESS
}
