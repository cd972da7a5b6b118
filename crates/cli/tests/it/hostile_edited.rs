//! The generator's `edited input` property: every command a night's unit may run
//! (`workflow::night::plan::KINDS`), in its valid invocation (`common::invocations::templates`,
//! read from the CLI's definition like every class of `hostile.rs`), is run once by
//! `instpol run` as a one-unit plan that lists only its frames (the positional files) as
//! inputs; then each other file its command line names (an instrument file, masters, a
//! calibration, a table) and its first frame are edited in turn (bytes appended), and the next
//! run must not call the unit up to date: it runs it again, or it fails. The run records hash
//! every file a command reads by its role in the command's own arguments, not only the files
//! a plan lists; a unit left "up to date" over an edited instrument file gave last week's
//! numbers with exit 0.
//!
//! Checked by mutation once (a scratch change, then dropped): the runner's record made of the
//! plan's listed inputs alone (`all_inputs` returning `u.inputs`) fails this property for the
//! instrument file of every command here, e.g. "reduce: mini.toml edited -> up_to_date".

use crate::common;

use common::invocations::{self, fill};
use serde_json::Value;
use std::path::{Path, PathBuf};
use workflow::night::plan::{Plan, Unit, KINDS, PLAN_VERSION};

/// The unit's status after `instpol run plan --json`.
fn status(plan: &Path) -> String {
    let (_, out, err) = common::run(&["run".to_string(), plan.display().to_string(), "--json".into()]);
    let v: Value = serde_json::from_str(&out).unwrap_or_else(|e| panic!("run --json: {e}: {out} {err}"));
    v["outcomes"][0]["status"].as_str().unwrap_or_default().to_string()
}

#[test]
fn every_unit_reruns_when_a_file_its_command_names_is_edited() {
    let f = invocations::fixture();
    let root = tempfile::tempdir().unwrap();
    let mut failures = Vec::new();
    let mut counts: Vec<(String, usize)> = Vec::new();
    for (n, t) in invocations::templates(&f).into_iter().enumerate() {
        if !KINDS.contains(&t.name()) || t.args.iter().any(|a| a.contains("{DIR}")) {
            continue;
        }
        let dir = root.path().join(format!("u{n}"));
        std::fs::create_dir_all(&dir).unwrap();
        let args = fill(&t.args, &dir, t.out_name);
        // The positional files (frames, tables) are the plan's inputs; files after a flag are not.
        let positional: Vec<PathBuf> = args
            .iter()
            .enumerate()
            .skip(1)
            .filter(|(i, a)| !args[i - 1].starts_with("--") && Path::new(a.as_str()).is_file())
            .map(|(_, a)| PathBuf::from(a))
            .collect();
        let named: Vec<PathBuf> =
            args.iter().skip(1).map(PathBuf::from).filter(|p| p.is_file() && !positional.contains(p)).collect();
        let stdout = t.out_name.is_none();
        let output = dir.join(t.out_name.map_or_else(|| "printed.json".to_string(), str::to_string));
        let mut unit = Unit::new("u", t.name(), positional.clone(), vec![output], args.clone(), vec![]);
        unit.stdout = stdout;
        unit.check = t.name() == "validate";
        let plan = Plan {
            version: PLAN_VERSION,
            instrument: "mini".into(),
            records: dir.join(".records"),
            units: vec![unit],
            files: vec![],
            left_out: vec![],
            product: None,
        };
        let plan_path = dir.join("plan.toml");
        std::fs::write(&plan_path, plan.to_text(&plan_path).unwrap()).unwrap();
        let first = status(&plan_path);
        if !matches!(first.as_str(), "done" | "check_failed") {
            failures.push(format!("{}: the valid unit did not run: {first}", t.command));
            continue;
        }
        if status(&plan_path) != "up_to_date" {
            failures.push(format!("{}: not up to date when nothing changed", t.command));
            continue;
        }
        // Each file the command line names besides the frames, and the first frame.
        let edited: Vec<PathBuf> = named.iter().chain(positional.first()).cloned().collect();
        for p in &edited {
            let before = std::fs::read(p).unwrap();
            let mut after = before.clone();
            after.extend_from_slice(b"\n");
            std::fs::write(p, &after).unwrap();
            let s = status(&plan_path);
            if s == "up_to_date" {
                failures.push(format!("{}: {} edited -> up_to_date", t.command, p.display()));
            }
            std::fs::write(p, &before).unwrap();
            // Back to as it was: the unit runs again or is up to date, never a failure.
            let back = status(&plan_path);
            if !matches!(back.as_str(), "done" | "check_failed" | "up_to_date") {
                failures.push(format!("{}: {} restored -> {back}", t.command, p.display()));
            }
        }
        counts.push((t.command.to_string(), edited.len()));
    }
    eprintln!("edited input: cases per command {counts:?}");
    let covered: Vec<&str> = counts.iter().map(|(c, _)| c.split(' ').next().unwrap_or_default()).collect();
    for k in KINDS {
        assert!(covered.contains(k), "no invocation of {k} was tried (templates: common::invocations)");
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
