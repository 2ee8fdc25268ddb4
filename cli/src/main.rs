//! `msth`: the one command of the toolkit. Errors are reported once, here.

use std::process::ExitCode;

fn main() -> ExitCode {
    match msth_cli::run(std::env::args_os()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
