//! What Triax's tests and benches share, in one place:
//!
//! - [`browser`]: a WebDriver client for headless Chromium (the console's tests);
//! - [`child`]: the test binary run again as a child process (a gateway or a node one can kill);
//! - [`proc`]: what a bench reads of a process from /proc (CPU, context switches, memory).

pub mod browser;
pub mod child;
pub mod proc;

use std::time::Duration;

/// The one deadline every wait of the tests shares: only a real failure reaches it.
pub const TIMEOUT: Duration = Duration::from_secs(60);

/// A loopback TCP port free now (the OS's choice for port 0).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free loopback port")
}
