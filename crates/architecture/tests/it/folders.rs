//! The design document's folder table against the tree: every folder under a crate's `src`
//! that holds Rust files is a row of `docs/architecture.md`'s "Folders" table with its job,
//! every row is such a folder, and each folder's module says its job in a doc comment.

use crate::common::{files_under, workspace};
use std::collections::BTreeSet;

/// The rows of the "Folders" table: (folder, job).
fn table_rows(doc: &str) -> Vec<(String, String)> {
    let start = doc.find("### Folders").expect("docs/architecture.md has a \"### Folders\" section");
    let mut rows = Vec::new();
    for line in doc[start..].lines().skip(1) {
        if line.starts_with('#') {
            break;
        }
        let cells: Vec<&str> = line.split('|').map(str::trim).collect();
        if cells.len() >= 4 && cells[1].starts_with("`crates/") {
            rows.push((cells[1].trim_matches('`').to_string(), cells[2].to_string()));
        }
    }
    rows
}

/// Every folder under `crates/*/src` that holds a Rust file, relative to the workspace.
fn source_folders() -> BTreeSet<String> {
    let root = workspace();
    let mut out = BTreeSet::new();
    for file in files_under(&root.join("crates"), Some(".rs")) {
        let rel = file.strip_prefix(&root).unwrap().to_string_lossy().replace('\\', "/");
        let parts: Vec<&str> = rel.split('/').collect();
        // crates/<c>/src/<folder...>/<file>.rs
        if parts.len() > 4 && parts[2] == "src" {
            for k in 4..parts.len() {
                out.insert(parts[..k].join("/"));
            }
        }
    }
    out
}

/// The file whose doc comment says what a folder module is: its `mod.rs`, or the file of the
/// same name beside the folder.
fn module_doc(folder: &str) -> String {
    let root = workspace();
    let inside = root.join(folder).join("mod.rs");
    let beside = root.join(format!("{folder}.rs"));
    let text = std::fs::read_to_string(&inside).or_else(|_| std::fs::read_to_string(&beside)).unwrap_or_default();
    text.lines().take_while(|l| l.starts_with("//!")).collect::<Vec<_>>().join("\n")
}

#[test]
fn every_source_folder_is_in_the_table_with_its_job() {
    let doc = std::fs::read_to_string(workspace().join("docs/architecture.md")).unwrap();
    let rows = table_rows(&doc);
    let listed: BTreeSet<String> = rows.iter().map(|(f, _)| f.clone()).collect();
    let found = source_folders();
    let missing: Vec<_> = found.difference(&listed).collect();
    let stale: Vec<_> = listed.difference(&found).collect();
    assert!(missing.is_empty(), "folders not in docs/architecture.md's Folders table: {missing:?}");
    assert!(stale.is_empty(), "rows of the Folders table with no such folder of Rust files: {stale:?}");
    for (folder, job) in &rows {
        assert!(job.split_whitespace().count() >= 4, "{folder}: the table says no job ({job:?})");
        assert!(!module_doc(folder).trim().is_empty(), "{folder}: its module has no doc comment saying its job");
    }
}

/// The checks see what they are meant to: the tree has folders, and the table parser reads a
/// row written here.
#[test]
fn the_table_reader_reads_a_row() {
    let doc = "x\n### Folders\n\n| folder | one job |\n|---|---|\n| `crates/a/src/b` | the b part of a |\n\n## Next\n| `crates/z/src/q` | not this |\n";
    assert_eq!(table_rows(doc), vec![("crates/a/src/b".to_string(), "the b part of a".to_string())]);
    assert!(source_folders().contains("crates/fit/src/models"));
}
