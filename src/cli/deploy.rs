//! `cloudlight deploy kubernetes TOPOLOGY --out DIR`.

use std::path::PathBuf;
use std::process::ExitCode;

use cloudlight::deploy;

/// What to deploy to.
#[derive(clap::Subcommand)]
pub enum DeployCommand {
    /// Write Kubernetes manifests for a topology: per node a headless Service and a
    /// one-replica StatefulSet running `cloudlight node` (UDP transport port, metrics port,
    /// readiness from /healthz, Prometheus annotations), the topology in a ConfigMap with the
    /// pods' DNS names as addresses, the secret in a Secret; and a README.md saying how to
    /// apply them.
    Kubernetes(Args),
}

/// Options of `deploy kubernetes`.
#[derive(clap::Args)]
pub struct Args {
    /// The topology file (TOML).
    topology: PathBuf,
    /// Folder for the manifests (JSON, one object per file) and their README.md.
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Container image the pods run (built from this repository's Dockerfile).
    #[arg(long, default_value = "cloudlight:latest")]
    image: String,
    /// Namespace of every object.
    #[arg(long, default_value = "cloudlight")]
    namespace: String,
}

pub fn run(command: DeployCommand) -> ExitCode {
    let DeployCommand::Kubernetes(args) = command;
    let registry = cloudlight::actors::registry();
    let plan = match cloudlight::runtime::Plan::load(&args.topology, &registry) {
        Ok(p) => p,
        Err(errors) => {
            eprintln!("{errors}");
            return ExitCode::from(2);
        }
    };
    let options = deploy::Options {
        image: args.image,
        namespace: args.namespace,
    };
    let deployment = match deploy::kubernetes(&plan, &args.topology, &options, &args.out) {
        Ok(d) => d,
        Err(e) => return super::report_error(e),
    };
    // The topology the pods run is checked as `validate` would (with a stand-in for the
    // secret the pods read from their environment).
    let check = deployment.topology.replace(
        &format!("secret_env = \"{}\"", deploy::SECRET_ENV),
        "secret = \"stand-in\"",
    );
    if let Err(errors) = cloudlight::runtime::Plan::from_str("topology.toml", &check, &registry) {
        eprintln!("error: the deployed topology is not valid:\n{errors}");
        return ExitCode::FAILURE;
    }
    for d in &deployment.nodes {
        println!("node {} -> {} (UDP {})", d.node, d.address, d.port);
    }
    for f in &deployment.files {
        println!("  {}", f.display());
    }
    println!(
        "apply with: kubectl apply -f {} (see its README.md)",
        args.out.display()
    );
    ExitCode::SUCCESS
}
