//! `instpol scan` and `instpol run`: a night of raw files sorted into a plan, and the plan
//! run (`workflow::night`).

use anyhow::{bail, Context, Result};
use std::path::PathBuf;
use workflow::night;

/// Sort a folder of raw files by their headers alone (the instrument file's [headers] table
/// says which keywords and values mean bias, flat, polarimetric exposure and standard) and
/// write a plan of the work that makes the night's products: master biases and flats, a map
/// and a catalog of every complete HWP set (chip files of one exposure together, repeated
/// cycles kept, masters of the nearest night with the same binning and filter), a
/// calibration of every sky field given with --sky, a zero angle from every polarized
/// standard (and their weighted mean per night and filter), the instrumental polarization at
/// every unpolarized standard, and a validation of every standard against its filter's
/// calibration nearest in time. Unusable files and incomplete sets are listed with the reason (an aborted set
/// names its missing angles). The plan is TOML, or JSON for a .json name; edit it freely and
/// run it with `instpol run`.
///
/// Example:
///   instpol scan night/ --instrument fors2 --sky "EMPTY-V:1.74:-53.8" --out night.toml
#[derive(clap::Args)]
pub struct ScanArgs {
    /// Folders of raw files (searched recursively for .fits, .fit, .fts) or files.
    #[arg(required = true)]
    pub dirs: Vec<PathBuf>,
    /// Instrument: built-in name or instrument TOML with a [headers] table.
    #[arg(long)]
    pub instrument: String,
    /// The plan to write (TOML; JSON for a .json name).
    #[arg(long)]
    pub out: PathBuf,
    /// Where the products go (default: a folder `products` beside the plan).
    #[arg(long)]
    pub products: Option<PathBuf>,
    /// A sky field of known polarization to calibrate on: TARGET:P_PERCENT:CHI_DEG, repeated.
    #[arg(long, value_name = "TARGET:P%:CHI", allow_hyphen_values = true)]
    pub sky: Vec<String>,
    /// Sky fields from a table (CSV, ECSV, FITS, VOTable) with columns target, p_percent
    /// (percent) and chi_deg (deg), beside any --sky.
    #[arg(long, value_name = "TABLE")]
    pub sky_table: Option<PathBuf>,
    /// A standards file (TOML, the format of instruments/standards.toml).
    #[arg(long)]
    pub standards: Option<PathBuf>,
    /// Largest distance (arcsec) of one set's pointings, and of a standard from the pointing.
    #[arg(long, default_value_t = 60.0)]
    pub pointing_tol: f64,
    /// Largest gap (minutes) between two exposures of one set.
    #[arg(long, default_value_t = 60.0)]
    pub max_gap: f64,
    /// Bin side (px) of the maps and calibrations.
    #[arg(long, default_value_t = 30)]
    pub bin: usize,
    /// Expected FWHM (px) of the stars, for the catalogs.
    #[arg(long, default_value_t = 4.0)]
    pub fwhm: f64,
    /// Aperture radius (px) of the catalogs and the standards' zero angles.
    #[arg(long, default_value_t = 8.0)]
    pub aperture: f64,
    /// Print the plan as JSON instead of a summary.
    #[arg(long)]
    pub json: bool,
}

/// Run a plan written by `instpol scan`: units in dependency order (masters before what
/// uses them), each skipped when its record says its inputs and outputs are unchanged, a
/// failing unit reported without stopping the others (exit status 1 when any failed, or when
/// a validate unit's standard is off its prediction: a check that did not pass). A run
/// killed at any point and started again redoes no finished unit. `--unit K` runs one unit
/// (after what it follows) for a Slurm job array or GNU parallel; `instpol run PLAN --list`
/// prints the unit ids, one a line.
///
/// Examples:
///   instpol run night.toml --jobs 4
///   instpol run night.toml --list | parallel instpol run night.toml --unit {}
#[derive(clap::Args)]
pub struct RunArgs {
    /// The plan (from `instpol scan`).
    pub plan: PathBuf,
    /// Number of units run at once (processes).
    #[arg(long, default_value_t = 1)]
    pub jobs: usize,
    /// Run this unit (by id or 0-based number in the plan) and what it follows; repeatable.
    #[arg(long, conflicts_with = "units")]
    pub unit: Vec<String>,
    /// Run units A to B (0-based numbers in the plan, inclusive) and what they follow.
    #[arg(long, value_name = "A..B")]
    pub units: Option<String>,
    /// Say what would run; run and write nothing.
    #[arg(long)]
    pub dry_run: bool,
    /// Print the unit ids, one a line, and nothing else.
    #[arg(long)]
    pub list: bool,
    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,
}

pub fn run_scan(a: ScanArgs) -> Result<()> {
    let products = match &a.products {
        Some(p) => p.clone(),
        None => a
            .out
            .parent()
            .filter(|d| !d.as_os_str().is_empty())
            .map_or_else(|| PathBuf::from("products"), |d| d.join("products")),
    };
    let mut opts = night::ScanOptions::new(&a.instrument, &products);
    opts.sky_fields = a
        .sky
        .iter()
        .map(|s| night::SkyField::parse(s).with_context(|| format!("--sky '{s}'")))
        .collect::<Result<_>>()?;
    if let Some(t) = &a.sky_table {
        opts.sky_fields.extend(night::SkyField::read_table(t)?);
    }
    opts.standards = a.standards.clone();
    opts.pointing_tol_arcsec = a.pointing_tol;
    opts.max_gap_min = a.max_gap;
    opts.bin_px = a.bin;
    opts.fwhm_px = a.fwhm;
    opts.aperture_px = a.aperture;
    let plan = night::scan(&a.dirs, &opts)?;
    if plan.files.iter().any(|f| f.path == std::path::absolute(&a.out).unwrap_or_default()) {
        bail!("output {} is one of the scanned files: refusing to write over an input", a.out.display());
    }
    // The plan and the products folder are outputs: neither may be one of the inputs named on
    // the command line (`--instrument`, `--sky-table`, `--standards`), whatever the name.
    crate::util::check_output(&a.out)?;
    crate::util::check_output(&products)?;
    plan.write(&a.out)?;
    if a.json {
        return crate::util::print_json(&plan);
    }
    let mut roles = std::collections::BTreeMap::<&str, usize>::new();
    for f in &plan.files {
        *roles.entry(f.role.as_str()).or_default() += 1;
    }
    let nleft: usize = plan.left_out.iter().map(|l| l.files.len()).sum();
    outln!(
        "{}: {} files usable ({}), {} left out; {} units",
        a.out.display(),
        plan.files.len(),
        roles.iter().map(|(r, n)| format!("{n} {r}")).collect::<Vec<_>>().join(", "),
        nleft,
        plan.units.len()
    );
    let mut kinds = std::collections::BTreeMap::<&str, usize>::new();
    for u in &plan.units {
        *kinds.entry(u.kind.as_str()).or_default() += 1;
    }
    outln!("{:<14} {:>5}", "unit kind", "count");
    for (k, n) in kinds {
        outln!("{k:<14} {n:>5}");
    }
    outln!("{:<44} {:>6}", "set (reduce unit)", "frames");
    for u in plan.units.iter().filter(|u| u.kind == "reduce") {
        let frames = u.inputs.iter().filter(|p| !p.starts_with(plan.records.parent().unwrap_or(&plan.records))).count();
        outln!("{:<44} {:>6}", u.id.trim_start_matches("reduce-"), frames);
    }
    if !plan.left_out.is_empty() {
        outln!("left out:");
        for l in &plan.left_out {
            outln!("  {}: {}", left_out_files(l), l.why);
        }
    }
    Ok(())
}

pub fn run_run(a: RunArgs) -> Result<()> {
    crate::util::inputs([a.plan.as_path()])?;
    let plan = night::Plan::load(&a.plan)?;
    if a.list {
        for u in &plan.units {
            outln!("{}", u.id);
        }
        return Ok(());
    }
    let by_number = |t: &str| -> Result<String> {
        match t.trim().parse::<usize>() {
            Ok(k) => plan.units.get(k).map(|u| u.id.clone()).with_context(|| {
                format!("unit number {k}: the plan has units 0 to {}", plan.units.len().saturating_sub(1))
            }),
            Err(_) => Ok(plan.unit(t.trim())?.id.clone()),
        }
    };
    let only = if !a.unit.is_empty() {
        Some(a.unit.iter().map(|t| by_number(t)).collect::<Result<Vec<_>>>()?)
    } else if let Some(r) = &a.units {
        let (lo, hi) = r.split_once("..").with_context(|| format!("--units '{r}': expected A..B, e.g. 0..4"))?;
        let (lo, hi): (usize, usize) = match (lo.trim().parse(), hi.trim().parse()) {
            (Ok(l), Ok(h)) if l <= h => (l, h),
            _ => bail!("--units '{r}': expected A..B with numbers A <= B"),
        };
        if hi >= plan.units.len() {
            bail!("--units '{r}': the plan has units 0 to {}", plan.units.len().saturating_sub(1));
        }
        Some(plan.units[lo..=hi].iter().map(|u| u.id.clone()).collect())
    } else {
        None
    };
    if a.jobs == 0 {
        bail!("--jobs 0: run at least one unit at a time");
    }
    let opts = night::RunOptions { jobs: a.jobs, only, dry_run: a.dry_run };
    // Units run in process through the library; a command the runner does not know whole
    // (one that prints its result) runs this binary.
    let exe = std::env::current_exe().context("cannot find the instpol binary to run the units")?;
    let exec = night::library_executor(Some(exe), plan.records.clone());
    let n = night::run::selection(&plan, &opts.only)?.len();
    let bar =
        if a.json || a.dry_run { indicatif::ProgressBar::hidden() } else { indicatif::ProgressBar::new(n as u64) };
    bar.set_style(
        indicatif::ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} units ({elapsed})")
            .expect("template")
            .progress_chars("=> "),
    );
    bar.set_message("running");
    let report = night::run::run(&plan, &opts, &exec, &|o| {
        bar.inc(1);
        if let night::Status::Failed(why) = &o.status {
            bar.println(format!("unit {} failed: {why}", o.id));
        }
    })?;
    bar.finish_and_clear();
    if a.json {
        crate::util::print_json(&report)?;
    } else {
        outln!("{:<48} {:<12} {:>8}  reason", "unit", "status", "seconds");
        for o in &report.outcomes {
            let (status, why) = match &o.status {
                night::Status::Done => ("done", ""),
                night::Status::UpToDate => ("up to date", ""),
                night::Status::WouldRun => ("would run", ""),
                night::Status::Failed(w) => ("FAILED", w.as_str()),
                night::Status::Blocked(w) => ("blocked", w.as_str()),
                night::Status::CheckFailed(w) => ("check failed", w.as_str()),
            };
            outln!("{:<48} {:<12} {:>8.1}  {why}", o.id, status, o.seconds);
        }
        let [done, up, would, failed, blocked, checks] = report.counts();
        outln!(
            "{done} done, {up} up to date, {would} would run, {failed} failed, {blocked} blocked, {checks} check(s) did not pass"
        );
    }
    let [_, _, _, failed, blocked, checks] = report.counts();
    if !report.ok() {
        return Err(crate::util::CheckFailed(format!("{failed} unit(s) failed and {blocked} blocked")).into());
    }
    if checks > 0 {
        return Err(crate::util::CheckFailed(format!(
            "{checks} check unit(s) ran and did not pass (validate: a standard off its prediction)"
        ))
        .into());
    }
    Ok(())
}

/// The files of a left-out entry for a person: the first three names, and how many more.
pub fn left_out_files(l: &night::LeftOut) -> String {
    let names: Vec<String> = l
        .files
        .iter()
        .take(3)
        .map(|p| p.file_name().map_or_else(|| p.display().to_string(), |n| n.to_string_lossy().to_string()))
        .collect();
    let more = if l.files.len() > 3 { format!(" and {} more", l.files.len() - 3) } else { String::new() };
    format!("{}{more}", names.join(", "))
}
