//! One process per directory: an exclusive advisory lock on a file (`flock`), held until the
//! file is closed, whichever way the process ends. The gateway holds one on its store, the
//! history's writer on its directory and a node on its buffer, so that a second process
//! started on the same files is refused instead of interleaving its writes with the first's.
//!
//! The lock belongs to the open file description: a second `open` of the same file, in this
//! process or another, does not get it while the first is open.

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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_open_is_refused_until_the_first_closes() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("LOCK");
        let open = || {
            File::options()
                .create(true)
                .truncate(false)
                .write(true)
                .open(&path)
                .unwrap()
        };
        let first = open();
        assert!(try_lock_exclusive(&first).unwrap());
        let second = open();
        assert!(!try_lock_exclusive(&second).unwrap());
        drop(first);
        assert!(try_lock_exclusive(&second).unwrap());
    }
}
