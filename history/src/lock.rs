//! An exclusive advisory lock on a file (`flock`), held until the file is closed: one writer per
//! directory, even across processes.

use std::fs::File;
use std::os::fd::AsRawFd;

/// Takes the lock if free: `Ok(false)` when another open file description holds it.
pub fn try_lock_exclusive(file: &File) -> std::io::Result<bool> {
    // SAFETY: `flock` reads only the descriptor, which `file` keeps open for the call.
    let r = unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
    if r == 0 {
        return Ok(true);
    }
    let e = std::io::Error::last_os_error();
    match e.raw_os_error() {
        Some(libc::EWOULDBLOCK) => Ok(false),
        _ => Err(e),
    }
}
