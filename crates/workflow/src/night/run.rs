//! Running a plan: units in dependency order, each skipped when it is up to date, a failing
//! unit reported without stopping the others, any number at once.
//!
//! Design. A unit is the command line of an existing `instpol` command, and the runner hands
//! it to an *executor* given as a parameter; the CLI's and Python's executor
//! (`super::call::library_executor`) reads the command back into the library call the command
//! makes (`crate::steps`) and makes it in process, or runs the `instpol` binary
//! ([`process_executor`]) for a command it does not know whole, so a unit's outputs are those
//! of the command run by hand, apart from the provenance's date and command line (no second
//! way of making a map or a catalog to keep in step). What is this module's own is the
//! scheduling:
//!
//! - **Up to date**: after a unit succeeds, a record (`<records>/<id>.json`) keeps its command
//!   and the BLAKE3 hashes (`skyfield::provenance::hash_file`, the provenance's hash) of its
//!   inputs and outputs, with each file's size and modification time. Its inputs are the
//!   plan's for the unit and every other file the command says it read: the files its own
//!   arguments name as inputs by their roles in the command's definition (an instrument file,
//!   a master, a calibration, a table), reported with the hashes ([`INPUT_HASHES_ENV`]). A
//!   unit is up to date, and skipped, when its record exists, names the same command and
//!   inputs with the same hashes, and every output exists with its recorded hash. An edited
//!   option, a changed frame, an edited instrument file or a damaged product runs it again. A file whose size and modification time (to the
//!   nanosecond) are those recorded is taken to have its recorded hash, as make and rsync
//!   take it, so that checking a plan's finished units does not read every frame again.
//! - **Hashes read once**: an input's hash is the one the command itself computed for its
//!   provenance while reading it (the executor asks the `instpol` binary for them through
//!   [`INPUT_HASHES_ENV`]; a unit made in process hands over its provenance's), so a unit reads its frames once, not twice (`bench/run_plan.sh`:
//!   hashing them again made a reduction of 16 full frames 40 % slower); an input the command
//!   did not report is hashed by the runner.
//! - **Atomic**: every command writes its outputs through a temporary file and a rename; the
//!   runner writes a printed output and the record the same way, the record last. A run killed
//!   at any point leaves each unit either recorded (finished: skipped next time) or not (run
//!   again, its outputs replaced whole). The temporaries of a unit's command and of the
//!   runner's writes for it carry the unit's id (`skyfield::fits::TEMP_TAG_ENV`); those a
//!   killed run left are removed by the unit's next run, under its lock.
//! - **Locks**: a unit runs holding an exclusive lock on `<records>/<id>.lock`, so workers of a
//!   Slurm array or GNU parallel that reach the same dependency run it once: the second waits,
//!   then finds it up to date.
//! - **Failures**: a failing unit is reported with its command's last lines of error; the
//!   units that follow it are reported blocked; the others run.
//! - **Checks**: a unit marked `check` (a `validate`) runs a command whose exit status 1 means
//!   that its check ran and did not pass (the CLI's convention). Its output is kept and
//!   recorded like any other, the units that follow it run, and it is reported as
//!   [`Status::CheckFailed`], again on every later run that skips it.

use super::plan::{Plan, Unit};
use super::{write_atomic_tagged, Error};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::{Condvar, Mutex};

/// The environment variable naming the file where an `instpol` command writes, when it
/// succeeds (or its check ran), the inputs of its provenance with the hashes it computed
/// while reading them: a JSON array of `{path, hash}` (`skyfield::provenance::InputFile`).
pub const INPUT_HASHES_ENV: &str = "INSTPOL_INPUT_HASHES";

/// What a finished unit read and wrote (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Record {
    pub command: Vec<String>,
    /// `(path, blake3:<hex>)` of each input.
    pub inputs: Vec<(PathBuf, String)>,
    /// `(path, blake3:<hex>)` of each output.
    pub outputs: Vec<(PathBuf, String)>,
    /// `(path, size in bytes, modification time in ns since the epoch)` of every input and
    /// output when recorded (module docs, "Up to date").
    #[serde(default)]
    pub stats: Vec<(PathBuf, u64, i128)>,
    /// A check unit whose check did not pass: why (module docs, "Checks").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub check_failed: Option<String>,
    /// What the unit's products are of: the plan's product ([`Plan::product`]) in the unit's
    /// filter. Absent in records written before records said it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub product: Option<skyfield::provenance::Product>,
}

/// What happened to a unit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "status", content = "reason")]
pub enum Status {
    /// Ran and succeeded.
    Done,
    /// Skipped: its record matches its inputs and outputs.
    UpToDate,
    /// Dry run: would run.
    WouldRun,
    /// Ran and failed, with the reason.
    Failed(String),
    /// A check unit that ran (or was recorded) and whose check did not pass: its output is
    /// written; the reason is the command's message.
    CheckFailed(String),
    /// Not run: a unit it follows failed or was blocked.
    Blocked(String),
}

/// One unit's outcome.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Outcome {
    pub id: String,
    pub kind: String,
    #[serde(flatten)]
    pub status: Status,
    pub seconds: f64,
}

/// What a run did, unit by unit in the order they finished.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Report {
    pub outcomes: Vec<Outcome>,
}

impl Report {
    /// True when no unit failed or was blocked (a check that did not pass is a result, not a
    /// failure: [`Report::counts`] counts them).
    pub fn ok(&self) -> bool {
        self.outcomes.iter().all(|o| !matches!(o.status, Status::Failed(_) | Status::Blocked(_)))
    }
    /// How many units ended with each status: done, up to date, would run, failed, blocked,
    /// check failed.
    pub fn counts(&self) -> [usize; 6] {
        let mut c = [0; 6];
        for o in &self.outcomes {
            c[match o.status {
                Status::Done => 0,
                Status::UpToDate => 1,
                Status::WouldRun => 2,
                Status::Failed(_) => 3,
                Status::Blocked(_) => 4,
                Status::CheckFailed(_) => 5,
            }] += 1;
        }
        c
    }
}

/// Which units to run.
#[derive(Debug, Clone, Default)]
pub struct RunOptions {
    /// Units run at once (at least 1).
    pub jobs: usize,
    /// Only these units (by id) and the units they follow; `None`: every unit.
    pub only: Option<Vec<String>>,
    /// Say what would run, run nothing, write nothing.
    pub dry_run: bool,
}

/// What a unit's command did when it ran to its end.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Executed {
    /// What it printed on standard output.
    pub stdout: Vec<u8>,
    /// A check unit whose check did not pass: the command's message (module docs, "Checks").
    pub check_failed: Option<String>,
    /// `(path, blake3:<hex>)` of the inputs it hashed while reading them, when it says.
    pub input_hashes: Vec<(PathBuf, String)>,
}

/// Runs one unit's command: what it did, or the reason it failed.
pub type Executor<'a> = dyn Fn(&Unit) -> Result<Executed, String> + Sync + 'a;

/// The executor that runs `program` (the `instpol` binary) with the unit's command, its
/// standard input closed; a failure's reason is the last lines of what it printed on standard
/// error (and its exit status). Exit status 1 of a check unit is its check not passing.
/// The command reports the hashes of its inputs (module docs, "Hashes read once") in a file
/// beside its record, read and removed after it ends.
pub fn process_executor(program: PathBuf, records: PathBuf) -> impl Fn(&Unit) -> Result<Executed, String> + Sync {
    move |u: &Unit| {
        let report = records.join(format!(".{}.hashes-{}.json", u.id, std::process::id()));
        let out = std::process::Command::new(&program)
            .args(&u.command)
            .env(INPUT_HASHES_ENV, &report)
            .env(skyfield::fits::TEMP_TAG_ENV, &u.id)
            .stdin(std::process::Stdio::null())
            .output()
            .map_err(|e| format!("cannot start {}: {e}", program.display()))?;
        let input_hashes = read_hash_report(&report);
        let _ = std::fs::remove_file(&report);
        let err = String::from_utf8_lossy(&out.stderr);
        let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
        let tail = lines[lines.len().saturating_sub(3)..].join(" | ");
        let tail = if tail.is_empty() { "no message".to_string() } else { tail };
        if out.status.success() {
            return Ok(Executed { stdout: out.stdout, check_failed: None, input_hashes });
        }
        if u.check && out.status.code() == Some(1) {
            return Ok(Executed { stdout: out.stdout, check_failed: Some(tail), input_hashes });
        }
        Err(format!("{tail} ({})", out.status))
    }
}

impl Status {
    /// The status of a unit that has just run: done, unless its check did not pass.
    fn done(self) -> Status {
        match self {
            Status::UpToDate => Status::Done,
            s => s,
        }
    }
}

/// The `(path, hash)` pairs of a command's report ([`INPUT_HASHES_ENV`]); none when it wrote
/// none or something else.
fn read_hash_report(path: &Path) -> Vec<(PathBuf, String)> {
    let Ok(text) = std::fs::read_to_string(path) else { return vec![] };
    let Ok(list) = serde_json::from_str::<Vec<skyfield::provenance::InputFile>>(&text) else { return vec![] };
    list.into_iter().map(|i| (PathBuf::from(i.path), i.hash)).collect()
}

/// A file's size and modification time (ns since the epoch).
fn stat(path: &Path) -> Option<(u64, i128)> {
    let m = std::fs::metadata(path).ok()?;
    let t = m.modified().ok()?.duration_since(std::time::UNIX_EPOCH).ok()?.as_nanos() as i128;
    Some((m.len(), t))
}

/// The hash of each of `paths`: `known`'s when it names the file, else the file's own
/// (`None` when one cannot be read).
fn hashes_with(paths: &[PathBuf], known: &dyn Fn(&Path) -> Option<String>) -> Option<Vec<(PathBuf, String)>> {
    paths.iter().map(|p| known(p).or_else(|| skyfield::provenance::hash_file(p).ok()).map(|h| (p.clone(), h))).collect()
}

/// The hashes of `paths` now, taking a record's hash for a file whose size and modification
/// time it recorded unchanged (module docs, "Up to date").
fn hashes(paths: &[PathBuf], rec: Option<&Record>) -> Option<Vec<(PathBuf, String)>> {
    hashes_with(paths, &|p: &Path| {
        let r = rec?;
        let (size, t) = r.stats.iter().find(|(q, _, _)| q == p).map(|(_, s, t)| (*s, *t))?;
        (stat(p)? == (size, t)).then_some(())?;
        r.inputs.iter().chain(&r.outputs).find(|(q, _)| q == p).map(|(_, h)| h.clone())
    })
}

/// Remove what a killed run of unit `u` left: its command's temporaries and the runner's
/// (tagged with its id) beside its outputs and its record, and its command's hash report.
/// Called under the unit's lock, when no other run of it can be writing them.
fn remove_leftovers(plan: &Plan, u: &Unit) {
    let prefix = skyfield::fits::temp_prefix(Some(&u.id));
    let report = format!(".{}.hashes-", u.id);
    let mut dirs: Vec<PathBuf> = u
        .outputs
        .iter()
        .map(|o| o.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new(".")).to_path_buf())
        .collect();
    dirs.push(plan.records.clone());
    dirs.sort();
    dirs.dedup();
    for d in dirs {
        let Ok(rd) = std::fs::read_dir(&d) else { continue };
        for e in rd.flatten() {
            let name = e.file_name().to_string_lossy().to_string();
            if name.starts_with(&prefix) || (d == plan.records && name.starts_with(&report)) {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
}

/// Every input of unit `u` a record keeps: the plan's, in order, then the other files its
/// command reported reading (module docs, "Up to date"), by path.
fn all_inputs(u: &Unit, reported: &[(PathBuf, String)]) -> Vec<PathBuf> {
    let mut extra: Vec<PathBuf> =
        reported.iter().map(|(p, _)| p.clone()).filter(|p| !u.inputs.contains(p) && p.is_file()).collect();
    extra.sort();
    extra.dedup();
    u.inputs.iter().cloned().chain(extra).collect()
}

fn record_path(plan: &Plan, u: &Unit) -> PathBuf {
    plan.records.join(format!("{}.json", u.id))
}

/// Unit `u`'s record when it matches its command, its inputs' hashes now and its outputs
/// (module docs): the unit is up to date.
pub fn up_to_date(plan: &Plan, u: &Unit) -> Option<Record> {
    let text = std::fs::read_to_string(record_path(plan, u)).ok()?;
    let r = serde_json::from_str::<Record>(&text).ok()?;
    let recorded: Vec<PathBuf> = r.inputs.iter().map(|(p, _)| p.clone()).collect();
    let same = r.command == u.command
        && r.outputs.iter().map(|(p, _)| p).eq(u.outputs.iter())
        && recorded.starts_with(&u.inputs)
        && hashes(&recorded, Some(&r)).is_some_and(|h| h == r.inputs)
        && hashes(&u.outputs, Some(&r)).is_some_and(|h| h == r.outputs);
    same.then_some(r)
}

/// The status of a unit found up to date: its recorded check's, else up to date.
fn recorded_status(r: Record) -> Status {
    match r.check_failed {
        Some(why) => Status::CheckFailed(why),
        None => Status::UpToDate,
    }
}

/// Run one unit under its lock: skip it when up to date, else execute it and record it.
fn run_unit(plan: &Plan, u: &Unit, exec: &Executor) -> Status {
    if let Err(e) = std::fs::create_dir_all(&plan.records) {
        return Status::Failed(format!("cannot make the records folder {}: {e}", plan.records.display()));
    }
    let lock_path = plan.records.join(format!("{}.lock", u.id));
    let lock = match std::fs::OpenOptions::new().create(true).truncate(false).write(true).open(&lock_path) {
        Ok(f) => f,
        Err(e) => return Status::Failed(format!("cannot open the lock {}: {e}", lock_path.display())),
    };
    if let Err(e) = lock.lock() {
        return Status::Failed(format!("cannot lock {}: {e}", lock_path.display()));
    }
    remove_leftovers(plan, u);
    if let Some(r) = up_to_date(plan, u) {
        return recorded_status(r);
    }
    if let Some(missing) = u.inputs.iter().find(|p| !p.is_file()) {
        return Status::Failed(format!("input {} is missing or unreadable", missing.display()));
    }
    // Each input's size and time before the run: a file changed while the command ran is
    // recorded as changed, and the next run sees it.
    let before: Vec<Option<(u64, i128)>> = u.inputs.iter().map(|p| stat(p)).collect();
    for o in &u.outputs {
        if let Some(d) = o.parent().filter(|d| !d.as_os_str().is_empty()) {
            if let Err(e) = std::fs::create_dir_all(d) {
                return Status::Failed(format!("cannot make folder {}: {e}", d.display()));
            }
        }
    }
    let ran = match exec(u) {
        Ok(r) => r,
        Err(why) => return Status::Failed(why),
    };
    if u.stdout {
        if let Err(e) = write_atomic_tagged(&u.outputs[0], Some(&u.id), &ran.stdout) {
            return Status::Failed(e.to_string());
        }
    }
    let reported = |p: &Path| ran.input_hashes.iter().find(|(q, _)| q == p).map(|(_, h)| h.clone());
    let read = all_inputs(u, &ran.input_hashes);
    let Some(inputs) = hashes_with(&read, &reported) else {
        let missing =
            u.inputs.iter().find(|p| !p.is_file()).map_or_else(|| "an input".into(), |p| p.display().to_string());
        return Status::Failed(format!("input {missing} is missing or unreadable"));
    };
    let Some(outputs) = hashes(&u.outputs, None) else {
        let missing =
            u.outputs.iter().find(|p| !p.is_file()).map_or_else(|| "an output".into(), |p| p.display().to_string());
        return Status::Failed(format!("the command succeeded but did not write {missing}"));
    };
    // An input whose size or time moved during the run keeps no stat: it is hashed next time.
    // (The other files the command read were not known before it ran: theirs is taken now.)
    let stats = u
        .inputs
        .iter()
        .zip(&before)
        .filter_map(|(p, b)| stat(p).filter(|s| Some(*s) == *b).map(|(n, t)| (p.clone(), n, t)))
        .chain(read[u.inputs.len()..].iter().chain(&u.outputs).filter_map(|p| stat(p).map(|(n, t)| (p.clone(), n, t))))
        .collect();
    let product = plan
        .product
        .clone()
        .map(|p| skyfield::provenance::Product { filter: u.filter.clone().or(p.filter.clone()), ..p });
    let rec = Record { command: u.command.clone(), inputs, outputs, stats, check_failed: ran.check_failed, product };
    let text = serde_json::to_string_pretty(&rec).unwrap_or_default();
    match write_atomic_tagged(&record_path(plan, u), Some(&u.id), text.as_bytes()) {
        Ok(()) => recorded_status(rec).done(),
        Err(e) => Status::Failed(e.to_string()),
    }
}

/// The units (indices in the plan) selected by `only` (with everything they follow; `None`:
/// every unit), in dependency order: what [`run`] runs.
pub fn selection(plan: &Plan, only: &Option<Vec<String>>) -> Result<Vec<usize>, Error> {
    let order = plan.order()?;
    let Some(ids) = only else { return Ok(order) };
    let mut keep = vec![false; plan.units.len()];
    for id in ids {
        for i in plan.with_dependencies(id)? {
            keep[i] = true;
        }
    }
    Ok(order.into_iter().filter(|&i| keep[i]).collect())
}

struct State {
    /// Per unit of the selection: `None` pending, `Some(true)` running or finished well,
    /// `Some(false)` failed or blocked.
    started: Vec<bool>,
    finished: Vec<Option<bool>>,
    report: Report,
}

/// Run `plan` (module docs): the one library call of `instpol run` and `instpol.run`.
/// `on_outcome` is told of every unit as it ends (a progress bar).
pub fn run(
    plan: &Plan,
    opts: &RunOptions,
    exec: &Executor,
    on_outcome: &(dyn Fn(&Outcome) + Sync),
) -> Result<Report, Error> {
    plan.check()?;
    let sel = selection(plan, &opts.only)?;
    if opts.dry_run {
        let mut report = Report::default();
        for &i in &sel {
            let u = &plan.units[i];
            let status = up_to_date(plan, u).map_or(Status::WouldRun, recorded_status);
            let o = Outcome { id: u.id.clone(), kind: u.kind.clone(), status, seconds: 0.0 };
            on_outcome(&o);
            report.outcomes.push(o);
        }
        return Ok(report);
    }
    let n = sel.len();
    let pos_of = |id: &str| sel.iter().position(|&i| plan.units[i].id == id);
    let deps: Vec<Vec<usize>> =
        sel.iter().map(|&i| plan.units[i].after.iter().filter_map(|d| pos_of(d)).collect()).collect();
    let state = Mutex::new(State { started: vec![false; n], finished: vec![None; n], report: Report::default() });
    let cv = Condvar::new();
    let jobs = opts.jobs.max(1).min(n.max(1));
    std::thread::scope(|scope| {
        for _ in 0..jobs {
            scope.spawn(|| loop {
                let mut st = state.lock().unwrap_or_else(|e| e.into_inner());
                let k = loop {
                    // Units whose dependency failed are blocked without running.
                    let mut changed = false;
                    for k in 0..n {
                        if st.started[k] {
                            continue;
                        }
                        if let Some(&d) = deps[k].iter().find(|&&d| st.finished[d] == Some(false)) {
                            st.started[k] = true;
                            st.finished[k] = Some(false);
                            let u = &plan.units[sel[k]];
                            let o = Outcome {
                                id: u.id.clone(),
                                kind: u.kind.clone(),
                                status: Status::Blocked(format!("unit {} did not succeed", plan.units[sel[d]].id)),
                                seconds: 0.0,
                            };
                            on_outcome(&o);
                            st.report.outcomes.push(o);
                            changed = true;
                        }
                    }
                    if changed {
                        cv.notify_all();
                    }
                    if let Some(k) =
                        (0..n).find(|&k| !st.started[k] && deps[k].iter().all(|&d| st.finished[d] == Some(true)))
                    {
                        st.started[k] = true;
                        break Some(k);
                    }
                    if st.started.iter().all(|&s| s) {
                        break None;
                    }
                    st = cv.wait(st).unwrap_or_else(|e| e.into_inner());
                };
                drop(st);
                let Some(k) = k else {
                    cv.notify_all();
                    return;
                };
                let u = &plan.units[sel[k]];
                let t0 = std::time::Instant::now();
                let status = run_unit(plan, u, exec);
                let ok = matches!(status, Status::Done | Status::UpToDate | Status::CheckFailed(_));
                let o = Outcome { id: u.id.clone(), kind: u.kind.clone(), status, seconds: t0.elapsed().as_secs_f64() };
                on_outcome(&o);
                let mut st = state.lock().unwrap_or_else(|e| e.into_inner());
                st.finished[k] = Some(ok);
                st.report.outcomes.push(o);
                drop(st);
                cv.notify_all();
            });
        }
    });
    Ok(state.into_inner().unwrap_or_else(|e| e.into_inner()).report)
}
