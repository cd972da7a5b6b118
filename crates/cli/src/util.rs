//! Small helpers shared by the commands: JSON printing and atomic file writes.

use anyhow::{Context, Result};
use std::io::Write;
use std::path::Path;

/// Print a value as pretty JSON on stdout.
pub fn print_json<T: serde::Serialize>(v: &T) -> Result<()> {
    println!("{}", serde_json::to_string_pretty(v)?);
    Ok(())
}

/// The one way the CLI writes a file: `write` fills a temporary file (named `.instpol-*SUFFIX`)
/// in the destination folder, which is then renamed onto `path`; on any error the temporary
/// is removed, so an interrupted or failed run never leaves a half-written file.
pub fn write_via_temp(path: &Path, suffix: &str, write: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let tmp = skyfield::io::temp_beside(path, suffix)
        .with_context(|| format!("cannot create a temporary file in {}", dir.display()))?;
    write(tmp.path())?;
    // Keep only the io::Error: the PersistError also holds the temporary, which must be
    // dropped (deleted) here, not when the error is (main exits without unwinding).
    tmp.persist(path).map_err(|e| e.error).with_context(|| format!("cannot write {}", path.display()))?;
    Ok(())
}

/// Write `bytes` to `path` through [`write_via_temp`].
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_via_temp(path, ".tmp", |tmp| {
        std::fs::File::create(tmp)
            .and_then(|mut f| f.write_all(bytes))
            .with_context(|| format!("cannot write {}", path.display()))
    })
}
