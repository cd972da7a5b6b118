//! The documentation a reader opens first stays usable: the README is short (under 200 lines,
//! no line over 120 characters outside code blocks and tables), and every relative link and
//! anchor in the README, the crates' READMEs and `docs/**/*.md` leads somewhere (a file or
//! folder of the repository, and a heading of the target when the link names one, with the
//! anchors a code host makes from headings).

use std::collections::HashMap;
use std::path::{Path, PathBuf};

fn repository_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// `line` with its inline code spans (`` `...` ``) blanked out: a link written as code is an
/// example, not a link.
fn without_code_spans(line: &str) -> String {
    let mut out = String::with_capacity(line.len());
    let mut in_code = false;
    for c in line.chars() {
        if c == '`' {
            in_code = !in_code;
            out.push(' ');
        } else {
            out.push(if in_code { ' ' } else { c });
        }
    }
    out
}

/// The lines of `text` outside fenced code blocks, with their 1-based numbers.
fn prose_lines(text: &str) -> Vec<(usize, &str)> {
    let mut fenced = false;
    let mut out = vec![];
    for (i, line) in text.lines().enumerate() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            continue;
        }
        if !fenced {
            out.push((i + 1, line));
        }
    }
    out
}

/// The targets of the inline links and images of `line` (`[text](target)`, `![alt](target)`,
/// an optional `"title"` dropped).
fn link_targets(line: &str) -> Vec<String> {
    let line = without_code_spans(line);
    let mut out = vec![];
    let mut rest = line.as_str();
    while let Some(i) = rest.find("](") {
        let after = &rest[i + 2..];
        let Some(end) = after.find(')') else { break };
        let target = after[..end].split_whitespace().next().unwrap_or("").trim_matches(['<', '>']);
        if !target.is_empty() {
            out.push(target.to_string());
        }
        rest = &after[end..];
    }
    out
}

/// The anchor a code host gives a heading: lower case, punctuation other than `-` and `_`
/// dropped, spaces made hyphens; a repeated heading gets `-1`, `-2`, ...
fn anchors(text: &str) -> Vec<String> {
    let mut seen: HashMap<String, usize> = HashMap::new();
    let mut out = vec![];
    for (_, line) in prose_lines(text) {
        let t = line.trim_start();
        if !t.starts_with('#') {
            continue;
        }
        let title = t.trim_start_matches('#');
        if !title.starts_with(' ') {
            continue;
        }
        let slug: String = title
            .trim()
            .to_lowercase()
            .chars()
            .filter(|c| c.is_alphanumeric() || *c == ' ' || *c == '-' || *c == '_')
            .map(|c| if c == ' ' { '-' } else { c })
            .collect();
        let n = seen.entry(slug.clone()).or_insert(0);
        out.push(if *n == 0 { slug.clone() } else { format!("{slug}-{n}") });
        *n += 1;
    }
    out
}

/// Every broken relative link of the Markdown file `md` (`path:line: why`).
fn broken_links(md: &Path, root: &Path) -> Vec<String> {
    let text = std::fs::read_to_string(md).unwrap_or_else(|e| panic!("{}: {e}", md.display()));
    let rel = md.strip_prefix(root).unwrap_or(md).display().to_string();
    let dir = md.parent().unwrap();
    let mut out = vec![];
    for (n, line) in prose_lines(&text) {
        for target in link_targets(line) {
            if target.contains("://") || target.starts_with("mailto:") {
                continue;
            }
            let (path, anchor) = match target.split_once('#') {
                Some((p, a)) => (p, Some(a)),
                None => (target.as_str(), None),
            };
            let file = if path.is_empty() { md.to_path_buf() } else { dir.join(path) };
            if !file.exists() {
                out.push(format!("{rel}:{n}: link to {target}: {} does not exist", file.display()));
                continue;
            }
            if let Some(a) = anchor {
                let heads = if file.extension().is_some_and(|e| e == "md") {
                    anchors(&std::fs::read_to_string(&file).unwrap())
                } else {
                    vec![]
                };
                if !heads.iter().any(|h| h == a) {
                    out.push(format!("{rel}:{n}: link to {target}: no heading makes the anchor #{a}"));
                }
            }
        }
    }
    out
}

/// README.md, every crate's README.md and every `.md` under docs/.
fn documentation_files(root: &Path) -> Vec<PathBuf> {
    fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
        let mut entries: Vec<PathBuf> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().path()).collect();
        entries.sort();
        for p in entries {
            if p.is_dir() {
                walk(&p, out);
            } else if p.extension().is_some_and(|e| e == "md") {
                out.push(p);
            }
        }
    }
    let mut files = vec![root.join("README.md")];
    let mut crates: Vec<PathBuf> = std::fs::read_dir(root.join("crates")).unwrap().map(|e| e.unwrap().path()).collect();
    crates.sort();
    files.extend(crates.into_iter().map(|c| c.join("README.md")).filter(|p| p.is_file()));
    walk(&root.join("docs"), &mut files);
    files
}

#[test]
fn every_relative_link_and_anchor_in_the_documentation_resolves() {
    let root = repository_root();
    let files = documentation_files(&root);
    assert!(files.len() >= 10, "found only {files:?}");
    let broken: Vec<String> = files.iter().flat_map(|f| broken_links(f, &root)).collect();
    assert!(broken.is_empty(), "{} broken link(s):\n{}", broken.len(), broken.join("\n"));
}

#[test]
fn the_readme_is_short_and_its_prose_lines_fit_a_screen() {
    let text = std::fs::read_to_string(repository_root().join("README.md")).unwrap();
    let n = text.lines().count();
    assert!(n < 200, "README.md has {n} lines: at most 199 (move the rest into docs/guide/)");
    let long: Vec<String> = prose_lines(&text)
        .into_iter()
        .filter(|(_, l)| !l.trim_start().starts_with('|') && l.chars().count() > 120)
        .map(|(i, l)| format!("README.md:{i}: {} characters", l.chars().count()))
        .collect();
    assert!(long.is_empty(), "lines over 120 characters outside code and tables:\n{}", long.join("\n"));
}

/// The checker itself, on a folder written here: a broken file link and a broken anchor are
/// found, good ones and links inside code are not.
#[test]
fn the_checker_finds_a_broken_link_and_a_broken_anchor() {
    let dir = tempfile_dir();
    std::fs::write(dir.join("b.md"), "# Title\n\n## A section: with `code`\n\n## Twice\n\n## Twice\n").unwrap();
    std::fs::write(
        dir.join("a.md"),
        "[ok](b.md) [ok](b.md#a-section-with-code) [ok](b.md#twice-1) [ok](#top) [web](https://x.org/y)\n\
         # Top\n\
         [gone](missing.md) [bad anchor](b.md#nope) `[code](nowhere.md)`\n\
         ```\n[fenced](nowhere.md)\n```\n",
    )
    .unwrap();
    let broken = broken_links(&dir.join("a.md"), &dir);
    assert_eq!(broken.len(), 2, "{broken:#?}");
    assert!(broken[0].contains("a.md:3") && broken[0].contains("missing.md"), "{}", broken[0]);
    assert!(broken[1].contains("#nope"), "{}", broken[1]);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A fresh folder under the system's temporary directory (this crate has no tempfile).
fn tempfile_dir() -> PathBuf {
    let d = std::env::temp_dir().join(format!("instpol-docs-links-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Every page of the guide a message names (`docs/guide/NAME.md` in a crate's source, e.g.
/// `instrument::ZERO_ANGLE_GUIDE`) exists, so that an error's pointer leads somewhere.
#[test]
fn every_guide_page_a_message_names_exists() {
    let root = repository_root();
    let mut named = 0;
    let mut missing = vec![];
    let mut stack = vec![root.join("crates")];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") {
                let text = std::fs::read_to_string(&p).unwrap();
                for (i, _) in text.match_indices("\"docs/guide/") {
                    let name: String = text[i + 1..].chars().take_while(|c| *c != '"' && *c != '#').collect();
                    if !name.ends_with(".md") {
                        continue;
                    }
                    named += 1;
                    if !root.join(&name).is_file() {
                        missing.push(format!("{}: {name}", p.display()));
                    }
                }
            }
        }
    }
    assert!(named >= 1, "no message names a guide page");
    assert!(missing.is_empty(), "guide pages named in messages that do not exist:\n{}", missing.join("\n"));
}
