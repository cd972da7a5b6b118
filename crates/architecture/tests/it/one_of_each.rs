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

/// A median written inline instead of called: the middle of a sorted or selected sample taken
/// by hand (`v[v.len() / 2]`, `v[(v.len() - 1) / 2]`, `select_nth_unstable`), in every crate's
/// `src/` (the CLI and the Python module included; `#[cfg(test)]` modules are tests).
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
        let toks = tokens(code);
        let t: Vec<&str> = toks.iter().map(|t| t.text.as_str()).collect();
        for k in 0..t.len() {
            let middle = t[k..].starts_with(&["len", "(", ")", "/", "2", "]"])
                || t[k..].starts_with(&["len", "(", ")", "-", "1", ")", "/", "2", "]"]);
            let allowed = INLINE_ALLOWED.iter().any(|(f, first, _)| *f == rel && t[k] == *first);
            if (middle || t[k].starts_with("select_nth_unstable")) && !allowed {
                found.push(format!("{rel}:{}: {}", toks[k].line, t[k..(k + 9).min(t.len())].concat()));
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
