//! Child processes of the test binary itself.
//!
//! A test that needs a gateway (or a node) it can kill with SIGKILL runs one in a process of its
//! own: the test binary again, made to run a single `#[ignore]`d test that is that process's
//! entry point (`<exe> --ignored --exact <entry> --nocapture`), with what it needs in its
//! environment. The entry runs its service with [`run_until_stdin_closes`]: closing the child's
//! standard input is the clean stop (as SIGTERM is for the binaries), killing it the crash.

use std::ffi::OsStr;
use std::future::Future;
use std::path::Path;
use std::pin::Pin;
use std::process::{Child, Command, ExitStatus, Stdio};

/// A child process of this test binary running the entry point `entry` (the test's path, as
/// `cargo test` names it: `history::gateway_process`).
pub struct Entry {
    command: Command,
}

impl Entry {
    pub fn new(entry: &str) -> Entry {
        let exe = std::env::current_exe().expect("the test binary's path");
        let mut command = Command::new(exe);
        command
            .args(["--ignored", "--exact", entry, "--nocapture"])
            .stdin(Stdio::piped())
            .stdout(Stdio::null())
            .stderr(Stdio::null());
        Entry { command }
    }

    pub fn env(mut self, key: impl AsRef<OsStr>, value: impl AsRef<OsStr>) -> Entry {
        self.command.env(key, value);
        self
    }

    /// Keeps the child's log (its standard error) in `path`.
    pub fn log_to(mut self, path: &Path) -> Entry {
        let log = std::fs::File::create(path)
            .unwrap_or_else(|e| panic!("the child's log {}: {e}", path.display()));
        self.command.stderr(log);
        self
    }

    /// Starts it; its standard input is a pipe, closed by [`stop_cleanly`].
    pub fn spawn(mut self) -> Child {
        self.command.spawn().expect("the test binary starts again")
    }
}

/// Stops a child of [`Entry::spawn`] the clean way (its standard input closed) and waits for it.
pub fn stop_cleanly(child: &mut Child) -> ExitStatus {
    drop(child.stdin.take());
    child.wait().expect("the child ends")
}

/// Kills a child with SIGKILL (no shutdown, no last flush) and reaps it.
pub fn kill_9(child: &mut Child) {
    // Err only when it has ended already, which `wait` then reports.
    let _ = child.kill();
    let _ = child.wait();
}

/// The child's side: runs `service` on a multi-threaded Tokio runtime of its own, handing it a
/// future that completes when this process's standard input closes.
pub fn run_until_stdin_closes<F, Fut>(service: F) -> Fut::Output
where
    F: FnOnce(Pin<Box<dyn Future<Output = ()> + Send>>) -> Fut,
    Fut: Future,
{
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("a runtime for the child process");
    let stdin_closed = Box::pin(async {
        let watcher = tokio::task::spawn_blocking(|| {
            use std::io::Read;
            let mut buf = [0u8; 64];
            while matches!(std::io::stdin().read(&mut buf), Ok(n) if n > 0) {}
        });
        // Err only if the watcher panicked, which reading stdin does not.
        let _ = watcher.await;
    });
    runtime.block_on(service(stdin_closed))
}
