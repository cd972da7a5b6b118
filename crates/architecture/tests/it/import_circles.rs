//! No file-level import circles: within a crate's `src/`, no module file uses another that,
//! directly or through others, uses it back. A crate whose files form layers can be read and
//! changed a layer at a time; a circle makes its files one unit.
//!
//! The graph: a file uses the file of every module path its code names that starts with
//! `crate::`, `super::`, `self::` or a module the file declares (`mod x;` then `x::...`), in
//! `use` items and in paths written inline; the path's longest prefix that is a module file
//! is the file used (a directory module counts as its files: `table/mod.rs`, `table/csv.rs`).
//! Comments, literals and `#[cfg(test)]` modules are left out (tests may reach anywhere). The
//! crate root's paths through its own modules (`pub use maps::StokesMap`) are its table of
//! contents, not uses; what the root defines (`crate::Error`) is used like any file's.

use crate::common;

use common::{circles, crate_graph, cycles, describe, graph_of, workspace};
use std::collections::BTreeMap;

/// The cycles of crate `name`, described, or nothing.
fn circles_of(name: &str) -> Vec<String> {
    let src = workspace().join("crates").join(name).join("src");
    let g = crate_graph(&src);
    assert!(g.edges.len() > 3, "crate {name}: too few module files found in {}", src.display());
    circles(&g.edges)
        .iter()
        .map(|(files, cycle)| format!("{} (e.g. {})", files.join(", "), describe(cycle, &g.edges)))
        .collect()
}

fn assert_no_circles(name: &str) {
    let found = circles_of(name);
    assert!(found.is_empty(), "crate {name} has file-level import circles:\n  {}", found.join("\n  "));
}

#[test]
fn skyfield_has_no_import_circles() {
    assert_no_circles("skyfield");
}

#[test]
fn fit_has_no_import_circles() {
    assert_no_circles("fit");
}

/// The cycle finder on small graphs written out: a three-file circle with a tail into it, a
/// separate two-file circle, a diamond (no circle), and a self-use (not a circle).
#[test]
fn cycle_finder_finds_each_circle_once() {
    let g = |edges: &[(&str, &str)]| {
        let mut m: BTreeMap<String, BTreeMap<String, usize>> = BTreeMap::new();
        for (k, (a, b)) in edges.iter().enumerate() {
            m.entry(a.to_string()).or_default().insert(b.to_string(), k + 1);
        }
        m
    };
    let edges = g(&[("a", "b"), ("b", "c"), ("c", "a"), ("d", "a"), ("e", "f"), ("f", "e"), ("c", "g")]);
    let mut found = cycles(&edges);
    found.sort();
    assert_eq!(found, vec![vec!["a", "b", "c", "a"], vec!["e", "f", "e"]]);
    let mut members: Vec<Vec<String>> = circles(&edges).into_iter().map(|c| c.0).collect();
    members.sort();
    assert_eq!(members, vec![vec!["a", "b", "c"], vec!["e", "f"]]);
    assert_eq!(describe(&found[1], &edges), "e -> f (line 5 of e) -> e (line 6 of f)");
    let diamond = g(&[("top", "l"), ("top", "r"), ("l", "bottom"), ("r", "bottom"), ("bottom", "bottom")]);
    assert!(cycles(&diamond).is_empty());
    // The shortest way round is the one reported.
    let two_ways = g(&[("a", "b"), ("b", "c"), ("c", "d"), ("d", "a"), ("b", "a")]);
    assert_eq!(cycles(&two_ways), vec![vec!["a", "b", "a"]]);
}

/// The parser on a small crate written out: `use` trees, inline `crate::` and `super::` paths,
/// a directory module and its parent, a child module named in its parent, `super::*` in an
/// inline test module (the same file), and paths in comments, strings and test modules (none
/// of which count). A directory module's `pub use child::Item` is its folder's table of
/// contents, not a use (`table`); its private use of a child is one (`geo`, a circle).
#[test]
fn graph_of_a_small_crate() {
    let files: Vec<(String, String)> = [
        (
            "lib.rs",
            "pub mod fits;\npub mod frame;\npub mod geo;\npub mod io;\npub mod table;\npub use io::read;\npub struct Error;\n",
        ),
        ("fits.rs", "use crate::Error;\n// crate::io::read in a comment\nconst S: &str = \"crate::frame::X\";\nlet c = '\"';\n"),
        (
            "frame.rs",
            "use crate::{fits::{self, open}, Error as E};\nfn f() -> crate::fits::Hdu { todo!() }\n#[cfg(test)]\nmod tests {\n    use super::*;\n    use crate::io::read;\n}\n",
        ),
        ("io.rs", "use crate::frame::Frame;\nfn g() { let x = std::io::stdin(); crate::table::csv::parse(); }\n"),
        ("table/mod.rs", "mod csv;\npub use csv::parse;\npub struct Table;\n"),
        ("table/csv.rs", "use super::Table;\nmod inner { use super::super::Table; }\n"),
        ("geo/mod.rs", "mod wcs;\npub use wcs::Sky;\nuse wcs::Sky as S;\npub struct Geo;\n"),
        ("geo/wcs.rs", "use super::Geo;\npub struct Sky;\n"),
    ]
    .iter()
    .map(|(a, b)| (a.to_string(), b.to_string()))
    .collect();
    let g = graph_of(&files);
    let uses = |f: &str| g.edges[f].keys().cloned().collect::<Vec<_>>();
    assert_eq!(uses("lib.rs"), Vec::<String>::new());
    assert_eq!(uses("fits.rs"), vec!["lib.rs"]);
    assert_eq!(uses("frame.rs"), vec!["fits.rs", "lib.rs"]);
    assert_eq!(uses("io.rs"), vec!["frame.rs", "table/csv.rs"]);
    assert_eq!(uses("table/mod.rs"), Vec::<String>::new());
    assert_eq!(uses("geo/mod.rs"), vec!["geo/wcs.rs"]);
    assert_eq!(uses("table/csv.rs"), vec!["table/mod.rs"]);
    assert_eq!(g.edges["frame.rs"]["fits.rs"], 1);
    assert_eq!(g.edges["io.rs"]["table/csv.rs"], 2);
    assert_eq!(cycles(&g.edges), vec![vec!["geo/mod.rs", "geo/wcs.rs", "geo/mod.rs"]]);
}

/// Every crate of the workspace, read the same way (those with fewer than four module files
/// cannot hold a circle worth the name and are read all the same).
#[test]
fn no_crate_has_import_circles() {
    let crates = workspace().join("crates");
    let mut found = Vec::new();
    for e in std::fs::read_dir(&crates).unwrap().flatten() {
        let src = e.path().join("src");
        if !src.is_dir() {
            continue;
        }
        let name = e.file_name().to_string_lossy().to_string();
        let g = crate_graph(&src);
        for (files, cycle) in circles(&g.edges) {
            found.push(format!("{name}: {} (e.g. {})", files.join(", "), describe(&cycle, &g.edges)));
        }
    }
    assert!(found.is_empty(), "file-level import circles:\n  {}", found.join("\n  "));
}
