//! `cloudlight`: validate topologies, run them in one process or one node of them, describe
//! scenes, render references and measure the system. One module per subcommand ([`cli`]).

use std::process::ExitCode;

use clap::Parser;

mod cli;

/// mimalloc keeps freed memory for reuse where glibc's allocator maps and unmaps every
/// large block: a BVH rebuilt each update (moving geometry) otherwise faults its ~25 MB of
/// nodes, blocks and scratch in afresh, page by page (measured on city:250000, one thread:
/// 61 -> 55 ms a build; Embree keeps its own pools likewise).
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> ExitCode {
    let cli = cli::Cli::parse();
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(cli.default_log_filter()));
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .init();
    cli.run()
}
