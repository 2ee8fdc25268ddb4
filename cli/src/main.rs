//! `msth`: the one command of the toolkit. Errors are reported once, here.

use std::process::ExitCode;

fn main() -> ExitCode {
    quiet_on_closed_stdout();
    match msth_cli::run(std::env::args_os()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// `msth inspect FILE | head` closes the pipe before `msth` has printed everything; `println!`
/// then panics with "failed printing to stdout: Broken pipe". A reader that stopped reading is
/// not an error of ours: exit quietly with success, as other command-line tools do. Every other
/// panic keeps the default report.
fn quiet_on_closed_stdout() {
    let default = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let payload = info.payload();
        let message = payload
            .downcast_ref::<String>()
            .map(String::as_str)
            .or_else(|| payload.downcast_ref::<&str>().copied())
            .unwrap_or("");
        if message.starts_with("failed printing to stdout") && message.contains("Broken pipe") {
            std::process::exit(0);
        }
        default(info)
    }));
}
