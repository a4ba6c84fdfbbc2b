//! `cloudlight bench fronts`: the Pareto fronts of saved photon `bench quality` runs in one
//! plot (before and after a change: another commit's build, other knobs, another seed).

use std::path::PathBuf;
use std::process::ExitCode;

/// Options of `bench fronts`.
#[derive(clap::Args)]
pub struct Args {
    /// Runs: a photon `bench quality` run's `quality.json`, as `PATH` or `PATH=LABEL`
    /// (default label: the folder holding it). A sweep's file gives one front per
    /// combination.
    #[arg(required = true, value_name = "PATH[=LABEL]")]
    runs: Vec<String>,
    /// Where to write the plot (PNG).
    #[arg(long, default_value = "fronts.png")]
    out: PathBuf,
}

/// `PATH=LABEL`, or `PATH` labelled by its folder's name.
fn run_and_label(arg: &str) -> (PathBuf, String) {
    if let Some((path, label)) = arg.rsplit_once('=')
        && !label.is_empty()
        && !label.contains('/')
    {
        return (PathBuf::from(path), label.to_string());
    }
    let path = PathBuf::from(arg);
    let label = path
        .parent()
        .and_then(|p| p.file_name())
        .map_or_else(|| arg.to_string(), |n| n.to_string_lossy().into_owned());
    (path, label)
}

pub fn run(a: Args) -> ExitCode {
    let runs: Vec<_> = a.runs.iter().map(|r| run_and_label(r)).collect();
    match cloudlight::bench::photons::fronts(&runs, &a.out) {
        Ok((sets, png)) => {
            println!("| front | photons | Mbit/s | update ms | relMSE |\n|---|---|---|---|---|");
            for (label, points) in &sets {
                for p in points {
                    println!(
                        "| {label} | {} | {:.2} | {:.2} | {:.4} |",
                        p.photons, p.mbps, p.update_ms, p.relmse
                    );
                }
            }
            println!("\nwrote {}", png.display());
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(2)
        }
    }
}
