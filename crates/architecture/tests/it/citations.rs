//! Nothing in the repository's code and documents cites what its reader cannot open: the old
//! design card that lived outside the repository, or the number of an issue, a stop or a work
//! session in place of the reason itself (`docs/architecture.md`, Conventions, "Citations").
//! Every text file under `crates/` and `docs/` is read; each offence is printed as
//! `path:line: text`, all of them at once.

use std::path::{Path, PathBuf};

/// Words that cite a numbered thing when a space, an optional `#` and a digit follow them.
/// Matched as whole words (not inside a longer word) in any case; the longer form first.
const NUMBERED: [&str; 5] = ["issues", "issue", "sessions", "session", "stop"];

/// Directories never read: build outputs and caches.
const SKIP_DIRS: [&str; 6] = ["target", "dist", "build", "__pycache__", ".pytest_cache", "node_modules"];

/// Lines allowed to match: `(path from the repository root, text the line contains)`, for a
/// string literal a test needs (an input or an expected message that cites a number on
/// purpose). None is needed today; an entry says why beside it.
const ALLOWED: &[(&str, &str)] = &[];

/// The old design card's file name, put together here so that this file does not cite it.
fn design_card() -> String {
    ["DESIGN", ".md"].concat()
}

fn is_word_char(c: char) -> bool {
    c.is_alphanumeric() || c == '_'
}

/// What in `line` cites a numbered issue, stop or session, or the design card: one description
/// per citation found.
fn citations(line: &str, card: &str) -> Vec<String> {
    let mut found = vec![];
    if line.contains(card) {
        found.push(format!("cites {card}, which is not in the repository"));
    }
    let lower = line.to_ascii_lowercase();
    let mut prev: Option<char> = None;
    for (i, c) in lower.char_indices() {
        let starts_word = prev.is_none_or(|p| !is_word_char(p));
        prev = Some(c);
        if !starts_word {
            continue;
        }
        for word in NUMBERED {
            let Some(rest) = lower[i..].strip_prefix(word) else { continue };
            let Some(rest) = rest.strip_prefix(' ') else { continue };
            let rest = rest.strip_prefix('#').unwrap_or(rest);
            if rest.starts_with(|d: char| d.is_ascii_digit()) {
                let end = (i + word.len() + 8).min(line.len());
                let end = (end..=line.len()).find(|&e| line.is_char_boundary(e)).unwrap_or(line.len());
                found.push(format!("cites a number ('{}')", line[i..end].trim_end()));
            }
            break;
        }
    }
    found
}

/// Every file under `dir`, depth first, in a fixed order, leaving out [`SKIP_DIRS`] and hidden
/// directories.
fn files_under(dir: &Path, out: &mut Vec<PathBuf>) {
    let mut entries: Vec<_> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap_or_else(|e| panic!("{}: {e}", dir.display())).path())
        .collect();
    entries.sort();
    for p in entries {
        let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
        if p.is_dir() {
            if !name.starts_with('.') && !SKIP_DIRS.contains(&name) {
                files_under(&p, out);
            }
        } else {
            out.push(p);
        }
    }
}

fn repository_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

#[test]
fn nothing_in_crates_or_docs_cites_an_outside_design_or_a_numbered_issue() {
    let root = repository_root();
    let card = design_card();
    let mut files = vec![];
    for top in ["crates", "docs"] {
        files_under(&root.join(top), &mut files);
    }
    let mut read = 0;
    let mut rust = 0;
    let mut offences = vec![];
    for path in &files {
        let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        // Binary files (FITS data, compressed tables) are not text anyone cites from.
        let Ok(text) = std::str::from_utf8(&bytes) else { continue };
        if text.contains('\0') {
            continue;
        }
        read += 1;
        rust += usize::from(path.extension().is_some_and(|e| e == "rs"));
        let rel = path.strip_prefix(&root).unwrap_or(path).to_string_lossy().replace('\\', "/");
        for (n, line) in text.lines().enumerate() {
            if ALLOWED.iter().any(|(p, t)| *p == rel && line.contains(t)) {
                continue;
            }
            for what in citations(line, &card) {
                offences.push(format!("{rel}:{}: {what}: {}", n + 1, line.trim()));
            }
        }
    }
    // The walk found the workspace: a wrong root would read nothing and pass.
    assert!(rust > 100 && read > rust, "read {read} text files, {rust} Rust, under {}", root.display());
    assert!(
        offences.is_empty(),
        "{} citation(s) a reader of the repository cannot follow; say the reason, or cite the \
         document, equation or test that holds it (docs/architecture.md, Conventions):\n{}",
        offences.len(),
        offences.join("\n")
    );
}

/// The matcher against lines written to hold, or not hold, a citation (built at run time, so
/// that this file itself holds none).
#[test]
fn the_matcher_finds_numbered_citations_and_only_those() {
    let card = design_card();
    for word in ["issue", "Issue", "issues", "ISSUE", "session", "Session", "stop", "sessions"] {
        for tail in [" 16", " #12", " 5 and 6", " 14 item 4", " 15)"] {
            let line = format!("// the rule ({word}{tail}): applied once");
            assert_eq!(citations(&line, &card).len(), 1, "missed: {line}");
        }
        // A number that does not follow the word directly is no citation.
        for tail in ["", "d as warnings", "s", " of the manual, 5", "#3", "  7"] {
            let line = format!("// {word}{tail}");
            assert!(citations(&line, &card).is_empty(), "false alarm: {line}");
        }
        // Inside a longer word: not the word.
        let line = format!("// t{word} 5, non{word} 6, set_{word} 7");
        assert!(citations(&line, &card).is_empty(), "false alarm: {line}");
    }
    let line = format!("/// Conventions (see {card}).");
    assert_eq!(citations(&line, &card).len(), 1);
    let two = format!("// {card}, and {} 3", NUMBERED[1]);
    assert_eq!(citations(&two, &card).len(), 2);
    // A multi-byte character right after the citation does not split the printed excerpt.
    assert_eq!(citations(&format!("{} 1 — é", NUMBERED[1]), &card).len(), 1);
}
