//! Reading the workspace's Rust sources for the rule tests: the files of a crate, their code
//! without comments and literals, and the module paths they use.

#![allow(dead_code)]

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The workspace's root folder.
pub fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..").canonicalize().expect("the workspace root")
}

/// Every file under `dir` (recursively, sorted) whose name ends with `ext` (`None`: all).
pub fn files_under(dir: &Path, ext: Option<&str>) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&d) else { continue };
        for e in entries.flatten() {
            let p = e.path();
            let name = e.file_name().to_string_lossy().to_string();
            if p.is_dir() {
                // Build output and Python environments are not sources.
                if !matches!(name.as_str(), "target" | ".venv" | "__pycache__" | ".git") {
                    stack.push(p);
                }
            } else if ext.is_none_or(|x| name.ends_with(x)) {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

/// Every Rust file of every crate's `src/` (sorted), with its path relative to the workspace
/// (`crates/fit/src/lsq.rs`): the code the design rules are about (tests are elsewhere).
pub fn source_files() -> Vec<(PathBuf, String)> {
    let root = workspace();
    files_under(&root.join("crates"), Some(".rs"))
        .into_iter()
        .filter_map(|p| {
            let rel = p.strip_prefix(&root).ok()?.to_string_lossy().replace('\\', "/");
            (rel.split('/').nth(2) == Some("src")).then_some((p, rel))
        })
        .collect()
}

/// `src` with every comment and every string and character literal blanked out (newlines
/// kept, so line numbers stay), leaving the code.
pub fn code_only(src: &str) -> String {
    let c: Vec<char> = src.chars().collect();
    let mut out = String::with_capacity(src.len());
    let blank = |out: &mut String, ch: char| out.push(if ch == '\n' { '\n' } else { ' ' });
    let ident = |ch: char| ch.is_alphanumeric() || ch == '_';
    let mut i = 0;
    while i < c.len() {
        let at = |k: usize| c.get(k).copied().unwrap_or('\0');
        let token_start = i == 0 || !ident(c[i - 1]);
        if c[i] == '/' && at(i + 1) == '/' {
            while i < c.len() && c[i] != '\n' {
                i += 1;
            }
        } else if c[i] == '/' && at(i + 1) == '*' {
            // Block comments nest.
            let mut depth = 0;
            while i < c.len() {
                if c[i] == '/' && at(i + 1) == '*' {
                    depth += 1;
                    out.push_str("  ");
                    i += 2;
                } else if c[i] == '*' && at(i + 1) == '/' {
                    depth -= 1;
                    out.push_str("  ");
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    blank(&mut out, c[i]);
                    i += 1;
                }
            }
        } else if token_start && (c[i] == 'r' || (c[i] == 'b' && at(i + 1) == 'r')) && {
            // A raw string: r"..", r#".."#, br#".."#.
            let mut k = i + if c[i] == 'b' { 2 } else { 1 };
            while at(k) == '#' {
                k += 1;
            }
            at(k) == '"'
        } {
            let start = i;
            i += if c[i] == 'b' { 2 } else { 1 };
            let mut hashes = 0;
            while c[i] == '#' {
                hashes += 1;
                i += 1;
            }
            i += 1;
            while i < c.len() && !(c[i] == '"' && (1..=hashes).all(|h| at(i + h) == '#')) {
                i += 1;
            }
            i = (i + 1 + hashes).min(c.len());
            (start..i).for_each(|k| blank(&mut out, c[k]));
        } else if c[i] == '"' {
            let start = i;
            i += 1;
            while i < c.len() && c[i] != '"' {
                i += if c[i] == '\\' { 2 } else { 1 };
            }
            i = (i + 1).min(c.len());
            (start..i).for_each(|k| blank(&mut out, c[k]));
        } else if c[i] == '\'' && (at(i + 1) == '\\' || (at(i + 2) == '\'' && at(i + 1) != '\'')) {
            // A character literal ('x', '\n', '\u{..}'); a lifetime or a label is code.
            let start = i;
            i += 1;
            while i < c.len() && c[i] != '\'' {
                i += if c[i] == '\\' { 2 } else { 1 };
            }
            i = (i + 1).min(c.len());
            (start..i).for_each(|k| blank(&mut out, c[k]));
        } else {
            out.push(c[i]);
            i += 1;
        }
    }
    out
}

/// A token of code: an identifier (or keyword, or number), `::`, or one other character.
#[derive(Debug, Clone, PartialEq)]
pub struct Token {
    pub text: String,
    pub line: usize,
}

/// The tokens of `code` (as [`code_only`] leaves it).
pub fn tokens(code: &str) -> Vec<Token> {
    let c: Vec<char> = code.chars().collect();
    let mut out = Vec::new();
    let (mut i, mut line) = (0, 1);
    while i < c.len() {
        let ch = c[i];
        if ch == '\n' {
            line += 1;
            i += 1;
        } else if ch.is_whitespace() {
            i += 1;
        } else if ch.is_alphanumeric() || ch == '_' {
            let s = i;
            while i < c.len() && (c[i].is_alphanumeric() || c[i] == '_') {
                i += 1;
            }
            out.push(Token { text: c[s..i].iter().collect(), line });
        } else if ch == ':' && c.get(i + 1) == Some(&':') {
            out.push(Token { text: "::".into(), line });
            i += 2;
        } else {
            out.push(Token { text: ch.to_string(), line });
            i += 1;
        }
    }
    out
}

/// A use of a module path in a file: the path's segments as written (`crate`, `super`, `self`
/// or a child module's name first) and the line.
#[derive(Debug, Clone, PartialEq)]
pub struct PathUse {
    /// The inline modules (`mod name { .. }`) the use is written in, outermost first.
    pub inline: Vec<String>,
    pub segments: Vec<String>,
    pub line: usize,
}

/// What a file says about modules: the file modules it declares (`mod name;`) and the paths it
/// uses that start with `crate`, `super`, `self` or one of those declared modules. Paths inside
/// `#[cfg(test)]` modules are left out (tests may reach anywhere; the layers are the code's).
#[derive(Debug, Default)]
pub struct FileModules {
    pub children: Vec<String>,
    pub uses: Vec<PathUse>,
}

fn is_ident(t: &str) -> bool {
    t.chars().next().is_some_and(|c| c.is_alphabetic() || c == '_')
}

/// The paths of a `use` tree (the tokens between `use` and `;`), each as its segments with its
/// line: `a::{b, c::d}` is `a::b` and `a::c::d`; `self` in a group and a glob `*` are the
/// group's own path; a rename (`as x`) ends a path.
fn use_tree(toks: &[Token]) -> Vec<(Vec<String>, usize)> {
    fn tree(toks: &[Token], i: &mut usize, prefix: &[String], out: &mut Vec<(Vec<String>, usize)>) {
        let mut path = prefix.to_vec();
        let line = toks.get(*i).map_or(0, |t| t.line);
        while let Some(t) = toks.get(*i).map(|t| t.text.as_str()) {
            match t {
                "::" => *i += 1,
                "{" => {
                    *i += 1;
                    while toks.get(*i).is_some_and(|t| t.text != "}") {
                        tree(toks, i, &path, out);
                        if toks.get(*i).is_some_and(|t| t.text == ",") {
                            *i += 1;
                        }
                    }
                    *i += 1;
                    return;
                }
                "as" => {
                    *i += 2;
                    break;
                }
                "*" => *i += 1,
                "self" if !path.is_empty() => *i += 1,
                _ if is_ident(t) => {
                    path.push(t.to_string());
                    *i += 1;
                }
                _ => break,
            }
        }
        if !path.is_empty() {
            out.push((path, line));
        }
    }
    let mut out = Vec::new();
    let mut i = 0;
    tree(toks, &mut i, &[], &mut out);
    out
}

/// The modules a file declares and the module paths it uses (see [`FileModules`]). `root`:
/// the crate root, whose paths through its own child modules (`pub use maps::StokesMap`) are
/// the crate's table of contents, not uses. A directory module's `mod.rs` (`dir`) is the root
/// of its folder: its `pub use child::Item` re-exports are that folder's table of contents,
/// while its other uses of a child (calls, private `use`) are uses.
pub fn file_modules(src: &str, root: bool) -> FileModules {
    file_modules_of(src, root, false)
}

/// [`file_modules`], with `dir` saying whether the file is a directory module's `mod.rs`.
pub fn file_modules_of(src: &str, root: bool, dir: bool) -> FileModules {
    let code = code_only(src);
    let toks = tokens(&code);
    let mut fm = FileModules::default();
    // First the declared file modules (they decide which bare paths are module paths).
    for w in toks.windows(3) {
        if w[0].text == "mod" && is_ident(&w[1].text) && w[2].text == ";" {
            fm.children.push(w[1].text.clone());
        }
    }
    // Braces: an inline module's (name, a test module) or another block's (None).
    let mut stack: Vec<Option<(String, bool)>> = Vec::new();
    let in_test = |stack: &[Option<(String, bool)>]| stack.iter().flatten().any(|m| m.1);
    let inline = |stack: &[Option<(String, bool)>]| stack.iter().flatten().map(|m| m.0.clone()).collect::<Vec<_>>();
    let mut i = 0;
    while i < toks.len() {
        let t = toks[i].text.as_str();
        match t {
            "{" => {
                // `mod name {`, with the attributes before it (`#[cfg(test)]`).
                let named = (i >= 2 && toks[i - 2].text == "mod" && is_ident(&toks[i - 1].text)).then(|| {
                    let mut k = i - 2;
                    let mut test = false;
                    while k > 0 {
                        let p = toks[k - 1].text.as_str();
                        if p == "pub" || p == "crate" || p == "super" || p == "(" || p == ")" || p == "in" {
                            k -= 1;
                        } else if p == "]" {
                            // An attribute: back to its `#[`.
                            let end = k - 1;
                            let mut depth = 0;
                            let mut j = end;
                            loop {
                                match toks[j].text.as_str() {
                                    "]" => depth += 1,
                                    "[" => depth -= 1,
                                    _ => {}
                                }
                                if depth == 0 || j == 0 {
                                    break;
                                }
                                j -= 1;
                            }
                            let attr: Vec<&str> = toks[j..=end].iter().map(|t| t.text.as_str()).collect();
                            test |= attr.windows(4).any(|a| a == ["cfg", "(", "test", ")"]);
                            k = j.saturating_sub(1);
                            if toks.get(k).is_none_or(|t| t.text != "#") {
                                break;
                            }
                        } else {
                            break;
                        }
                    }
                    (toks[i - 1].text.clone(), test)
                });
                stack.push(named);
                i += 1;
            }
            "}" => {
                stack.pop();
                i += 1;
            }
            _ if in_test(&stack) => i += 1,
            "use" => {
                let end = (i..toks.len()).find(|&k| toks[k].text == ";").unwrap_or(toks.len());
                let reexport = i > 0 && matches!(toks[i - 1].text.as_str(), "pub" | ")");
                for (segments, line) in use_tree(&toks[i + 1..end]) {
                    let contents = dir && reexport && fm.children.contains(&segments[0]);
                    if !contents && starts_module_path(&segments[0], &fm.children, root) {
                        fm.uses.push(PathUse { inline: inline(&stack), segments, line });
                    }
                }
                i = end;
            }
            _ if is_ident(t)
                && toks.get(i + 1).is_some_and(|n| n.text == "::")
                && !(i > 0 && toks[i - 1].text == "::")
                && starts_module_path(t, &fm.children, root) =>
            {
                let line = toks[i].line;
                let mut segments = vec![t.to_string()];
                let mut k = i + 1;
                while k + 1 < toks.len() && toks[k].text == "::" && is_ident(&toks[k + 1].text) {
                    segments.push(toks[k + 1].text.clone());
                    k += 2;
                }
                fm.uses.push(PathUse { inline: inline(&stack), segments, line });
                i = k;
            }
            _ => i += 1,
        }
    }
    fm
}

fn starts_module_path(first: &str, children: &[String], root: bool) -> bool {
    matches!(first, "crate" | "super" | "self") || (!root && children.iter().any(|c| c == first))
}

/// A crate's file-level graph: for each module file (relative to `src/`), the module files its
/// code uses, each with the first line that uses it.
#[derive(Debug, Default)]
pub struct Graph {
    pub edges: BTreeMap<String, BTreeMap<String, usize>>,
}

/// The module path of a file relative to `src/` (`lib.rs` and `main.rs`: the root).
fn module_of(rel: &str) -> Vec<String> {
    let mut parts: Vec<String> = rel.trim_end_matches(".rs").split('/').map(String::from).collect();
    if matches!(parts.last().map(String::as_str), Some("mod" | "lib" | "main")) {
        parts.pop();
    }
    parts
}

/// The file-level graph of the crate whose sources are in `src` (binaries under `src/bin`
/// are crates of their own and left out).
pub fn crate_graph(src: &Path) -> Graph {
    let files: Vec<(String, String)> = files_under(src, Some(".rs"))
        .into_iter()
        .map(|p| {
            let rel = p.strip_prefix(src).expect("under src").to_string_lossy().replace('\\', "/");
            let text = std::fs::read_to_string(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
            (rel, text)
        })
        .filter(|(rel, _)| !rel.starts_with("bin/"))
        .collect();
    graph_of(&files)
}

/// [`crate_graph`] of files given as `(path relative to src/, text)`.
pub fn graph_of(files: &[(String, String)]) -> Graph {
    let by_module: BTreeMap<Vec<String>, String> = files.iter().map(|(rel, _)| (module_of(rel), rel.clone())).collect();
    let mut g = Graph::default();
    for (rel, text) in files {
        let here = module_of(rel);
        let root = here.is_empty();
        let fm = file_modules_of(text, root, rel == "mod.rs" || rel.ends_with("/mod.rs"));
        let entry = g.edges.entry(rel.clone()).or_default();
        for u in fm.uses {
            let mut abs: Vec<String> = here.iter().chain(&u.inline).cloned().collect();
            let mut segs = u.segments.iter().peekable();
            match segs.peek().map(|s| s.as_str()) {
                Some("crate") => {
                    abs.clear();
                    segs.next();
                }
                Some("self") => {
                    segs.next();
                }
                Some("super") => {
                    while segs.peek().is_some_and(|s| *s == "super") {
                        segs.next();
                        if abs.pop().is_none() {
                            // Above the crate root: not a path of this crate.
                            abs.push("\0".into());
                        }
                    }
                }
                // A child module of this file (declared at its top level).
                _ => abs = here.clone(),
            }
            abs.extend(segs.cloned());
            // The longest prefix that is a module file.
            let target = (0..=abs.len()).rev().find_map(|n| by_module.get(&abs[..n]));
            if let Some(t) = target.filter(|t| *t != rel) {
                entry.entry(t.clone()).or_insert(u.line);
            }
        }
    }
    g
}

/// The circles of a graph: per strongly connected component of more than one file (Tarjan's
/// algorithm), its files (sorted) and one cycle through them (the shortest from its first
/// file, in order, that file repeated at the end).
pub fn circles(g: &BTreeMap<String, BTreeMap<String, usize>>) -> Vec<(Vec<String>, Vec<String>)> {
    let nodes: BTreeSet<&String> = g.keys().chain(g.values().flat_map(|m| m.keys())).collect();
    let nodes: Vec<&String> = nodes.into_iter().collect();
    let index_of: BTreeMap<&String, usize> = nodes.iter().enumerate().map(|(i, n)| (*n, i)).collect();
    let succ: Vec<Vec<usize>> =
        nodes.iter().map(|n| g.get(*n).map(|m| m.keys().map(|t| index_of[t]).collect()).unwrap_or_default()).collect();
    // Tarjan, iteratively.
    let n = nodes.len();
    let (mut index, mut low, mut on) = (vec![usize::MAX; n], vec![0; n], vec![false; n]);
    let (mut stack, mut sccs, mut next) = (Vec::new(), Vec::new(), 0);
    for s in 0..n {
        if index[s] != usize::MAX {
            continue;
        }
        let mut work = vec![(s, 0usize)];
        while let Some(&mut (v, ref mut k)) = work.last_mut() {
            if *k == 0 {
                index[v] = next;
                low[v] = next;
                next += 1;
                stack.push(v);
                on[v] = true;
            }
            if *k < succ[v].len() {
                let w = succ[v][*k];
                *k += 1;
                if index[w] == usize::MAX {
                    work.push((w, 0));
                } else if on[w] {
                    low[v] = low[v].min(index[w]);
                }
                continue;
            }
            work.pop();
            if let Some(&(u, _)) = work.last() {
                low[u] = low[u].min(low[v]);
            }
            if low[v] == index[v] {
                let mut comp = Vec::new();
                loop {
                    let w = stack.pop().expect("v is on the stack");
                    on[w] = false;
                    comp.push(w);
                    if w == v {
                        break;
                    }
                }
                if comp.len() > 1 {
                    sccs.push(comp);
                }
            }
        }
    }
    // One cycle through each component: a shortest path from its first file back to it.
    let mut out = Vec::new();
    for comp in sccs {
        let inside: BTreeSet<usize> = comp.iter().copied().collect();
        let start = *comp.iter().min_by_key(|&&v| nodes[v]).expect("not empty");
        let mut prev = vec![usize::MAX; n];
        let mut queue = std::collections::VecDeque::from([start]);
        let mut end = None;
        'bfs: while let Some(v) = queue.pop_front() {
            for &w in &succ[v] {
                if !inside.contains(&w) {
                    continue;
                }
                if w == start {
                    end = Some(v);
                    break 'bfs;
                }
                if prev[w] == usize::MAX {
                    prev[w] = v;
                    queue.push_back(w);
                }
            }
        }
        let mut chain = Vec::new();
        let mut v = end.expect("a component of several files has a cycle through each");
        while v != start {
            chain.push(v);
            v = prev[v];
        }
        chain.reverse();
        let path = std::iter::once(start).chain(chain).chain([start]);
        let mut members: Vec<String> = comp.iter().map(|&v| nodes[v].clone()).collect();
        members.sort();
        out.push((members, path.map(|v| nodes[v].clone()).collect()));
    }
    out
}

/// One cycle per circle of [`circles`].
pub fn cycles(g: &BTreeMap<String, BTreeMap<String, usize>>) -> Vec<Vec<String>> {
    circles(g).into_iter().map(|c| c.1).collect()
}

/// A cycle as `a.rs -> b.rs (line 12 of a.rs) -> a.rs (line 30 of b.rs)`.
pub fn describe(cycle: &[String], g: &BTreeMap<String, BTreeMap<String, usize>>) -> String {
    let mut s = cycle[0].clone();
    for w in cycle.windows(2) {
        let line = g.get(&w[0]).and_then(|m| m.get(&w[1])).copied().unwrap_or(0);
        s.push_str(&format!(" -> {} (line {line} of {})", w[1], w[0]));
    }
    s
}
