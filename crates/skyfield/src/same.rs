//! The same data under two names is one input: the one decision, for every command and function
//! that takes several files or rows, of which of them are the same data.
//!
//! Files ([`distinct_files`]) are the same when they are named by the same path, when they are
//! the same file on disk (a hard link, a symlink, the same file reached through another
//! folder: the same device and inode), or, among the files of one role (the frames of a set,
//! the catalogs of a calibration, the tables of a fit, the files of a night: [`By::Content`]),
//! when their bytes are the same (a copy, a folder downloaded twice): by the BLAKE3 hash of
//! their content, the provenance's hash ([`crate::provenance::hash_file`]). Files of different
//! roles are compared by name and identity only ([`By::Identity`]): a Q map and a U map of
//! the same bytes (both zero) are two inputs. Files are compared by size first and by the hash of
//! their first 64 KiB next, so that only files alike so far are read whole: a night's frames,
//! all of one size, differ in their headers and cost one block each.
//!
//! Rows ([`repeated_rows`]) are the same when every value is (bit for bit, but for the sign of
//! a zero; a NaN equals a NaN): a measurement written twice.
//!
//! The caller decides what a duplicate does (a command refuses a file given twice; a folder's
//! scan and a table's rows use the first and say so), never counts it twice, and words it
//! (each [`Duplicate`] names both).

use std::collections::HashMap;
use std::io::Read;
use std::path::{Path, PathBuf};

/// How two names are one input.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum How {
    /// The same path given twice.
    SamePath,
    /// The same file on disk under two names (a hard link, a symlink).
    SameFile,
    /// Two files with the same bytes (a copy).
    SameContent,
}

/// A name that is an earlier one's data again.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Duplicate {
    /// The name kept (the earlier).
    pub first: PathBuf,
    /// The later name, the same data.
    pub again: PathBuf,
    pub how: How,
}

impl std::fmt::Display for Duplicate {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (a, b) = (self.first.display(), self.again.display());
        match self.how {
            How::SamePath => write!(f, "{a} is given twice"),
            How::SameFile => write!(f, "{a} and {b} are the same file (a link)"),
            How::SameContent => write!(f, "{a} and {b} are the same data (identical bytes, a copy)"),
        }
    }
}

/// What makes two files the same (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum By {
    /// The same path or the same file on disk.
    Identity,
    /// As [`By::Identity`], or the same bytes.
    Content,
}

/// Files after [`distinct_files`]: each distinct one once, in the order given, and every later
/// name of one of them.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Distinct {
    pub files: Vec<PathBuf>,
    pub duplicates: Vec<Duplicate>,
}

/// How many bytes of each file of a common size are hashed before files are read whole.
const PREFIX: u64 = 64 * 1024;

/// The hash of a file's first [`PREFIX`] bytes (`None`: unreadable).
fn prefix_hash(path: &Path) -> Option<blake3::Hash> {
    let mut buf = Vec::new();
    std::fs::File::open(path).ok()?.take(PREFIX).read_to_end(&mut buf).ok()?;
    Some(blake3::hash(&buf))
}

/// The files of `paths` that are the same data under another name (module docs), by path, by
/// identity and (with [`By::Content`]) by content; the first name of each is kept. A name that is not a readable
/// regular file (missing, a folder, unreadable) is kept unless its path or identity repeats:
/// its reader reports it.
pub fn distinct_files<P: AsRef<Path>>(paths: &[P], by: By) -> Distinct {
    use std::os::unix::fs::MetadataExt;
    let mut out = Distinct::default();
    // Each duplicate with the index of its later name.
    let mut found: Vec<(usize, Duplicate)> = vec![];
    let mut by_path: HashMap<&Path, usize> = HashMap::new();
    let mut by_id: HashMap<(u64, u64), usize> = HashMap::new();
    // Kept regular files by size: (index in `paths`).
    let mut by_size: HashMap<u64, Vec<usize>> = HashMap::new();
    let mut kept = vec![true; paths.len()];
    for (i, p) in paths.iter().enumerate() {
        let p = p.as_ref();
        if let Some(&j) = by_path.get(p) {
            found.push((i, Duplicate { first: paths[j].as_ref().into(), again: p.into(), how: How::SamePath }));
            kept[i] = false;
            continue;
        }
        by_path.insert(p, i);
        let Ok(m) = std::fs::metadata(p) else { continue };
        if let Some(&j) = by_id.get(&(m.dev(), m.ino())) {
            found.push((i, Duplicate { first: paths[j].as_ref().into(), again: p.into(), how: How::SameFile }));
            kept[i] = false;
            continue;
        }
        by_id.insert((m.dev(), m.ino()), i);
        if m.is_file() && by == By::Content {
            by_size.entry(m.len()).or_default().push(i);
        }
    }
    // Files of a common size: by the hash of their start, then of their whole content.
    let mut groups: Vec<Vec<usize>> = by_size.into_values().filter(|g| g.len() > 1).collect();
    groups.sort();
    for group in groups {
        let mut by_prefix: HashMap<blake3::Hash, Vec<usize>> = HashMap::new();
        for i in group {
            if let Some(h) = prefix_hash(paths[i].as_ref()) {
                by_prefix.entry(h).or_default().push(i);
            }
        }
        let mut alike: Vec<Vec<usize>> = by_prefix.into_values().filter(|g| g.len() > 1).collect();
        alike.sort();
        for g in alike {
            let mut by_hash: HashMap<String, usize> = HashMap::new();
            for i in g {
                let Ok(h) = crate::provenance::hash_file(paths[i].as_ref()) else { continue };
                if let Some(&j) = by_hash.get(&h) {
                    let (first, again) = (paths[j].as_ref().into(), paths[i].as_ref().into());
                    found.push((i, Duplicate { first, again, how: How::SameContent }));
                    kept[i] = false;
                } else {
                    by_hash.insert(h, i);
                }
            }
        }
    }
    out.files = paths.iter().zip(&kept).filter(|(_, k)| **k).map(|(p, _)| p.as_ref().to_path_buf()).collect();
    // Reported in the order the later names were given.
    found.sort_by_key(|f| f.0);
    out.duplicates = found.into_iter().map(|f| f.1).collect();
    out
}

/// A row whose every value is an earlier row's (indices from 0).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RepeatedRow {
    pub first: usize,
    pub again: usize,
}

/// The rows of a table that repeat an earlier row value for value (module docs), in order.
pub fn repeated_rows<R: AsRef<[f64]>>(rows: &[R]) -> Vec<RepeatedRow> {
    let key = |r: &[f64]| -> Vec<u64> {
        r.iter()
            .map(|&v| {
                if v == 0.0 {
                    0
                } else if v.is_nan() {
                    f64::NAN.to_bits()
                } else {
                    v.to_bits()
                }
            })
            .collect()
    };
    let mut seen: HashMap<Vec<u64>, usize> = HashMap::new();
    let mut out = vec![];
    for (i, r) in rows.iter().enumerate() {
        match seen.entry(key(r.as_ref())) {
            std::collections::hash_map::Entry::Occupied(e) => out.push(RepeatedRow { first: *e.get(), again: i }),
            std::collections::hash_map::Entry::Vacant(e) => {
                e.insert(i);
            }
        }
    }
    out
}

/// [`repeated_rows`] told in words for a note: the first `shown` pairs by `name` (a row's
/// label, e.g. its file and line) and how many more.
pub fn describe_repeated(repeats: &[RepeatedRow], name: &dyn Fn(usize) -> String, shown: usize) -> String {
    let mut parts: Vec<String> =
        repeats.iter().take(shown).map(|r| format!("{} repeats {}", name(r.again), name(r.first))).collect();
    if repeats.len() > shown {
        parts.push(format!("and {} more", repeats.len() - shown));
    }
    parts.join("; ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn copies_links_and_repeats_are_found_once_each() {
        let d = tempfile::tempdir().unwrap();
        let p = |n: &str| d.path().join(n);
        // Two files of one size and one first block, differing in the last byte: not the same.
        let mut a = vec![7u8; 200_000];
        std::fs::write(p("a"), &a).unwrap();
        a[199_999] = 8;
        std::fs::write(p("b"), &a).unwrap();
        std::fs::copy(p("a"), p("a_copy")).unwrap();
        std::fs::hard_link(p("b"), p("b_link")).unwrap();
        std::os::unix::fs::symlink(p("a"), p("a_sym")).unwrap();
        std::fs::write(p("c"), b"other").unwrap();
        let names = ["a", "b", "a_copy", "b_link", "a_sym", "c", "a", "missing", "missing"].map(p);
        let r = distinct_files(&names, By::Content);
        assert_eq!(r.files, ["a", "b", "c", "missing"].map(p));
        let got: Vec<(PathBuf, PathBuf, How)> =
            r.duplicates.iter().map(|x| (x.first.clone(), x.again.clone(), x.how)).collect();
        assert_eq!(
            got,
            [
                (p("a"), p("a_copy"), How::SameContent),
                (p("b"), p("b_link"), How::SameFile),
                (p("a"), p("a_sym"), How::SameFile),
                (p("a"), p("a"), How::SamePath),
                (p("missing"), p("missing"), How::SamePath),
            ]
        );
        assert!(r.duplicates[0].to_string().contains("a_copy"));
        // By identity, the copy is another input.
        let r = distinct_files(&names, By::Identity);
        assert_eq!(r.files, ["a", "b", "a_copy", "c", "missing"].map(p));
    }

    #[test]
    fn rows_repeated_value_for_value() {
        let rows = [vec![1.0, 2.0], vec![1.0, 2.5], vec![1.0, 2.0], vec![-0.0, f64::NAN], vec![0.0, f64::NAN]];
        assert_eq!(repeated_rows(&rows), [RepeatedRow { first: 0, again: 2 }, RepeatedRow { first: 3, again: 4 }]);
        let text = describe_repeated(&repeated_rows(&rows), &|i| format!("row {}", i + 1), 1);
        assert_eq!(text, "row 3 repeats row 1; and 1 more");
    }
}
