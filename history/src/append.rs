//! Appending to a segment's log without passing every byte through the page cache.
//!
//! A history is written once and read rarely, a few seconds of it at a time. Through the page
//! cache each byte is copied into a page the kernel allocates for it, and on a virtual machine a
//! page the guest has not touched before costs a fault in the host as well: measured here,
//! 2.5 ns of system time a byte into fresh pages and 0.45–0.65 ns into recycled ones, against
//! 0.2 ns for direct writes of 1 MiB (BENCHMARKS.md, "History on and off"). A direct write has
//! a cost of its own per request (about 60 µs of the caller's CPU here, the device's round trip
//! through the hypervisor), so it pays only when it is large. Hence: long runs of whole pages
//! go straight to the disk (`O_DIRECT`) from a staging buffer of [`STAGE_BYTES`]; what lies
//! before the first page boundary and after the last, and every write shorter than
//! [`DIRECT_MIN`], goes through the page cache as before. A building at its pace (about 1.2 MB a second at a thousand
//! sensors) writes one direct request a flush.
//!
//! **Invariant:** no page of the log is written both ways. A direct write starts at the page
//! boundary at or after everything written so far and ends on one; the bytes before it (the rest
//! of a page the page cache already holds) and after it go through the page cache. So the
//! kernel never has to reconcile a cached page with a direct write over it, and a reader, which
//! reads through the page cache, sees what was written.
//!
//! Durability is the caller's: nothing here syncs. Where direct I/O is refused (tmpfs, some
//! network file systems answer `EINVAL`), the appender goes through the page cache from then on.

use std::fs::{File, OpenOptions};
use std::io::{self, Write};
use std::os::unix::fs::{FileExt, OpenOptionsExt};
use std::path::Path;

/// Alignment of a direct write's file offset, length and memory: a page suits devices with
/// 512-byte and 4 KiB logical blocks alike.
pub const ALIGN: usize = 4096;
/// Bytes gathered before a direct write.
pub const STAGE_BYTES: usize = 1 << 20;
/// Shortest run of whole pages written directly: below it the request's own cost is more than
/// the page cache's copy.
pub const DIRECT_MIN: usize = 128 << 10;

/// Appends to one log file (see the module's documentation).
#[derive(Debug)]
pub struct Appender {
    /// The log, opened for appending, through the page cache.
    file: File,
    /// The same file opened for direct I/O, while the file system allows it.
    direct: Option<File>,
    /// Bytes appended: written to the file or staged.
    appended: u64,
    /// Allocated at the first write long enough to go direct, kept after.
    stage: Option<Stage>,
    /// Bytes written directly since [`take_direct_bytes`](Self::take_direct_bytes).
    direct_bytes: u64,
}

/// Bytes on their way to a direct write, laid out so that a page-aligned file offset falls on a
/// page-aligned address. Handed from a segment to the next ([`Appender::take_stage`]): a fresh
/// megabyte a segment would be fresh pages to fault in.
#[derive(Debug)]
pub struct Stage {
    /// Fixed size, never grows: `origin` stays aligned.
    buf: Vec<u8>,
    /// Index of the first page-aligned address in `buf`.
    origin: usize,
    /// File offset of the first staged byte.
    base: u64,
    len: usize,
}

impl Stage {
    fn new(base: u64) -> Stage {
        let buf = vec![0u8; STAGE_BYTES + 2 * ALIGN];
        let addr = buf.as_ptr() as usize;
        let origin = addr.next_multiple_of(ALIGN) - addr;
        Stage {
            buf,
            origin,
            base,
            len: 0,
        }
    }

    /// Index in `buf` of the first staged byte: its file offset's place within a page.
    fn start(&self) -> usize {
        self.origin + (self.base % ALIGN as u64) as usize
    }

    fn room(&self) -> usize {
        STAGE_BYTES - self.len
    }

    fn push(&mut self, bytes: &[u8]) {
        let at = self.start() + self.len;
        self.buf[at..at + bytes.len()].copy_from_slice(bytes);
        self.len += bytes.len();
    }
}

impl Appender {
    /// Appends to `file` (new and empty, opened with `append`), directly as well when the file
    /// system allows it and `direct` is asked; with `stage` if one is at hand.
    pub fn new(file: File, path: &Path, direct: bool, stage: Option<Stage>) -> Appender {
        let direct = direct
            .then(|| {
                OpenOptions::new()
                    .write(true)
                    .custom_flags(libc::O_DIRECT)
                    .open(path)
                    .ok()
            })
            .flatten();
        Appender {
            file,
            direct,
            appended: 0,
            stage: stage.filter(|s| s.len == 0),
            direct_bytes: 0,
        }
    }

    /// Whether long runs still go direct.
    pub fn is_direct(&self) -> bool {
        self.direct.is_some()
    }

    /// The staging buffer, for the next log, once everything staged is written
    /// ([`finish`](Self::finish)).
    pub fn take_stage(&mut self) -> Option<Stage> {
        self.stage.take_if(|s| s.len == 0)
    }

    /// Bytes written directly since the last call.
    pub fn take_direct_bytes(&mut self) -> u64 {
        std::mem::take(&mut self.direct_bytes)
    }

    /// Bytes appended so far, staged or written.
    pub fn appended(&self) -> u64 {
        self.appended
    }

    /// Appends `bufs` in order. Short runs are written at once; long ones may stay staged in
    /// part until [`finish`](Self::finish).
    pub fn append(&mut self, bufs: &[Vec<u8>]) -> io::Result<()> {
        let total: usize = bufs.iter().map(Vec::len).sum();
        let staged = self.stage.as_ref().map_or(0, |s| s.len);
        if staged == 0 && (self.direct.is_none() || total < DIRECT_MIN) {
            write_all_vectored(&mut self.file, bufs)?;
            self.appended += total as u64;
            return Ok(());
        }
        let appended = self.appended;
        let stage = self.stage.get_or_insert_with(|| Stage::new(appended));
        if stage.len == 0 {
            stage.base = appended;
        }
        for buf in bufs {
            let mut rest = &buf[..];
            while !rest.is_empty() {
                // Allocated above; `drain` keeps it.
                let stage = self.stage.as_mut().expect("stage allocated above");
                let n = rest.len().min(stage.room());
                stage.push(&rest[..n]);
                rest = &rest[n..];
                self.appended += n as u64;
                if stage.room() == 0 {
                    self.drain(false)?;
                }
            }
        }
        Ok(())
    }

    /// Writes whatever is staged: after it the file holds every byte appended.
    pub fn finish(&mut self) -> io::Result<()> {
        self.drain(true)
    }

    pub fn sync_data(&self) -> io::Result<()> {
        self.file.sync_data()
    }

    /// Writes the staged bytes: the whole pages among them directly when they are many, and
    /// the rest through the page cache; unless `all`, the part after the last page boundary
    /// stays staged, the start of the next direct run.
    fn drain(&mut self, all: bool) -> io::Result<()> {
        let Some(stage) = self.stage.as_mut() else {
            return Ok(());
        };
        if stage.len == 0 {
            return Ok(());
        }
        let first = stage.base;
        let end = first + stage.len as u64;
        let a = first.next_multiple_of(ALIGN as u64);
        let b = end - end % ALIGN as u64;
        let run = if self.direct.is_some() && b > a {
            (b - a) as usize
        } else {
            0
        };
        let s = stage.start();
        if run < DIRECT_MIN {
            self.file.write_all(&stage.buf[s..s + stage.len])?;
            stage.base = end;
            stage.len = 0;
            return Ok(());
        }
        let head = (a - first) as usize;
        let tail = (end - b) as usize;
        self.file.write_all(&stage.buf[s..s + head])?;
        let at = s + head;
        self.direct_bytes += write_direct(
            &mut self.direct,
            &mut self.file,
            &stage.buf[at..at + run],
            a,
        )? as u64;
        let at = at + run;
        if all {
            self.file.write_all(&stage.buf[at..at + tail])?;
            stage.base = end;
            stage.len = 0;
        } else {
            stage.buf.copy_within(at..at + tail, stage.origin);
            stage.base = b;
            stage.len = tail;
        }
        Ok(())
    }
}

/// Writes `bytes` at `at`, the end of the file, directly; what the file system refuses to take
/// directly (`EINVAL`) goes through the page cache, and direct writes stop for good. Returns the
/// bytes written directly.
fn write_direct(
    direct: &mut Option<File>,
    file: &mut File,
    bytes: &[u8],
    at: u64,
) -> io::Result<usize> {
    let mut done = 0;
    while done < bytes.len() {
        let Some(d) = direct.as_ref() else { break };
        match d.write_at(&bytes[done..], at + done as u64) {
            Ok(0) => return Err(io::ErrorKind::WriteZero.into()),
            Ok(n) => done += n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) if e.raw_os_error() == Some(libc::EINVAL) => *direct = None,
            Err(e) => return Err(e),
        }
    }
    // Appending: the file ends where the direct bytes did.
    file.write_all(&bytes[done..])?;
    Ok(done)
}

/// Writes every buffer, in order, in as few system calls as the kernel allows.
fn write_all_vectored(file: &mut File, bufs: &[Vec<u8>]) -> io::Result<()> {
    // At most this many slices a call (the kernel's IOV_MAX is 1024).
    const IOV: usize = 1024;
    for chunk in bufs.chunks(IOV) {
        let mut slices: Vec<io::IoSlice<'_>> = chunk.iter().map(|b| io::IoSlice::new(b)).collect();
        let mut rest = &mut slices[..];
        while !rest.is_empty() {
            let n = file.write_vectored(rest)?;
            if n == 0 {
                return Err(io::ErrorKind::WriteZero.into());
            }
            io::IoSlice::advance_slices(&mut rest, n);
        }
    }
    Ok(())
}

/// Whether the file system under `dir` takes direct writes (for tests and the bench's report).
pub fn direct_supported(dir: &Path) -> bool {
    let path = dir.join(".direct-probe");
    let ok = OpenOptions::new()
        .create(true)
        .truncate(true)
        .write(true)
        .custom_flags(libc::O_DIRECT)
        .open(&path)
        .is_ok();
    let _ = std::fs::remove_file(&path);
    ok
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bytes(n: usize, seed: u64) -> Vec<u8> {
        let mut x = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
        (0..n)
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                x as u8
            })
            .collect()
    }

    fn appender(dir: &Path, direct: bool) -> (Appender, std::path::PathBuf) {
        let path = dir.join("log");
        let file = OpenOptions::new()
            .create_new(true)
            .append(true)
            .open(&path)
            .unwrap();
        (Appender::new(file, &path, direct, None), path)
    }

    /// Appends writes of the given sizes, finishing after each group, and checks the file
    /// against the bytes appended; true if some run went direct.
    fn round_trip(dir: &Path, groups: &[&[usize]], direct: bool) -> bool {
        let (mut a, path) = appender(dir, direct);
        let mut want = Vec::new();
        let mut seed = 0;
        for group in groups {
            let bufs: Vec<Vec<u8>> = group
                .iter()
                .map(|&n| {
                    seed += 1;
                    bytes(n, seed)
                })
                .collect();
            bufs.iter().for_each(|b| want.extend_from_slice(b));
            a.append(&bufs).unwrap();
            assert_eq!(a.appended(), want.len() as u64);
            a.finish().unwrap();
            a.sync_data().unwrap();
            let got = std::fs::read(&path).unwrap();
            assert_eq!(got.len(), want.len(), "length after {group:?}");
            assert!(got == want, "contents after {group:?}");
        }
        let went_direct = a.is_direct() && a.stage.is_some();
        std::fs::remove_file(&path).unwrap();
        went_direct
    }

    const SHAPES: &[&[&[usize]]] = &[
        // Short writes only: the page cache.
        &[&[10, 300], &[4000], &[5000, 1]],
        // A long run starting mid-page, then short and long ones alternating.
        &[&[777], &[300_000], &[12], &[ALIGN], &[200_000, 3, 70_000]],
        // More than a stage in one call, in frames of a block's size and odd ones.
        &[&[1 << 20, 1 << 20, 5, 1 << 20], &[1]],
        &[&[3 * STAGE_BYTES + 17]],
        // Exactly page-aligned runs.
        &[&[DIRECT_MIN], &[2 * DIRECT_MIN], &[STAGE_BYTES]],
    ];

    #[test]
    fn every_byte_lands_in_order_whichever_way_it_goes() {
        let dir = tempfile::tempdir().unwrap();
        let mut direct_somewhere = false;
        for shape in SHAPES {
            direct_somewhere |= round_trip(dir.path(), shape, true);
            round_trip(dir.path(), shape, false);
        }
        // The test directory is on the disk's file system, which takes direct writes: had it
        // not, the long runs above went through the page cache and this says so.
        if direct_supported(dir.path()) {
            assert!(direct_somewhere, "no run went direct");
        }
    }

    /// A direct write the file system refuses (`EINVAL`, here an offset off a page boundary, as
    /// a file system without direct I/O answers) goes through the page cache, and direct writes
    /// stop for good.
    #[test]
    fn a_refused_direct_write_goes_through_the_page_cache() {
        let dir = tempfile::tempdir().unwrap();
        if !direct_supported(dir.path()) {
            return;
        }
        let (mut a, path) = appender(dir.path(), true);
        assert!(a.is_direct());
        let head = bytes(100, 1);
        a.file.write_all(&head).unwrap();
        let run = bytes(2 * ALIGN, 2);
        assert_eq!(
            write_direct(&mut a.direct, &mut a.file, &run, 100).unwrap(),
            0
        );
        assert!(!a.is_direct());
        let got = std::fs::read(&path).unwrap();
        assert_eq!(got, [head, run].concat());
    }

    #[test]
    fn staged_bytes_keep_page_aligned_file_offsets_on_page_aligned_memory() {
        let mut s = Stage::new(4096 * 3 + 100);
        assert_eq!((s.buf.as_ptr() as usize + s.origin) % ALIGN, 0);
        let first_page = s.start() + (ALIGN - 100);
        assert_eq!((s.buf.as_ptr() as usize + first_page) % ALIGN, 0);
        s.push(&[1; 10]);
        assert_eq!(s.room(), STAGE_BYTES - 10);
    }
}
