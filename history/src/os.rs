//! The call to the C library the history makes itself: page-cache advice (`posix_fadvise`).
//! Its lock, one writer per directory even across processes, is `triax_lockfile`'s.

use std::fs::File;
use std::os::fd::AsRawFd;

/// Tells the kernel that `from..to` of `file` will not be read soon, so that its page cache pages
/// go back to the free list and the next writes reuse them: on a machine whose fresh pages are
/// costly to touch (a virtual machine, measured in BENCHMARKS.md), writing into recycled pages is
/// the cheaper half of the history's cost. Advice only: a failure changes nothing but speed.
pub fn drop_cached(file: &File, from: u64, to: u64) {
    let (Ok(offset), Ok(len)) = (i64::try_from(from), i64::try_from(to.saturating_sub(from)))
    else {
        return;
    };
    // SAFETY: `posix_fadvise` reads only the descriptor, which `file` keeps open for the call.
    unsafe {
        libc::posix_fadvise(file.as_raw_fd(), offset, len, libc::POSIX_FADV_DONTNEED);
    }
}
