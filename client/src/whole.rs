//! Files written whole or not at all: a temporary file beside the target (so that the rename
//! stays on one file system), synced, then renamed over it. A failed or killed writer leaves the
//! target as it was.

use std::io::{self, Write};
use std::path::Path;

use tempfile::NamedTempFile;

/// A temporary file in `dir` named `<prefix><random><suffix>`, readable by all as a file the
/// program created directly would be (a temporary file is otherwise its owner's only, and an
/// export is made for others to read).
pub(crate) fn temp_beside(dir: &Path, prefix: &str, suffix: &str) -> io::Result<NamedTempFile> {
    let mut b = tempfile::Builder::new();
    b.prefix(prefix).suffix(suffix);
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        b.permissions(std::fs::Permissions::from_mode(0o644));
    }
    b.tempfile_in(dir)
}

/// Syncs `tmp` and renames it over `path`.
pub(crate) fn commit(tmp: NamedTempFile, path: &Path) -> io::Result<()> {
    tmp.as_file().sync_all()?;
    tmp.persist(path).map_err(|e| e.error)?;
    Ok(())
}

/// Writes `parts` as the whole of `path`.
pub(crate) fn write<'a>(path: &Path, parts: impl IntoIterator<Item = &'a [u8]>) -> io::Result<()> {
    // Every target here has a parent: a day file under its SDS folders, or a file under --out.
    let dir = path.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir)?;
    let mut tmp = temp_beside(dir, ".triax-export-", "")?;
    for p in parts {
        tmp.write_all(p)?;
    }
    commit(tmp, path)
}
