//! `cloudlight kinds`.

use std::process::ExitCode;

pub fn run() -> ExitCode {
    for k in cloudlight::actors::registry().kinds() {
        println!("{} (technique {}): {}", k.name, k.technique, k.summary);
        for p in &k.inputs {
            match p.default {
                Some(d) => println!(
                    "  in  {:<12} {} [default {} {}]",
                    p.name,
                    p.ty.name(),
                    d.policy,
                    d.capacity
                ),
                None => println!("  in  {:<12} {}", p.name, p.ty.name()),
            }
        }
        for p in &k.outputs {
            println!("  out {:<12} {}", p.name, p.ty.name());
        }
    }
    ExitCode::SUCCESS
}
