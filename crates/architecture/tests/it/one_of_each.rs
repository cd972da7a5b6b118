//! One of each shared helper: the workspace has one median of a sample
//! (`stokes::stats::robust::median`, whose `Middle` says which middle an even count takes) and
//! one factor from a median absolute deviation to a Gaussian sigma
//! (`stokes::stats::robust::MAD_TO_SIGMA`, `1 / Phi^-1(3/4)`). A second definition drifts from
//! the first (the workspace once had seven medians of two definitions and the factor written
//! out eighteen times, rounded to five digits in some places and not in others). One nonlinear
//! least-squares loop (`fit::lsq`, its policies named there): the fits once had four loops with
//! four damping ladders and failure behaviours.

use crate::common;

use common::{code_only, files_under, source_files, tokens, workspace};

/// The module that defines the median and the factor.
const ROBUST: &str = "crates/stokes/src/stats/robust.rs";

/// Functions named `median*` that are not a second median of a sample, with why.
const ALLOWED: &[(&str, &str, &str)] = &[
    ("crates/stokes/src/stats/circular.rs", "median", "the circular median of angles (on a circle, not a line)"),
    ("crates/stokes/src/stats/rice.rs", "median", "the Rice distribution's median (of a distribution, not a sample)"),
    // The binning's and the background mesh's speed kernels: windowed and integer-key searches
    // that give the one median exactly (crates/skyfield/tests/it/clip_reference.rs and the module's
    // tests check them to the bit against it).
    ("crates/skyfield/src/bin.rs", "median", "a clipping column's median, searched in its window"),
    ("crates/skyfield/src/bin.rs", "median_near", "the windowed search, for its tests"),
    ("crates/skyfield/src/bin.rs", "median_near_by", "the windowed search"),
    ("crates/skyfield/src/bin.rs", "median_and_top", "the windowed search with the largest value"),
    ("crates/skyfield/src/bin.rs", "median_in_window", "the selection inside a window"),
    ("crates/skyfield/src/bin.rs", "median_of_keys", "the selection on integer keys"),
];

/// Every `fn median*` defined in `crates/*/src` (test functions left out), as
/// `(file relative to the workspace, name, line)`.
fn median_definitions() -> Vec<(String, String, usize)> {
    let mut out = Vec::new();
    for (path, rel) in source_files() {
        let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{rel}: {e}"));
        let toks = tokens(&code_only(&text));
        for (k, w) in toks.windows(2).enumerate() {
            if w[0].text == "fn" && w[1].text.starts_with("median") {
                // `#[test]` just before (possibly after other attributes): a test, not a median.
                let before: Vec<&str> = toks[k.saturating_sub(12)..k].iter().map(|t| t.text.as_str()).collect();
                let is_test = before.windows(4).any(|a| a == ["#", "[", "test", "]"]);
                if !is_test {
                    out.push((rel.clone(), w[1].text.clone(), w[1].line));
                }
            }
        }
    }
    out
}

#[test]
fn one_median() {
    let defs = median_definitions();
    assert!(
        defs.iter().any(|(f, n, _)| f == ROBUST && n == "median"),
        "the one median is no longer {ROBUST}'s `median`: update this test's ROBUST"
    );
    let others: Vec<String> = defs
        .iter()
        .filter(|(f, n, _)| f != ROBUST && !ALLOWED.iter().any(|(af, an, _)| af == f && an == n))
        .map(|(f, n, l)| format!("{f}:{l}: fn {n}"))
        .collect();
    assert!(
        others.is_empty(),
        "a second median is defined (use stokes::stats::robust::median with the Middle you need, \
         or list a speed kernel of the same definition in ALLOWED with why):\n  {}",
        others.join("\n  ")
    );
    // Each allowed one still exists (a stale entry would allow a new function of its name).
    for (f, n, why) in ALLOWED {
        assert!(defs.iter().any(|(df, dn, _)| df == f && dn == n), "ALLOWED lists {f}: fn {n} ({why}), which is gone");
    }
}

#[test]
fn one_mad_to_sigma() {
    // The needle is built here so that this file does not hold it.
    let needle = concat!("1.48", "26");
    let root = workspace();
    let mut found = Vec::new();
    let is_def = |l: &str| l.trim_start().starts_with("pub const MAD_TO_SIGMA: f64");
    let mut definition = false;
    for p in files_under(&root.join("crates"), None) {
        let Ok(text) = std::fs::read_to_string(&p) else { continue };
        let rel = p.strip_prefix(&root).expect("under the workspace").to_string_lossy().replace('\\', "/");
        let lines: Vec<&str> = text.lines().collect();
        definition |= rel == ROBUST && lines.iter().any(|l| is_def(l));
        for (k, line) in lines.iter().enumerate() {
            // The constant's definition and the doc comment just above it give its value.
            let doc_of_def = line.trim_start().starts_with("///")
                && lines[k + 1..].iter().find(|l| !l.trim_start().starts_with("///")).is_some_and(|l| is_def(l));
            if line.contains(needle) && !(rel == ROBUST && (is_def(line) || doc_of_def)) {
                found.push(format!("{rel}:{}: {}", k + 1, line.trim()));
            }
        }
    }
    assert!(definition, "MAD_TO_SIGMA is no longer defined in {ROBUST}: update this test");
    assert!(
        found.is_empty(),
        "the MAD-to-sigma factor is written out (use stokes::stats::robust::MAD_TO_SIGMA, or in a test a \
         closed form computed there, e.g. 1 / the inverse normal of 0.75):\n  {}",
        found.join("\n  ")
    );
}

/// The one least-squares loop's file.
const LSQ: &str = "crates/fit/src/lsq.rs";

#[test]
fn one_least_squares_loop() {
    let root = workspace();
    let mut found = Vec::new();
    for p in files_under(&root.join("crates"), Some(".rs")) {
        let rel = p.strip_prefix(&root).expect("under the workspace").to_string_lossy().replace('\\', "/");
        let parts: Vec<&str> = rel.split('/').collect();
        if parts.len() < 4 || parts[2] != "src" || rel == LSQ {
            continue;
        }
        let text = std::fs::read_to_string(&p).unwrap_or_else(|e| panic!("{rel}: {e}"));
        let toks = tokens(&code_only(&text));
        for (k, t) in toks.iter().enumerate() {
            let next: Vec<&str> = toks[k + 1..(k + 3).min(toks.len())].iter().map(|t| t.text.as_str()).collect();
            // A second solver (argmin's executor), or a damping ladder written out.
            if t.text == "argmin" || (t.text == "lambda" && next == ["*", "="]) {
                found.push(format!("{rel}:{}: {}", t.line, t.text));
            }
        }
    }
    assert!(root.join(LSQ).is_file(), "{LSQ} is gone: update this test");
    assert!(
        found.is_empty(),
        "a nonlinear least-squares loop outside {LSQ} (run fit::lsq with a policy of its own):\n  {}",
        found.join("\n  ")
    );
}

/// Where a sample's middle is taken by hand on purpose: speed kernels that give the one median
/// exactly (their tests check them to the bit against it), with why.
/// `(file, the first token of what is found there, why)`.
const INLINE_ALLOWED: &[(&str, &str, &str)] = &[
    ("crates/stokes/src/stats/robust.rs", "select_nth_unstable_by", "the one median itself"),
    ("crates/skyfield/src/bin.rs", "select_nth_unstable", "the windowed and integer-key searches listed in ALLOWED"),
    (
        "crates/skyfield/src/aperture.rs",
        "select_nth_unstable",
        "the centroid's background ring: its upper middle selected on the integer keys of the total order",
    ),
];

/// Where a token sequence takes a sample's middle rank: `len() / 2` or `(len() - 1) / 2` (the
/// receiver written before `len`), as `(first token of the receiver, index after the rank)`.
fn middle_rank(t: &[&str], k: usize) -> Option<(usize, usize)> {
    let end = if t[k..].starts_with(&["len", "(", ")", "/", "2"]) {
        k + 5
    } else if t[k..].starts_with(&["len", "(", ")", "-", "1", ")", "/", "2"]) {
        k + 8
    } else {
        return None;
    };
    // The receiver: `v.`, `self.v.`, `a.b.c.` (identifiers and dots) before `len`.
    let mut start = k;
    while start >= 2 && t[start - 1] == "." && t[start - 2].chars().all(|c| c.is_alphanumeric() || c == '_') {
        start -= 2;
    }
    // `(v.len() - 1) / 2` opens a parenthesis before its receiver.
    if end == k + 8 {
        start = start.checked_sub(1).filter(|&s| t[s] == "(")?;
    }
    Some((start, end))
}

/// The inline medians of one file's code (test modules already cut off): the middle of a
/// sample taken by hand, as `(line, what)`. Found: `v[v.len() / 2]` and `v[(v.len() - 1) / 2]`;
/// `v.get(v.len() / 2)` and `.nth(..)`; a name bound to that rank (`let mid = v.len() / 2;`)
/// and then used as an index (`v[mid]`, `v.get(mid)`, `.nth(mid)`); and any
/// `select_nth_unstable*`.
fn inline_medians(code: &str) -> Vec<(usize, String, String)> {
    let toks = tokens(code);
    let t: Vec<&str> = toks.iter().map(|t| t.text.as_str()).collect();
    let show = |k: usize| t[k..(k + 9).min(t.len())].concat();
    let mut found = Vec::new();
    let mut names: Vec<&str> = Vec::new();
    for k in 0..t.len() {
        if t[k].starts_with("select_nth_unstable") {
            found.push((toks[k].line, t[k].to_string(), show(k)));
            continue;
        }
        let Some((start, end)) = middle_rank(&t, k) else { continue };
        let next = t.get(end).copied().unwrap_or("");
        let call = start >= 2 && t[start - 1] == "(" && matches!(t[start - 2], "get" | "nth");
        if next == "]" || (next == ")" && call) {
            found.push((toks[k].line, t[k].to_string(), show(k)));
        } else if next == ";" && start >= 3 && t[start - 1] == "=" {
            // `let name =` or `let mut name =`.
            let bound = t[start - 3] == "let" || (start >= 4 && t[start - 4..start - 2] == ["let", "mut"]);
            if bound {
                names.push(t[start - 2]);
            }
        }
    }
    // A name bound to the middle rank, used as an index.
    for k in 1..t.len().saturating_sub(1) {
        if names.contains(&t[k]) {
            let indexed = t[k - 1] == "[" && t[k + 1] == "]";
            let called = k >= 2 && t[k - 1] == "(" && matches!(t[k - 2], "get" | "nth") && t[k + 1] == ")";
            if indexed || called {
                found.push((toks[k].line, t[k].to_string(), show(k.saturating_sub(2))));
            }
        }
    }
    found
}

/// A median written inline instead of called: the middle of a sorted or selected sample taken
/// by hand ([`inline_medians`]), in every crate's `src/` (the CLI and the Python module
/// included; `#[cfg(test)]` modules are tests).
#[test]
fn no_inline_median() {
    let mut found = Vec::new();
    for (path, rel) in source_files() {
        let text = std::fs::read_to_string(&path).unwrap();
        let code = code_only(&text);
        // The code before the first `#[cfg(test)]` module: unit tests sit at a file's end.
        let code = match code.find("#[cfg(test)]") {
            Some(k) => &code[..k],
            None => &code[..],
        };
        for (line, first, what) in inline_medians(code) {
            let allowed = INLINE_ALLOWED.iter().any(|(f, a, _)| *f == rel && first == *a);
            if !allowed {
                found.push(format!("{rel}:{line}: {what}"));
            }
        }
    }
    assert!(
        found.is_empty(),
        "a median written inline (call stokes::stats::robust::median with the Middle it takes, or list a \
         kernel of the same definition in INLINE_ALLOWED with why):\n  {}",
        found.join("\n  ")
    );
}

/// The finder on code written out: each way of taking the middle by hand is found once, and
/// a half length that is not an index (a capacity, a count) is not.
#[test]
fn inline_medians_are_found_in_each_form() {
    let found = |code: &str| inline_medians(code).into_iter().map(|f| f.0).collect::<Vec<_>>();
    let code = "fn a(v: &mut Vec<f64>) -> f64 {\n    v[v.len() / 2]\n}\n\
                fn b(s: &S) -> f64 {\n    s.d[(s.d.len() - 1) / 2]\n}\n\
                fn c(d: &[f64]) -> f64 {\n    d.get(d.len() / 2).copied().unwrap_or(0.1)\n}\n\
                fn d(v: &[f64]) -> f64 {\n    let mid = v.len() / 2;\n    v[mid]\n}\n\
                fn e(v: &mut [f64]) -> f64 {\n    *v.select_nth_unstable_by(3, f64::total_cmp).1\n}\n\
                fn f(v: &[f64]) -> usize {\n    let half = v.len() / 2;\n    Vec::<f64>::with_capacity(v.len() / 2).len() + half\n}\n";
    assert_eq!(found(code), vec![2, 5, 8, 15, 12]);
}
