//! No function over 150 lines outside tests (`docs/architecture.md`, Conventions): a function a
//! reader cannot hold in view is split at its seams. Lines run from the `fn` to its closing
//! brace, comments and blank lines included; `#[cfg(test)]` modules and `tests/` are left out.
//!
//! The functions that were longer when the rule became a test are listed in `LONGER` with the
//! length each had then: each may only shrink, and leaves the list (the test says so) once it is
//! within the rule. A function not listed fails at 151 lines.

use crate::common;

use common::{code_only, files_under, source_files, tokens, workspace, Token};

const LIMIT: usize = 150;

/// (file, function, its length when listed). Shrink, never add.
const LONGER: &[(&str, &str, usize)] = &[];

/// Every function with a body in `src` (outside `#[cfg(test)]` modules): (name, first line,
/// length in lines).
fn functions(src: &str) -> Vec<(String, usize, usize)> {
    let toks = tokens(&code_only(src));
    let text = |k: usize| toks.get(k).map_or("", |t: &Token| t.text.as_str());
    let close = |open: usize| -> usize {
        let mut depth = 0usize;
        for (k, t) in toks.iter().enumerate().skip(open) {
            match t.text.as_str() {
                "{" => depth += 1,
                "}" => {
                    depth -= 1;
                    if depth == 0 {
                        return k;
                    }
                }
                _ => {}
            }
        }
        toks.len() - 1
    };
    let mut out = Vec::new();
    let mut i = 0;
    while i < toks.len() {
        // `#[cfg(test)]`, any further attributes, then `mod name {`: skipped whole.
        if text(i) == "#" && text(i + 1) == "[" && text(i + 2) == "cfg" && text(i + 4) == "test" && text(i + 5) == ")" {
            let mut k = i + 7;
            while text(k) == "#" {
                while text(k) != "]" {
                    k += 1;
                }
                k += 1;
            }
            k += usize::from(text(k) == "pub");
            if text(k) == "mod" && text(k + 2) == "{" {
                i = close(k + 2) + 1;
                continue;
            }
        }
        if text(i) == "fn" && text(i + 1).chars().next().is_some_and(|c| c.is_alphabetic() || c == '_') {
            let mut k = i + 2;
            let mut depth = 0i32;
            while k < toks.len() {
                match text(k) {
                    "(" | "[" => depth += 1,
                    ")" | "]" => depth -= 1,
                    "{" | ";" if depth == 0 => break,
                    _ => {}
                }
                k += 1;
            }
            if text(k) == "{" {
                let end = close(k);
                out.push((text(i + 1).to_string(), toks[i].line, toks[end].line - toks[i].line + 1));
            }
        }
        i += 1;
    }
    out
}

#[test]
fn no_function_is_over_150_lines_outside_tests() {
    let mut found = Vec::new();
    let mut shrunk = Vec::new();
    let mut seen = Vec::new();
    for (file, rel) in source_files() {
        let src = std::fs::read_to_string(&file).unwrap();
        for (name, line, len) in functions(&src) {
            let listed = LONGER.iter().find(|(f, n, _)| *f == rel && *n == name);
            match listed {
                Some(&(_, _, was)) => {
                    seen.push((rel.clone(), name.clone()));
                    if len > was {
                        found.push(format!(
                            "{rel}:{line}: {name} is {len} lines, longer than the {was} it was listed at"
                        ));
                    } else if len <= LIMIT {
                        shrunk.push(format!("{rel}: {name} is now {len} lines: take it out of LONGER"));
                    }
                }
                None if len > LIMIT => found.push(format!("{rel}:{line}: {name} is {len} lines (at most {LIMIT})")),
                None => {}
            }
        }
    }
    let gone: Vec<String> = LONGER
        .iter()
        .filter(|(f, n, _)| !seen.iter().any(|(sf, sn)| sf == f && sn == n))
        .map(|(f, n, _)| format!("{f}: {n} is gone: take it out of LONGER"))
        .collect();
    let all: Vec<String> = found.into_iter().chain(shrunk).chain(gone).collect();
    assert!(all.is_empty(), "function lengths (docs/architecture.md, Conventions):\n  {}", all.join("\n  "));
}

#[test]
fn lengths_are_counted_from_fn_to_its_closing_brace() {
    let src = "fn a() {\n    let s = \"}\";\n    // }\n}\n\ntrait T {\n    fn decl(&self);\n    fn b(&self) -> [u8; 2] {\n        [0; 2]\n    }\n}\n\n#[cfg(test)]\n#[allow(dead_code)]\nmod tests {\n    fn hidden() {}\n}\nfn c<F: Fn(u8) -> u8>(f: F) where F: Copy { f(1); }\n";
    let got = functions(src);
    assert_eq!(
        got,
        vec![("a".to_string(), 1, 4), ("b".to_string(), 8, 3), ("c".to_string(), 18, 1)],
        "a literal brace and a comment do not count; a declaration has no body; a test module is skipped"
    );
}

/// A CLI command's file, at most (`docs/architecture.md`, Conventions): a face parses, prints
/// and calls; a command file longer than this holds a rule or a workflow that belongs in a
/// library, or is two files (its words, its plot) in one.
const COMMAND_LIMIT: usize = 350;

/// Command files longer when the rule became a test, with their lengths then (none now). Shrink,
/// never add.
const LONGER_COMMANDS: &[(&str, usize)] = &[];

#[test]
fn no_cli_command_file_is_over_350_lines() {
    let root = workspace();
    let mut found = Vec::new();
    for file in files_under(&root.join("crates/cli/src/cmd"), Some(".rs")) {
        let rel = file.strip_prefix(&root).unwrap().to_string_lossy().replace('\\', "/");
        let n = std::fs::read_to_string(&file).unwrap().lines().count();
        match LONGER_COMMANDS.iter().find(|(f, _)| *f == rel) {
            Some(&(_, was)) if n > was => {
                found.push(format!("{rel}: {n} lines, longer than the {was} it was listed at"))
            }
            Some(_) if n <= COMMAND_LIMIT => {
                found.push(format!("{rel}: now {n} lines: take it out of LONGER_COMMANDS"))
            }
            None if n > COMMAND_LIMIT => found.push(format!("{rel}: {n} lines (at most {COMMAND_LIMIT})")),
            _ => {}
        }
    }
    assert!(found.is_empty(), "CLI command files (docs/architecture.md, Conventions):\n  {}", found.join("\n  "));
}
