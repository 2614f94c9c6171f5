//! The durable record of every identification: per building, `modes.jsonl` under the building's
//! state directory, one `BuildingModes` JSON per line, appended and synced window by window.
//! Bounded: at `record_max_windows` lines the file becomes `modes.1.jsonl` (replacing the one
//! before), so at most twice that many windows are kept. A crash between the append and the
//! state's save identifies that window again after the restart and appends it a second time:
//! readers take the last line of a `window_start_ns`.

use std::io::Write;
use std::path::{Path, PathBuf};

use triax_protocol::messages::BuildingModes;

pub const RECORD_FILE: &str = "modes.jsonl";
pub const ROTATED_FILE: &str = "modes.1.jsonl";

/// Appends `modes` to the record in `dir`, which holds `lines` lines; rotates first when it
/// holds `max_lines`. Returns the lines the current file holds afterwards.
pub fn append(
    dir: &Path,
    modes: &BuildingModes,
    lines: u64,
    max_lines: u64,
) -> std::io::Result<u64> {
    std::fs::create_dir_all(dir)?;
    let path = dir.join(RECORD_FILE);
    let mut lines = lines;
    if lines >= max_lines {
        std::fs::rename(&path, dir.join(ROTATED_FILE))?;
        lines = 0;
    }
    let mut line = triax_protocol::to_json(modes);
    line.push(b'\n');
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&path)?;
    f.write_all(&line)?;
    f.sync_data()?;
    Ok(lines + 1)
}

/// Reads back every identification kept in `dir`, oldest first; lines that do not parse (a
/// torn last line after a crash) are skipped.
pub fn read(dir: &Path) -> std::io::Result<Vec<BuildingModes>> {
    let mut out = Vec::new();
    for name in [ROTATED_FILE, RECORD_FILE] {
        let path: PathBuf = dir.join(name);
        let text = match std::fs::read_to_string(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
            Err(e) => return Err(e),
        };
        out.extend(
            text.lines()
                .filter_map(|l| triax_protocol::from_json::<BuildingModes>(l.as_bytes()).ok()),
        );
    }
    Ok(out)
}
