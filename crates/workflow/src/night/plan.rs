//! The plan of a night: units of work, each one `instpol` command with the files it reads and
//! writes and the units it must follow, and what was left out and why. A plan is a value
//! (serde) written as TOML or JSON (by extension) that a person or a pipeline may edit;
//! [`Plan::check`] refuses a plan that cannot run before anything is written.

use super::Error;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The plan format's version (a change an older reader would misread increments it).
pub const PLAN_VERSION: u32 = 1;

/// The commands a unit may run (`kind`, the command's name).
pub const KINDS: &[&str] = &[
    "master-bias",
    "master-flat",
    "reduce",
    "catalog",
    "calibrate",
    "zero-angle",
    "photometry",
    "fit-standards",
    "validate",
];

/// One unit of work.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Unit {
    /// Unique name (`reduce-20190304-NGC_1234-v_HIGH`).
    pub id: String,
    /// The command it runs, one of [`KINDS`]; the first word of `command`.
    pub kind: String,
    /// Every file the command reads (frames and masters): hashed to decide whether the unit is
    /// up to date.
    pub inputs: Vec<PathBuf>,
    /// Every file it writes.
    pub outputs: Vec<PathBuf>,
    /// The `instpol` command line without the program: its inputs, outputs and options.
    pub command: Vec<String>,
    /// Units that must finish first (the ones that write its inputs).
    #[serde(default)]
    pub after: Vec<String>,
    /// The command prints its result (`--json`) instead of writing a file: the printed text
    /// is the one output, written atomically by the runner.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub stdout: bool,
    /// The command checks something (a `validate`): its exit status 1 means that the check ran
    /// and did not pass, and its output is kept (`workflow::night::run`, "Checks").
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub check: bool,
    /// What the unit measures, for reading its output back over many nights
    /// (`workflow::night::trend`): the start of its set (MJD), its filter, and the standard
    /// star it measures.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mjd: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub filter: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub standard: Option<String>,
}

impl Unit {
    /// The arguments of its command (after the command's name) that are neither its listed
    /// inputs nor its outputs, as paths: the files it names besides (an instrument file, a
    /// calibration), for the callers to test which exist.
    fn named_besides(&self) -> impl Iterator<Item = &Path> + '_ {
        self.command
            .iter()
            .skip(1)
            .map(Path::new)
            .filter(|p| !self.outputs.iter().any(|o| o == p) && !self.inputs.iter().any(|i| i == p))
    }

    pub fn new(
        id: &str,
        kind: &str,
        inputs: Vec<PathBuf>,
        outputs: Vec<PathBuf>,
        command: Vec<String>,
        after: Vec<String>,
    ) -> Self {
        Unit {
            id: id.into(),
            kind: kind.into(),
            inputs,
            outputs,
            command,
            after,
            stdout: false,
            check: false,
            mjd: None,
            filter: None,
            standard: None,
        }
    }
}

/// A file left out of the plan, or a note on a set, with the reason.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LeftOut {
    /// The files concerned (none for a note on a set that was kept).
    pub files: Vec<PathBuf>,
    pub why: String,
}

/// What a usable file was found to be.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileRole {
    pub path: PathBuf,
    /// bias, flat, polarimetry or standard.
    pub role: String,
}

/// A night's plan (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Plan {
    pub version: u32,
    /// The instrument as the commands are given it (`--instrument`).
    pub instrument: String,
    /// The folder where the runner records each finished unit (its input and output hashes).
    pub records: PathBuf,
    pub units: Vec<Unit>,
    /// Every usable file and its role.
    #[serde(default)]
    pub files: Vec<FileRole>,
    #[serde(default)]
    pub left_out: Vec<LeftOut>,
    /// What the night's products are of (`skyfield::provenance::Product`): the instrument's
    /// name, the BLAKE3 of its definition, its plate and detector (each unit names its filter).
    /// `None` in plans written before plans recorded it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub product: Option<skyfield::provenance::Product>,
}

fn is_json(path: &Path) -> bool {
    path.extension().is_some_and(|e| e.eq_ignore_ascii_case("json"))
}

impl Plan {
    /// The plan as text: JSON for a `.json` path, TOML otherwise.
    pub fn to_text(&self, path: &Path) -> Result<String, Error> {
        if is_json(path) {
            serde_json::to_string_pretty(self)
                .map(|s| s + "\n")
                .map_err(|e| Error::Plan { path: path.into(), why: e.to_string() })
        } else {
            toml::to_string(self).map_err(|e| Error::Plan { path: path.into(), why: e.to_string() })
        }
    }

    /// Write the plan atomically (TOML, or JSON for a `.json` path).
    pub fn write(&self, path: &Path) -> Result<(), Error> {
        let text = self.to_text(path)?;
        super::write_atomic(path, text.as_bytes())
    }

    /// Read and check a plan file (TOML, or JSON for a `.json` path).
    pub fn load(path: &Path) -> Result<Plan, Error> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::Input { path: path.into(), why: e.to_string() })?;
        let plan: Plan = if is_json(path) {
            serde_json::from_str(&text).map_err(|e| Error::Plan { path: path.into(), why: e.to_string() })?
        } else {
            toml::from_str(&text).map_err(|e| Error::Plan { path: path.into(), why: e.to_string() })?
        };
        plan.check().map_err(|e| match e {
            Error::Unit { id, why } => Error::Plan { path: path.into(), why: format!("unit {id}: {why}") },
            other => other,
        })?;
        Ok(plan)
    }

    /// The unit named `id`.
    pub fn unit(&self, id: &str) -> Result<&Unit, Error> {
        self.units.iter().find(|u| u.id == id).ok_or_else(|| Error::Unit {
            id: id.into(),
            why: format!(
                "no such unit in the plan ({} units: {})",
                self.units.len(),
                self.units.iter().map(|u| u.id.as_str()).take(8).collect::<Vec<_>>().join(", ")
                    + if self.units.len() > 8 { ", ..." } else { "" }
            ),
        })
    }

    /// Refuse a plan that cannot run, naming the unit and file: an unknown version or kind, a
    /// command that is not its kind's, two units of one name, a dependency on no unit, a
    /// cycle, an input that neither exists nor is made by a unit it follows, an output that is
    /// an existing input of the plan (a raw frame) or made by two units.
    pub fn check(&self) -> Result<(), Error> {
        let bad = |id: &str, why: String| Err(Error::Unit { id: id.into(), why });
        if self.version != PLAN_VERSION {
            return bad("(plan)", format!("version {} (this instpol reads version {PLAN_VERSION})", self.version));
        }
        let mut ids = BTreeSet::new();
        for u in &self.units {
            if u.id.trim().is_empty() || u.id.contains(['/', '\\']) {
                return bad(&u.id, "a unit's id must be a non-empty name without '/'".into());
            }
            if !ids.insert(u.id.as_str()) {
                return bad(&u.id, "two units have this id".into());
            }
            if !KINDS.contains(&u.kind.as_str()) {
                return bad(&u.id, format!("unknown kind '{}' (known: {})", u.kind, KINDS.join(", ")));
            }
            if u.command.first() != Some(&u.kind) {
                return bad(&u.id, format!("its command must start with its kind '{}'", u.kind));
            }
            if u.outputs.is_empty() {
                return bad(&u.id, "no output".into());
            }
            if u.stdout && u.outputs.len() != 1 {
                return bad(&u.id, "a unit whose output is what it prints has exactly one output".into());
            }
        }
        let mut maker: BTreeMap<&Path, &str> = BTreeMap::new();
        for u in &self.units {
            for o in &u.outputs {
                if let Some(other) = maker.insert(o.as_path(), u.id.as_str()) {
                    return bad(&u.id, format!("output {} is also unit {other}'s", o.display()));
                }
            }
        }
        let by_id: BTreeMap<&str, &Unit> = self.units.iter().map(|x| (x.id.as_str(), x)).collect();
        for u in &self.units {
            for d in &u.after {
                if !ids.contains(d.as_str()) {
                    return bad(&u.id, format!("it follows unit '{d}', which the plan does not have"));
                }
            }
            // Its inputs, and the files its command names besides (an instrument file, a
            // calibration): either way the command reads them.
            let named = u.named_besides().filter(|p| p.is_file() || maker.contains_key(p));
            for i in u.inputs.iter().map(PathBuf::as_path).chain(named) {
                match maker.get(i) {
                    Some(m) if *m == u.id => {
                        return bad(&u.id, format!("output {} is also its input: refusing to write over an input", i.display()))
                    }
                    Some(m) if !Self::follows(&by_id, u, m) => {
                        return bad(&u.id, format!("input {} is written by unit {m}, which it does not follow (after): refusing to write over an input of a unit that may run first", i.display()))
                    }
                    Some(_) => {}
                    None if !i.is_file() => {
                        return bad(&u.id, format!("input {} does not exist and no unit makes it", i.display()))
                    }
                    None => {}
                }
            }
        }
        // An output over a raw file of the night.
        let raw: BTreeSet<&Path> = self.files.iter().map(|f| f.path.as_path()).collect();
        for u in &self.units {
            for o in &u.outputs {
                if raw.contains(o.as_path()) {
                    return bad(
                        &u.id,
                        format!("output {} is a raw file of the night: refusing to write over an input", o.display()),
                    );
                }
            }
        }
        self.check_outputs_against_sources(&maker)?;
        self.order().map(|_| ())
    }

    /// Every file the plan reads that no unit makes (the units' inputs, the night's raw files,
    /// the instrument file, every existing file a command names): an output that is one of
    /// them under another name (spelled otherwise, through a symlink, a hard link) is refused,
    /// naming both names.
    fn check_outputs_against_sources(&self, maker: &BTreeMap<&Path, &str>) -> Result<(), Error> {
        let mut sources: Vec<&Path> = self.files.iter().map(|f| f.path.as_path()).collect();
        sources.push(Path::new(&self.instrument));
        for u in &self.units {
            sources.extend(u.inputs.iter().map(PathBuf::as_path).chain(u.named_besides()));
        }
        let sources: Vec<(&Path, FileId)> =
            sources.into_iter().filter(|p| !maker.contains_key(p) && p.is_file()).map(|p| (p, FileId::of(p))).collect();
        for u in &self.units {
            for o in &u.outputs {
                let id = FileId::of(o);
                if let Some((src, _)) = sources.iter().find(|(_, s)| s.same(&id)) {
                    return Err(Error::Unit {
                        id: u.id.clone(),
                        why: format!(
                            "output {} is {} under another name: refusing to write over an input",
                            o.display(),
                            src.display()
                        ),
                    });
                }
            }
        }
        Ok(())
    }

    /// The plan of instrument `inst` (given to the commands as `instrument`; what its products
    /// are of recorded) writing into the folder `products`, checked ([`Plan::check`]).
    pub(crate) fn checked(
        (instrument, inst): (&str, &instrument::Instrument),
        products: &Path,
        units: Vec<Unit>,
        files: Vec<FileRole>,
        left_out: Vec<LeftOut>,
    ) -> Result<Plan, Error> {
        let plan = Plan {
            version: PLAN_VERSION,
            instrument: instrument.to_string(),
            records: products.join(".instpol-run"),
            units,
            files,
            left_out,
            product: Some(skyfield::provenance::Product::of_instrument_alone(inst)),
        };
        plan.check()?;
        Ok(plan)
    }

    /// True when `u` follows unit `id`, directly or through others.
    fn follows(by_id: &BTreeMap<&str, &Unit>, u: &Unit, id: &str) -> bool {
        let mut stack: Vec<&str> = u.after.iter().map(|s| s.as_str()).collect();
        let mut seen = BTreeSet::new();
        while let Some(d) = stack.pop() {
            if d == id {
                return true;
            }
            if seen.insert(d) {
                if let Some(x) = by_id.get(d) {
                    stack.extend(x.after.iter().map(|s| s.as_str()));
                }
            }
        }
        false
    }

    /// The units' indices in an order where each follows its dependencies (stable: plan order
    /// among the ready ones); a cycle is an error naming its units.
    pub fn order(&self) -> Result<Vec<usize>, Error> {
        let idx: BTreeMap<&str, usize> = self.units.iter().enumerate().map(|(i, u)| (u.id.as_str(), i)).collect();
        let mut done = vec![false; self.units.len()];
        let mut out = Vec::with_capacity(self.units.len());
        while out.len() < self.units.len() {
            let before = out.len();
            for (i, u) in self.units.iter().enumerate() {
                if !done[i] && u.after.iter().all(|d| idx.get(d.as_str()).is_some_and(|&j| done[j])) {
                    done[i] = true;
                    out.push(i);
                }
            }
            if out.len() == before {
                let stuck: Vec<&str> =
                    self.units.iter().enumerate().filter(|(i, _)| !done[*i]).map(|(_, u)| u.id.as_str()).collect();
                return Err(Error::Unit {
                    id: stuck[0].into(),
                    why: format!("a cycle of dependencies among units {}", stuck.join(", ")),
                });
            }
        }
        Ok(out)
    }

    /// The indices of unit `id` and of every unit it follows, dependencies first.
    pub fn with_dependencies(&self, id: &str) -> Result<Vec<usize>, Error> {
        let u = self.unit(id)?;
        let order = self.order()?;
        let by_id: BTreeMap<&str, &Unit> = self.units.iter().map(|x| (x.id.as_str(), x)).collect();
        Ok(order
            .into_iter()
            .filter(|&i| self.units[i].id == u.id || Self::follows(&by_id, u, &self.units[i].id))
            .collect())
    }
}

/// Which file a path names, for telling two names of one file apart: its device and inode
/// when it exists, and its absolute path with `.`, `..` and symlinked folders resolved.
#[derive(Debug, Clone, PartialEq)]
struct FileId {
    inode: Option<(u64, u64)>,
    path: PathBuf,
}

impl FileId {
    fn of(p: &Path) -> FileId {
        #[cfg(unix)]
        let inode = {
            use std::os::unix::fs::MetadataExt;
            std::fs::metadata(p).ok().map(|m| (m.dev(), m.ino()))
        };
        #[cfg(not(unix))]
        let inode = None;
        let path = std::fs::canonicalize(p).unwrap_or_else(|_| {
            // Not there yet: its folder resolved, then its name.
            let dir = p.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
            match (std::fs::canonicalize(dir), p.file_name()) {
                (Ok(d), Some(n)) => d.join(n),
                _ => std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf()),
            }
        });
        FileId { inode, path }
    }

    /// Whether the two name one file.
    fn same(&self, other: &FileId) -> bool {
        matches!((self.inode, other.inode), (Some(a), Some(b)) if a == b) || self.path == other.path
    }
}
