//! Every shell example of the README and the guide (`docs/**/*.md`) runs against the built
//! binary, and its shown output is checked: an example that stops working, or a flag an
//! example uses that is renamed or deleted, fails here.
//!
//! How a Markdown file is read (in order, all blocks of one file in one temporary folder that
//! holds links to the repository's `instruments/` and `tests/`, so that later blocks use what
//! earlier ones wrote):
//!
//! - ```` ```toml file=NAME ```` (any language, with `file=`): the block's text is written to
//!   `NAME`, as a reader would save it.
//! - ```` ```console ````: lines starting with `$ ` are commands; the lines under a command,
//!   up to the next one, are its output as shown. A line `...` stands for any number of lines,
//!   and `[..]` inside a line for any text; the output checked is stdout followed by stderr.
//! - ```` ```sh ````: every line is a command (a line ending in `\` goes on on the next; a
//!   `# comment` after it is dropped), its output not shown. `cargo run --release -p instpol --`
//!   is the binary; the lines that install the tool or run the test suite itself
//!   (`cargo install`, `cargo test`, `pip`) are left out, because this test is part of that
//!   suite and CI installs the Python package itself. ```` ```sh data=DIR ```` runs on the
//!   files of `DIR` (relative to the repository, linked into the folder): real data kept
//!   outside the repository, and when `DIR` is missing the block is skipped, loudly. A
//!   ```` ```console data=DIR ```` block does the same and checks its shown output.
//!
//! The shown output is checked against stdout, or else against stdout followed by stderr.
//! Every command must exit with 0. Commands run through `sh` with the built binary first on
//! `PATH`, so globs (`frames/*.fits`) expand as in a reader's shell.

use std::path::{Path, PathBuf};
use std::process::Command;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// One fenced block: its info string, its lines (the fence's indentation removed) and where
/// it starts (1-based line of the opening fence).
struct Block {
    info: String,
    lines: Vec<String>,
    line: usize,
}

fn blocks(text: &str) -> Vec<Block> {
    let mut out = vec![];
    let mut open: Option<(usize, String, usize, Vec<String>)> = None;
    for (i, raw) in text.lines().enumerate() {
        let indent = raw.len() - raw.trim_start().len();
        let t = raw.trim_start();
        match open.as_mut() {
            None => {
                if let Some(info) = t.strip_prefix("```") {
                    open = Some((indent, info.trim().to_string(), i + 1, vec![]));
                }
            }
            Some((ind, _, _, lines)) => {
                if t == "```" {
                    let (_, info, line, lines) = open.take().unwrap();
                    out.push(Block { info, lines, line });
                } else {
                    let cut = (*ind).min(indent);
                    lines.push(raw[cut..].to_string());
                }
            }
        }
    }
    assert!(open.is_none(), "a fenced block is not closed");
    out
}

/// Markdown files whose examples are run: README.md and every `.md` under docs/.
fn markdown_files() -> Vec<PathBuf> {
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
    let mut files = vec![root().join("README.md")];
    walk(&root().join("docs"), &mut files);
    files
}

/// Whether `expected` (with `...` lines and `[..]` in lines) matches `actual`.
fn matches(expected: &[String], actual: &[&str]) -> bool {
    fn line_matches(pat: &str, line: &str) -> bool {
        let parts: Vec<&str> = pat.split("[..]").collect();
        if parts.len() == 1 {
            return pat.trim_end() == line.trim_end();
        }
        let line = line.trim_end();
        let Some(mut rest) = line.strip_prefix(parts[0]) else { return false };
        for (k, part) in parts[1..].iter().enumerate() {
            let part = if k + 2 == parts.len() { part.trim_end() } else { part };
            if k + 2 == parts.len() {
                return rest.ends_with(part);
            }
            match rest.find(part) {
                Some(i) => rest = &rest[i + part.len()..],
                None => return false,
            }
        }
        true
    }
    match expected.split_first() {
        None => actual.is_empty(),
        Some((first, more)) if first.trim() == "..." => (0..=actual.len()).any(|k| matches(more, &actual[k..])),
        Some((first, more)) => actual.first().is_some_and(|a| line_matches(first, a)) && matches(more, &actual[1..]),
    }
}

/// Why `sh` lines are left out (see the module documentation), or `None` to run them.
fn skipped(cmd: &str) -> Option<&'static str> {
    let first = cmd.split_whitespace().next().unwrap_or("");
    if cmd.starts_with("cargo test") {
        Some("the test suite itself")
    } else if cmd.starts_with("cargo install") || first == "pip" {
        Some("installation")
    } else {
        None
    }
}

/// Run `cmd` in `dir` with the binary first on PATH: (exit code, stdout then stderr, the
/// number of stdout's lines).
fn run(cmd: &str, dir: &Path) -> (i32, String, usize) {
    let bin = PathBuf::from(env!("CARGO_BIN_EXE_instpol"));
    let path = format!("{}:{}", bin.parent().unwrap().display(), std::env::var("PATH").unwrap_or_default());
    let cmd = cmd.replace("cargo run --release -p instpol --", "instpol");
    let o = Command::new("sh").arg("-c").arg(&cmd).current_dir(dir).env("PATH", path).output().unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout);
    let text = format!("{stdout}{}", String::from_utf8_lossy(&o.stderr));
    (o.status.code().unwrap_or(-1), text, stdout.lines().count())
}

/// The files of a block's `data=DIR` (relative to the repository) linked into `dir`: false
/// (and a loud note) when `DIR` is missing, and the block is skipped; true without `data=`.
fn link_data(info: &str, dir: &Path, name: &str, line: usize) -> bool {
    let Some(data) = info.split_whitespace().find_map(|w| w.strip_prefix("data=")) else { return true };
    let src = root().join(data);
    let Ok(entries) = std::fs::read_dir(&src) else {
        eprintln!("skipping {name}:{line}: its data {} is not there", src.display());
        return false;
    };
    for e in entries {
        let p = e.unwrap().path();
        let _ = std::os::unix::fs::symlink(&p, dir.join(p.file_name().unwrap()));
    }
    true
}

/// The examples of one Markdown file, run in order in a fresh folder: the failures found.
fn run_file(md: &Path) -> Vec<String> {
    let text = std::fs::read_to_string(md).unwrap();
    let name = md.strip_prefix(root()).unwrap_or(md).display().to_string();
    let dir = tempfile::tempdir().unwrap();
    for sub in ["instruments", "tests"] {
        std::os::unix::fs::symlink(root().join(sub), dir.path().join(sub)).unwrap();
    }
    let mut failures = vec![];
    let mut check = |cmd: &str, expected: &[String], line: usize| {
        let (code, out, stdout_lines) = run(cmd, dir.path());
        let actual: Vec<&str> = out.lines().collect();
        let stdout: Vec<&str> = actual[..stdout_lines].to_vec();
        if code != 0 {
            failures.push(format!("{name}:{line}: `{cmd}` exited with {code}:\n{out}"));
        } else if !expected.is_empty() && !matches(expected, &stdout) && !matches(expected, &actual) {
            failures.push(format!(
                "{name}:{line}: `{cmd}`: its output does not match the one shown.\nshown:\n{}\nactual:\n{out}",
                expected.join("\n")
            ));
        }
    };
    for b in blocks(&text) {
        if let Some(file) = b.info.split_whitespace().find_map(|w| w.strip_prefix("file=")) {
            let mut body = b.lines.join("\n");
            body.push('\n');
            std::fs::write(dir.path().join(file), body).unwrap();
            continue;
        }
        match b.info.as_str() {
            info if info == "console" || info.starts_with("console ") => {
                if !link_data(info, dir.path(), &name, b.line) {
                    continue;
                }
                let mut cmd: Option<(String, usize)> = None;
                let mut expected: Vec<String> = vec![];
                for (k, l) in b.lines.iter().enumerate() {
                    if let Some(c) = l.strip_prefix("$ ") {
                        if let Some((c0, at)) = cmd.take() {
                            check(&c0, &expected, at);
                        }
                        cmd = Some((c.to_string(), b.line + 1 + k));
                        expected.clear();
                    } else {
                        assert!(cmd.is_some(), "{name}:{}: a console block must start with `$ `", b.line);
                        expected.push(l.clone());
                    }
                }
                if let Some((c0, at)) = cmd {
                    check(&c0, &expected, at);
                }
            }
            info if info == "sh" || info.starts_with("sh ") => {
                if !link_data(info, dir.path(), &name, b.line) {
                    continue;
                }
                let mut pending = String::new();
                for (k, l) in b.lines.iter().enumerate() {
                    let c = l.split("  #").next().unwrap().trim();
                    if let Some(head) = c.strip_suffix('\\') {
                        pending.push_str(head);
                        continue;
                    }
                    let c = format!("{pending}{c}");
                    pending.clear();
                    if c.is_empty() || c.starts_with('#') || skipped(&c).is_some() {
                        continue;
                    }
                    check(&c, &[], b.line + 1 + k);
                }
            }
            _ => {}
        }
    }
    failures
}

#[test]
fn the_output_matcher_matches_what_it_should_and_nothing_else() {
    let s = |v: &[&str]| v.iter().map(|x| x.to_string()).collect::<Vec<_>>();
    assert!(matches(&s(&["a", "...", "d"]), &["a", "b", "c", "d"]));
    assert!(matches(&s(&["...", "c", "..."]), &["a", "b", "c", "d"]));
    assert!(matches(&s(&["P = [..] %"]), &["P = 0.967 %"]));
    assert!(matches(&s(&["x [..] y [..]"]), &["x 1 y 2"]));
    assert!(!matches(&s(&["a", "d"]), &["a", "b", "d"]));
    assert!(!matches(&s(&["P = [..] deg"]), &["P = 0.967 %"]));
    assert!(!matches(&s(&["...", "e"]), &["a", "b"]));
    assert!(matches(&[], &[]));
    assert!(!matches(&[], &["a"]));
}

#[test]
fn the_block_reader_finds_indented_blocks_and_files() {
    let b = blocks("text\n\n   ```console\n   $ instpol x\n   out\n   ```\n```toml file=a.toml\nk = 1\n```\n");
    assert_eq!(b.len(), 2);
    assert_eq!(b[0].info, "console");
    assert_eq!(b[0].lines, ["$ instpol x", "out"]);
    assert_eq!(b[0].line, 3);
    assert_eq!(b[1].info, "toml file=a.toml");
    assert_eq!(b[1].lines, ["k = 1"]);
}

/// The examples of every documentation file, the files run two at a time.
#[test]
fn every_shell_example_in_the_readme_and_the_guide_runs_with_its_shown_output() {
    let mut files = markdown_files();
    assert!(files.len() >= 10, "{files:?}");
    // While writing a page: INSTPOL_DOC_ONLY=scene-file runs the files whose path holds it.
    if let Ok(only) = std::env::var("INSTPOL_DOC_ONLY") {
        files.retain(|f| f.to_string_lossy().contains(&only));
        eprintln!("INSTPOL_DOC_ONLY={only}: running {files:?} only");
    }
    let next = std::sync::Mutex::new(files.into_iter());
    let failures = std::sync::Mutex::new(vec![]);
    std::thread::scope(|s| {
        for _ in 0..2 {
            s.spawn(|| loop {
                let Some(md) = next.lock().unwrap().next() else { break };
                let f = run_file(&md);
                failures.lock().unwrap().extend(f);
            });
        }
    });
    let failures = failures.into_inner().unwrap();
    assert!(failures.is_empty(), "{} example(s) failed:\n\n{}", failures.len(), failures.join("\n\n"));
}
