//! Durable writes: the last steps every writer of the workspace takes before an output gets its
//! final name.
//!
//! A write error is not always reported by the `write` call that caused it: a full disk or a
//! quota often shows up only when buffers are flushed (CFITSIO writes its last 2880-byte
//! blocks when the file is closed) or when the kernel writes the page cache back (fsync). So a
//! writer (1) closes a FITS file with [`close_fits`] and checks CFITSIO's status (fitsio's
//! `Drop` ignores it), (2) fsyncs the temporary and (3) only then renames it onto the final name
//! ([`finish`]). Any error on the way drops the temporary, which deletes it: a failed run leaves
//! neither a truncated file under the final name nor a temporary.
//!
//! No writer writes over one of its own inputs, whatever name the output is given by: a hard
//! link, a symlink, `..` in the path. [`same_file`] is the one test of two paths, and
//! [`refuse_overwrite`] the one refusal and its words, for both faces (the CLI registers a
//! command's inputs and checks every output against them; the Python functions check their
//! `output=` against their arguments).
//!
//! Tests cannot always fill a disk (mounting a tmpfs needs root), so the fsync step can be made
//! to fail on purpose: with the environment variable `INSTPOL_TEST_FAIL_SYNC` set to a
//! non-empty value, [`sync_file`] reports "No space left on device" (ENOSPC) without writing
//! anything. It exists only to prove, in tests, that every writer treats that error as fatal.

use fitsio::FitsFile;
use std::io;
use std::path::Path;

/// The environment variable that makes [`sync_file`] fail (tests only; see the module docs).
pub const FAIL_SYNC_ENV: &str = "INSTPOL_TEST_FAIL_SYNC";

/// Close `f` through CFITSIO and return its status as an error. CFITSIO writes its buffered
/// header and data blocks here, so on a full disk this is where the error appears; but a
/// write that fails in the C library's last flush at `fclose` is not always in that status
/// (a file a partial page short came back with status 0), so the file on disk is then read
/// back and must hold every HDU CFITSIO had, whole ([`fits_extent`]).
pub fn close_fits(mut f: FitsFile) -> Result<(), String> {
    let mut status: std::os::raw::c_int = 0;
    let mut nhdu: std::os::raw::c_int = 0;
    let mut name = [0 as std::os::raw::c_char; 1025];
    // SAFETY: `as_raw` gives the live pointer the FitsFile owns; ffflnm writes at most
    // FLEN_FILENAME (1025) bytes with the NUL. ffclos frees the fitsfile structure whatever
    // the status, so the FitsFile must not run its Drop (a second ffclos on freed memory): it
    // is forgotten (leaking only its path and mode, a few bytes).
    unsafe {
        fitsio::sys::ffthdu(f.as_raw(), &mut nhdu, &mut status);
        fitsio::sys::ffflnm(f.as_raw(), name.as_mut_ptr(), &mut status);
        fitsio::sys::ffclos(f.as_raw(), &mut status);
    }
    std::mem::forget(f);
    if status != 0 {
        let mut buf = [0 as std::os::raw::c_char; 32];
        // SAFETY: ffgerr writes at most 30 characters and a NUL into the 32-byte buffer.
        let text = unsafe {
            fitsio::sys::ffgerr(status, buf.as_mut_ptr());
            std::ffi::CStr::from_ptr(buf.as_ptr()).to_string_lossy().into_owned()
        };
        return Err(format!("closing the FITS file failed (CFITSIO status {status}: {text}); disk full?"));
    }
    // SAFETY: ffflnm wrote a NUL-terminated name into the buffer (zeroed beforehand).
    let name = unsafe { std::ffi::CStr::from_ptr(name.as_ptr()) }.to_string_lossy().into_owned();
    let path = Path::new(name.trim_start_matches('!'));
    let len = std::fs::metadata(path).map_err(|e| format!("reading back {}: {e}", path.display()))?.len();
    match fits_extent(path, nhdu.max(0) as usize) {
        Ok(end) if end == len => Ok(()),
        Ok(end) => Err(format!(
            "the FITS file holds {len} bytes where its {nhdu} HDUs end at byte {end}: a write was lost at close (disk full?)"
        )),
        Err(why) => Err(format!("the FITS file is not whole after closing ({why}): a write was lost (disk full?)")),
    }
}

/// Where the first `nhdu` HDUs of the FITS file at `path` end (bytes, a multiple of 2880),
/// read from their headers (`BITPIX`, `NAXISn`, `PCOUNT`, `GCOUNT`); `Err` naming what is cut
/// short when the file ends before them.
pub fn fits_extent(path: &Path, nhdu: usize) -> Result<u64, String> {
    use std::io::{Read, Seek, SeekFrom};
    const BLOCK: u64 = 2880;
    let mut f = std::fs::File::open(path).map_err(|e| e.to_string())?;
    let mut at = 0u64;
    for h in 0..nhdu {
        let mut keys: Vec<(String, i64)> = Vec::new();
        let mut block = [0u8; BLOCK as usize];
        'header: loop {
            f.seek(SeekFrom::Start(at)).map_err(|e| e.to_string())?;
            f.read_exact(&mut block).map_err(|_| format!("HDU {} header cut short at byte {at}", h + 1))?;
            at += BLOCK;
            for card in block.chunks(80) {
                let card = String::from_utf8_lossy(card);
                let key = card.get(..8).unwrap_or("").trim_end();
                if key == "END" {
                    break 'header;
                }
                if card.get(8..10) == Some("= ") {
                    let value = card[10..].split('/').next().unwrap_or("").trim();
                    if let Ok(v) = value.parse::<i64>() {
                        keys.push((key.to_string(), v));
                    }
                }
            }
        }
        let get = |k: &str| keys.iter().find(|(n, _)| n == k).map(|(_, v)| *v);
        let naxis = get("NAXIS").unwrap_or(0);
        let elements: i64 =
            if naxis > 0 { (1..=naxis).map(|i| get(&format!("NAXIS{i}")).unwrap_or(0)).product() } else { 0 };
        let bytes = get("BITPIX").unwrap_or(8).unsigned_abs() / 8
            * get("GCOUNT").unwrap_or(1).max(0) as u64
            * (get("PCOUNT").unwrap_or(0).max(0) + elements.max(0)) as u64;
        at += bytes.div_ceil(BLOCK) * BLOCK;
    }
    let len = f.metadata().map_err(|e| e.to_string())?.len();
    if len < at {
        return Err(format!("its {nhdu} HDUs need {at} bytes, the file holds {len}"));
    }
    Ok(at)
}

/// fsync the file at `path` (data and metadata), so that a deferred write error (ENOSPC, EIO,
/// EDQUOT) is reported now rather than lost after the rename.
pub fn sync_file(path: &Path) -> io::Result<()> {
    if std::env::var_os(FAIL_SYNC_ENV).is_some_and(|v| !v.is_empty()) {
        return Err(io::Error::new(
            io::ErrorKind::StorageFull,
            format!("No space left on device (injected by {FAIL_SYNC_ENV} for a test)"),
        ));
    }
    std::fs::OpenOptions::new().write(true).open(path)?.sync_all()
}

/// fsync the folder holding `path`, so that the rename itself survives a crash. Best effort:
/// some file systems refuse fsync on a folder, and the file's data is already safe.
fn sync_parent(path: &Path) {
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    if let Ok(d) = std::fs::File::open(dir) {
        let _ = d.sync_all();
    }
}

/// Outputs held back while a run that writes several files is staged ([`stage`]): each
/// complete, fsynced temporary with its final name.
type Staged = Vec<(tempfile::TempPath, std::path::PathBuf)>;
static STAGE: std::sync::Mutex<Option<Staged>> = std::sync::Mutex::new(None);

fn staged() -> std::sync::MutexGuard<'static, Option<Staged>> {
    STAGE.lock().unwrap_or_else(|e| e.into_inner())
}

/// Run `work`, holding back every file it writes through [`finish`] (each complete and
/// fsynced beside its final name) until it has succeeded, then rename them all onto their
/// names; when it fails, delete them all. A run that writes several files (a calibration and
/// its plots, one model per band) so succeeds whole or leaves none of them, where it left the
/// files written before the failure. Only renames remain after the last write, and those do
/// not fail for want of space. `work` must not read back what it writes (nothing is at its
/// final name before the end).
pub fn stage<T, E: From<io::Error>>(work: impl FnOnce() -> Result<T, E>) -> Result<T, E> {
    *staged() = Some(Vec::new());
    let result = work();
    let held = staged().take().unwrap_or_default();
    match result {
        Ok(v) => {
            for (tmp, path) in held {
                tmp.persist(&path).map_err(|e| {
                    io::Error::new(e.error.kind(), format!("cannot write {}: {}", path.display(), e.error))
                })?;
                sync_parent(&path);
            }
            Ok(v)
        }
        // Dropping the temporaries deletes them.
        Err(e) => Err(e),
    }
}

/// The final step of every writer: fsync the complete temporary `tmp`, then rename it onto
/// `path` (or hold it until a staged run ends, [`stage`]). On error the temporary is deleted
/// (dropped) and `path` is untouched.
pub fn finish(tmp: tempfile::TempPath, path: &Path) -> io::Result<()> {
    sync_file(&tmp)?;
    if let Some(held) = staged().as_mut() {
        held.push((tmp, path.to_path_buf()));
        return Ok(());
    }
    // Keep only the io::Error: the PersistError also holds the temporary, dropped (deleted) here.
    tmp.persist(path).map_err(|e| e.error)?;
    sync_parent(path);
    Ok(())
}

/// The identity of an existing file: device and inode (a hard link or a bind mount has another
/// name but the same identity).
pub fn file_id(p: &Path) -> Option<(u64, u64)> {
    use std::os::unix::fs::MetadataExt;
    std::fs::metadata(p).ok().map(|m| (m.dev(), m.ino()))
}

/// `p` with symlinks and `..` resolved; for a file that does not exist yet, its folder
/// resolved and the name appended.
fn resolved(p: &Path) -> Option<std::path::PathBuf> {
    if let Ok(c) = std::fs::canonicalize(p) {
        return Some(c);
    }
    let dir = p.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    Some(std::fs::canonicalize(dir).ok()?.join(p.file_name()?))
}

/// Whether `a` and `b` name the same file: the same identity when both exist; the same
/// resolved path when neither does (an existing file and a missing one are never the same).
/// `id_a` is `file_id(a)`, taken once by a caller comparing `a` with many files: each
/// comparison then costs one `stat` (resolving every path each time was 6 ms of a 34-file
/// reduction's start).
pub fn same_file(a: &Path, id_a: Option<(u64, u64)>, b: &Path) -> bool {
    match (id_a, file_id(b)) {
        (Some(x), Some(y)) => x == y,
        (None, None) => matches!((resolved(a), resolved(b)), (Some(x), Some(y)) if x == y),
        _ => false,
    }
}

/// Refuse to write `output` when it is one of `inputs` ([`same_file`]), with the message both
/// faces give.
pub fn refuse_overwrite<'a>(output: &Path, inputs: impl IntoIterator<Item = &'a Path>) -> Result<(), String> {
    let id = file_id(output);
    match inputs.into_iter().find(|i| same_file(output, id, i)) {
        Some(i) => Err(format!(
            "output {} is the input {} (the same file): refusing to write over an input; choose another output name",
            output.display(),
            i.display()
        )),
        None => Ok(()),
    }
}
