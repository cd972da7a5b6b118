//! Each crate imports only what `docs/architecture.md` says it may: the table "crate (package)
//! | one job | may import" is read from the document, and every crate's normal (not dev)
//! dependencies on workspace crates, read from its `Cargo.toml`, must be among the crates its
//! row lists ("all of the above": every crate of an earlier row). A dependency added against
//! the design fails here; so does a design that no longer says what the manifests do.

use crate::common;

use std::collections::{BTreeMap, BTreeSet};

/// The document's table: crate folder name -> what it may import (folder names), in order.
fn allowed() -> Vec<(String, BTreeSet<String>)> {
    let doc = std::fs::read_to_string(common::workspace().join("docs/architecture.md")).unwrap();
    let mut rows: Vec<(String, BTreeSet<String>)> = vec![];
    for line in doc.lines().filter(|l| l.starts_with("| `crates/")) {
        let cells: Vec<&str> = line.split('|').map(str::trim).collect();
        let name = cells[1].trim_start_matches("`crates/").split('`').next().unwrap().to_string();
        let may = cells[3];
        let set: BTreeSet<String> = if may == "all of the above" {
            rows.iter().map(|(n, _)| n.clone()).collect()
        } else if may == "none" {
            BTreeSet::new()
        } else {
            may.split(',').map(|s| s.trim().split(' ').next().unwrap().to_string()).collect()
        };
        rows.push((name, set));
    }
    rows
}

/// Crate folder -> its normal dependencies on workspace crates (by the workspace key, which is
/// the folder name except for the CLI).
fn manifests() -> BTreeMap<String, BTreeSet<String>> {
    let ws = common::workspace();
    let root: toml::Table = std::fs::read_to_string(ws.join("Cargo.toml")).unwrap().parse().unwrap();
    let internal: BTreeSet<String> = root["workspace"]["dependencies"]
        .as_table()
        .unwrap()
        .iter()
        .filter(|(_, v)| v.get("path").is_some())
        .map(|(k, _)| k.clone())
        .collect();
    let mut out = BTreeMap::new();
    for entry in std::fs::read_dir(ws.join("crates")).unwrap().flatten() {
        let Ok(text) = std::fs::read_to_string(entry.path().join("Cargo.toml")) else { continue };
        let m: toml::Table = text.parse().unwrap();
        let deps: BTreeSet<String> = m
            .get("dependencies")
            .and_then(|d| d.as_table())
            .map(|d| d.keys().filter(|k| internal.contains(*k)).cloned().collect())
            .unwrap_or_default();
        out.insert(entry.file_name().to_string_lossy().to_string(), deps);
    }
    out
}

#[test]
fn every_crate_imports_only_what_the_design_allows() {
    let rows = allowed();
    let manifests = manifests();
    assert!(rows.len() >= 10, "the table of crates was not found in docs/architecture.md ({} rows)", rows.len());
    for (name, deps) in &manifests {
        let (_, may) = rows
            .iter()
            .find(|(n, _)| n == name)
            .unwrap_or_else(|| panic!("crates/{name} has no row in docs/architecture.md's table of crates"));
        let extra: Vec<&String> = deps.iter().filter(|d| !may.contains(*d)).collect();
        assert!(extra.is_empty(), "crates/{name} depends on {extra:?}, which docs/architecture.md does not allow it");
    }
    // The rule the table exists for: the fits and the simulator stand side by side.
    assert!(!manifests["fit"].contains("sim") && !manifests["sim"].contains("fit"));
}
