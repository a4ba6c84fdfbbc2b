//! `cloudlight validate TOPOLOGY`.

use std::path::PathBuf;
use std::process::ExitCode;

use cloudlight::runtime::Plan;

/// Options of `validate`.
#[derive(clap::Args)]
pub struct Args {
    /// The topology file (TOML).
    topology: PathBuf,
}

pub fn run(args: Args) -> ExitCode {
    let registry = cloudlight::actors::registry();
    match Plan::load(&args.topology, &registry) {
        Ok(plan) => {
            println!("{}", plan.summary());
            for w in &plan.warnings {
                eprintln!("warning: {w}");
            }
            // The scene is what every stage loads first: check it as a run would.
            let scene = match cloudlight::scenes::load(&plan.topology.scene) {
                Ok(s) => s,
                Err(e) => {
                    eprintln!("{}: `scene`: {e}", args.topology.display());
                    return ExitCode::from(2);
                }
            };
            if let Err(errors) = plan.check_scene(&registry, &scene) {
                eprintln!("{errors}");
                return ExitCode::from(2);
            }
            println!("valid");
            ExitCode::SUCCESS
        }
        Err(errors) => {
            eprintln!("{errors}");
            ExitCode::from(2)
        }
    }
}
