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
            println!("valid");
            ExitCode::SUCCESS
        }
        Err(errors) => {
            eprintln!("{errors}");
            ExitCode::from(2)
        }
    }
}
