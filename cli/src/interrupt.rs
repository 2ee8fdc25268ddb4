//! Ctrl-C during `msth train`: the first asks the run to stop after the step in progress and
//! write a checkpoint (the run then says how to resume); a second stops the process at once,
//! keeping the last checkpoint written.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Once;

/// A Ctrl-C arrived since [`arm`].
static PENDING: AtomicBool = AtomicBool::new(false);
static LISTENING: Once = Once::new();

/// Starts listening for Ctrl-C (once per process) and forgets earlier ones.
pub(crate) fn arm() {
    LISTENING.call_once(|| {
        let listener = std::thread::Builder::new()
            .name("msth-ctrl-c".into())
            .spawn(|| {
                let Ok(rt) = tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .build()
                else {
                    return;
                };
                rt.block_on(async {
                    while tokio::signal::ctrl_c().await.is_ok() {
                        if PENDING.swap(true, Ordering::SeqCst) {
                            eprintln!("\nCtrl-C again: stopping now (the last checkpoint is kept)");
                            std::process::exit(130);
                        }
                        eprintln!(
                            "\nCtrl-C: finishing this step and writing a checkpoint (Ctrl-C again \
                             stops at once, without it)"
                        );
                    }
                });
            });
        if let Err(e) = listener {
            eprintln!("note: Ctrl-C will stop training without a last checkpoint ({e})");
        }
    });
    PENDING.store(false, Ordering::SeqCst);
}

/// Whether Ctrl-C was pressed since [`arm`].
pub(crate) fn pending() -> bool {
    PENDING.load(Ordering::SeqCst)
}
