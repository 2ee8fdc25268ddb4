//! `msth`: the one command of the toolkit. Errors are reported once, here.

use std::process::ExitCode;

fn main() -> ExitCode {
    quiet_device_select();
    quiet_on_closed_stdout();
    match msth_cli::run(std::env::args_os()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// Mesa's `VK_LAYER_MESA_device_select` (an implicit Vulkan layer that comes with
/// `mesa-vulkan-drivers`) asks the Wayland compositor for the default GPU whenever a Vulkan
/// instance is created, and without a desktop session (`XDG_RUNTIME_DIR` unset: containers, CI,
/// ssh) libwayland prints "error: XDG_RUNTIME_DIR is invalid or not set in the environment." to
/// stderr, once per instance: `msth demo` printed it twice between its steps, an error that is
/// none. Without a session there is no compositor to ask, and msth ranks the adapters itself
/// (`msth_gpu::AdapterPolicy`), so the layer is turned off (`NODEVICE_SELECT=1`) unless the user
/// set `NODEVICE_SELECT` or has a session. First thing in `main`, before any thread exists.
fn quiet_device_select() {
    if std::env::var_os("XDG_RUNTIME_DIR").is_none()
        && std::env::var_os("NODEVICE_SELECT").is_none()
    {
        std::env::set_var("NODEVICE_SELECT", "1");
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
