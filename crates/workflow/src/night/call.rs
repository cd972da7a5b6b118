//! A unit run in process: its command line read back into the library call it names
//! ([`Call`]), made through the steps the CLI and the Python package make
//! (`crate::steps`), under a provenance of its own (`skyfield::provenance::scoped`), so that
//! running a plan needs no `instpol` binary. The command line stays the unit's record and what
//! Slurm or GNU parallel run (docs/nights.md); a command this runner does not know whole (an
//! option a person added to a plan, a command that prints its result: `zero-angle`,
//! `photometry`, `fit-standards`, `validate`) runs the binary when one is given
//! ([`library_executor`]).

use super::plan::Unit;
use super::run::{process_executor, Executed};
// The defaults of the options a unit's command may leave out: the CLI's own, which its
// `--help` gives.
use crate::steps::{
    DEFAULT_APERTURE as APERTURE, DEFAULT_BIN_PX as BIN_PX, DEFAULT_FWHM_PX as FWHM_PX, DEFAULT_MASTER_NSIGMA as NSIGMA,
};
use skyfield::calib::ReadOptions;
use std::path::{Path, PathBuf};

/// The library call of a unit's command.
#[derive(Debug, Clone, PartialEq)]
pub enum Call {
    MasterBias {
        frames: Vec<PathBuf>,
        instrument: String,
        nsigma: f64,
        out: PathBuf,
    },
    MasterFlat {
        frames: Vec<PathBuf>,
        instrument: String,
        bias: Option<PathBuf>,
        nsigma: f64,
        out: PathBuf,
    },
    Reduce {
        frames: Vec<PathBuf>,
        instrument: String,
        bin: usize,
        bias: Option<PathBuf>,
        flat: Option<PathBuf>,
        out: PathBuf,
    },
    Catalog {
        frames: Vec<PathBuf>,
        instrument: String,
        fwhm: f64,
        aperture: String,
        bias: Option<PathBuf>,
        flat: Option<PathBuf>,
        out: PathBuf,
    },
    Calibrate {
        map: PathBuf,
        instrument: String,
        sky_p: f64,
        sky_chi: f64,
        bin: usize,
        out: PathBuf,
    },
}

/// A command line's arguments: the positional ones and `--name value` (or `--name=value`)
/// options; `None` for an option given without a value or twice.
fn split(args: &[String]) -> Option<(Vec<PathBuf>, Vec<(String, String)>)> {
    let (mut pos, mut opts) = (vec![], Vec::<(String, String)>::new());
    let mut it = args.iter();
    while let Some(a) = it.next() {
        match a.strip_prefix("--") {
            None => pos.push(PathBuf::from(a)),
            Some(name) => {
                let (name, value) = match name.split_once('=') {
                    Some((n, v)) => (n.to_string(), v.to_string()),
                    None => (name.to_string(), it.next()?.clone()),
                };
                if opts.iter().any(|(n, _)| *n == name) {
                    return None;
                }
                opts.push((name, value));
            }
        }
    }
    Some((pos, opts))
}

impl Call {
    /// The call unit `u` makes, when its command is one this runner knows whole: its kind's
    /// command with only the options `instpol scan` writes (module docs); `None` otherwise.
    pub fn of_unit(u: &Unit) -> Option<Call> {
        let (kind, rest) = u.command.split_first()?;
        if u.stdout || *kind != u.kind {
            return None;
        }
        let (frames, opts) = split(rest)?;
        let known: &[&str] = match kind.as_str() {
            "master-bias" => &["instrument", "nsigma", "out"],
            "master-flat" => &["instrument", "bias", "nsigma", "out"],
            "reduce" => &["instrument", "bin", "bias", "flat", "out"],
            "catalog" => &["instrument", "fwhm", "aperture", "bias", "flat", "out"],
            "calibrate" => &["map", "instrument", "sky-p", "sky-chi", "bin", "out"],
            _ => return None,
        };
        if opts.iter().any(|(n, _)| !known.contains(&n.as_str())) {
            return None;
        }
        let get = |n: &str| opts.iter().find(|(m, _)| m == n).map(|(_, v)| v.clone());
        let num = |n: &str, default: f64| get(n).map_or(Some(default), |v| v.parse::<f64>().ok());
        let bin = get("bin").map_or(Some(BIN_PX), |v| v.parse::<usize>().ok())?;
        let path = |n: &str| get(n).map(PathBuf::from);
        let (instrument, out) = (get("instrument")?, path("out")?);
        let call = match kind.as_str() {
            "master-bias" => Call::MasterBias { frames, instrument, nsigma: num("nsigma", NSIGMA)?, out },
            "master-flat" => {
                Call::MasterFlat { frames, instrument, bias: path("bias"), nsigma: num("nsigma", NSIGMA)?, out }
            }
            "reduce" => Call::Reduce { frames, instrument, bin, bias: path("bias"), flat: path("flat"), out },
            "catalog" => Call::Catalog {
                frames,
                instrument,
                fwhm: num("fwhm", FWHM_PX)?,
                aperture: get("aperture").unwrap_or_else(|| APERTURE.into()),
                bias: path("bias"),
                flat: path("flat"),
                out,
            },
            _ => {
                if !frames.is_empty() {
                    return None;
                }
                let (sky_p, sky_chi) = (get("sky-p")?.parse().ok()?, get("sky-chi")?.parse().ok()?);
                Call::Calibrate { map: path("map")?, instrument, sky_p, sky_chi, bin, out }
            }
        };
        (!call.frames().is_empty() || matches!(call, Call::Calibrate { .. })).then_some(call)
    }

    fn frames(&self) -> &[PathBuf] {
        match self {
            Call::MasterBias { frames, .. }
            | Call::MasterFlat { frames, .. }
            | Call::Reduce { frames, .. }
            | Call::Catalog { frames, .. } => frames,
            Call::Calibrate { .. } => &[],
        }
    }

    /// Every file the command names as an input, as `instpol` reports them to a runner: the
    /// frames, the masters, the map and the instrument file (a built-in instrument is no file).
    pub fn inputs(&self) -> Vec<PathBuf> {
        let (instrument, others): (&str, Vec<&Option<PathBuf>>) = match self {
            Call::MasterBias { instrument, .. } => (instrument, vec![]),
            Call::MasterFlat { instrument, bias, .. } => (instrument, vec![bias]),
            Call::Reduce { instrument, bias, flat, .. } | Call::Catalog { instrument, bias, flat, .. } => {
                (instrument, vec![bias, flat])
            }
            Call::Calibrate { instrument, .. } => (instrument, vec![]),
        };
        let map = match self {
            Call::Calibrate { map, .. } => Some(map.clone()),
            _ => None,
        };
        self.frames()
            .iter()
            .cloned()
            .chain(others.into_iter().flatten().cloned())
            .chain(map)
            .chain(instrument_file(instrument).map(Path::to_path_buf))
            .collect()
    }

    /// Make the call (inside its provenance's scope): the files are registered in the
    /// provenance as the command registers them, then the step runs. The error is the
    /// command's message.
    fn make(&self) -> Result<(), String> {
        let err = |e: &dyn std::fmt::Display| e.to_string();
        let load = |name: &str| instrument::Instrument::load(name).map_err(|e| err(&e));
        let distinct = |frames: &[PathBuf]| match skyfield::same::distinct_files(frames, skyfield::same::By::Content)
            .duplicates
            .first()
        {
            Some(d) => Err(format!("{d}: each input may be given once (the same data twice would be counted twice)")),
            None => Ok(()),
        };
        let register = |paths: &[&Path]| skyfield::provenance::add_inputs(paths);
        match self {
            Call::MasterBias { frames, instrument, nsigma, out } => {
                distinct(frames)?;
                register(&frames.iter().map(|p| p.as_path()).chain(instrument_file(instrument)).collect::<Vec<_>>());
                crate::steps::master_bias(frames, &load(instrument)?, *nsigma, out).map_err(|e| err(&e))?;
            }
            Call::MasterFlat { frames, instrument, bias, nsigma, out } => {
                distinct(frames)?;
                let named =
                    frames.iter().map(|p| p.as_path()).chain(bias.as_deref()).chain(instrument_file(instrument));
                register(&named.collect::<Vec<_>>());
                let inst = load(instrument)?;
                crate::steps::master_flat(frames, &inst, bias.as_deref(), *nsigma, out).map_err(|e| err(&e))?;
            }
            Call::Reduce { frames, instrument, bin, bias, flat, out } => {
                distinct(frames)?;
                register(&frames.iter().map(|p| p.as_path()).chain(instrument_file(instrument)).collect::<Vec<_>>());
                let inst = load(instrument)?;
                skyfield::reduce::check_bin(*bin, &inst).map_err(|e| format!("--bin {bin}: {e}"))?;
                let cfg = skyfield::reduce::ReduceConfig { bin_px: *bin, ..Default::default() };
                let read = ReadOptions { bias: bias.clone(), flat: flat.clone(), ..Default::default() };
                crate::steps::reduce(frames, &inst, &cfg, &read, Some(out), &|| {}).map_err(|e| err(&e))?;
            }
            Call::Catalog { frames, instrument, fwhm, aperture, bias, flat, out } => {
                distinct(frames)?;
                let inst = load(instrument)?;
                let cfg = catalog_config(*fwhm, aperture)?;
                skyfield::table::Format::from_path(out).map_err(|e| format!("--out {e}"))?;
                let streamed: Vec<&Path> = frames.iter().map(|p| p.as_path()).collect();
                skyfield::provenance::add_inputs_read_in_order(&streamed);
                register(
                    &[bias.as_deref(), flat.as_deref(), instrument_file(instrument)]
                        .into_iter()
                        .flatten()
                        .collect::<Vec<_>>(),
                );
                let read = ReadOptions { bias: bias.clone(), flat: flat.clone(), ..Default::default() };
                crate::steps::catalog(frames, &inst, &read, &cfg, None, Some(out), Box::new(|| {}))
                    .map_err(|e| err(&e))?;
            }
            Call::Calibrate { map, instrument, sky_p, sky_chi, bin, out } => {
                let sky = skyfield::solve::SkyPolarization::from_percent_deg(*sky_p, *sky_chi).map_err(|e| err(&e))?;
                // `instpol calibrate`'s defaults: the radial3 model, Huber weights, conservative errors.
                let opts = fit::models::pipeline::CalibrateOptions::default();
                register(&[Some(map.as_path()), instrument_file(instrument)].into_iter().flatten().collect::<Vec<_>>());
                let inst = load(instrument)?;
                skyfield::reduce::check_bin(*bin, &inst).map_err(|e| format!("--bin {bin}: {e}"))?;
                crate::steps::calibrate_map(map, &sky, &inst, &opts, Some(out))
                    .map_err(|e| format!("cannot calibrate from Stokes map {}: {e}", map.display()))?;
            }
        }
        Ok(())
    }

    /// Run the call for unit `u` under a provenance of its own: its command line (`instpol`
    /// and the unit's command) and instrument, its temporaries tagged with the unit's id; what
    /// it read with their hashes, as the binary reports them (`run::INPUT_HASHES_ENV`).
    pub fn run(&self, u: &Unit) -> Result<Executed, String> {
        let args: Vec<String> = std::iter::once("instpol".to_string()).chain(u.command.iter().cloned()).collect();
        let p = skyfield::provenance::Provenance::of_command(&args);
        let (made, prov) = skyfield::provenance::scoped(p, Some(&u.id), || {
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| self.make()))
        });
        match made {
            Ok(Ok(())) => {}
            Ok(Err(why)) => return Err(why),
            Err(_) => return Err(format!("unit {}: the library call panicked (a defect: please report it)", u.id)),
        }
        let mut read: Vec<(PathBuf, String)> =
            prov.inputs.iter().map(|i| (PathBuf::from(&i.path), i.hash.clone())).collect();
        for p in self.inputs() {
            if p.is_file() && !read.iter().any(|(q, _)| *q == p) {
                if let Ok(h) = skyfield::provenance::hash_file(&p) {
                    read.push((p, h));
                }
            }
        }
        Ok(Executed { stdout: vec![], check_failed: None, input_hashes: read })
    }
}

/// The instrument file `--instrument` names, when it names a file (else a built-in name).
fn instrument_file(name: &str) -> Option<&Path> {
    let p = Path::new(name);
    p.is_file().then_some(p)
}

/// The catalog's settings from a unit's `--fwhm` and `--aperture`, the others `instpol
/// catalog`'s defaults (`skyfield::catalog::CatalogConfig::with_detection`).
fn catalog_config(fwhm: f64, aperture: &str) -> Result<skyfield::catalog::CatalogConfig, String> {
    let radius = skyfield::photometry::ApertureRadius::parse(aperture)
        .ok_or_else(|| format!("--aperture '{aperture}': expected a radius in px, a multiple of the FWHM or 'best'"))?;
    let cfg = skyfield::catalog::CatalogConfig::with_detection(fwhm, radius);
    cfg.check().map_err(|e| format!("--{e}"))?;
    Ok(cfg)
}

/// The executor of a plan's units in process ([`Call`]); a unit whose command this runner does
/// not know whole runs `program` (the `instpol` binary, [`process_executor`]) when given, else
/// fails saying so.
pub fn library_executor(
    program: Option<PathBuf>,
    records: PathBuf,
) -> impl Fn(&Unit) -> Result<Executed, String> + Sync {
    let binary = program.map(|p| process_executor(p, records));
    move |u: &Unit| match (Call::of_unit(u), &binary) {
        (Some(call), _) => call.run(u),
        (None, Some(b)) => b(u),
        (None, None) => Err(format!(
            "the {} command of unit {} runs only through the instpol binary, and none was given \
             (instpol.run's instpol_bin or $INSTPOL_BIN, or instpol on PATH)",
            u.kind, u.id
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit(kind: &str, command: &[&str]) -> Unit {
        let command = command.iter().map(|s| s.to_string()).collect();
        Unit::new("u", kind, vec![], vec![PathBuf::from("o")], command, vec![])
    }

    /// The commands `instpol scan` writes read back into their calls, the options left out at
    /// the values `instpol --help` gives them (nsigma 3, bin 30, fwhm 4, aperture 8).
    #[test]
    fn the_commands_a_plan_holds_are_read_back() {
        let u = unit(
            "reduce",
            &["reduce", "a.fits", "b.fits", "--instrument", "fors2", "--bin", "8", "--flat=f.fits", "--out", "m.fits"],
        );
        let want = Call::Reduce {
            frames: vec!["a.fits".into(), "b.fits".into()],
            instrument: "fors2".into(),
            bin: 8,
            bias: None,
            flat: Some("f.fits".into()),
            out: "m.fits".into(),
        };
        assert_eq!(Call::of_unit(&u), Some(want));
        let u = unit("master-bias", &["master-bias", "b1.fits", "--instrument", "fors2", "--out", "bias.fits"]);
        let want = Call::MasterBias {
            frames: vec!["b1.fits".into()],
            instrument: "fors2".into(),
            nsigma: 3.0,
            out: "bias.fits".into(),
        };
        assert_eq!(Call::of_unit(&u), Some(want));
        let u = unit("catalog", &["catalog", "a.fits", "--instrument", "i.toml", "--out", "c.ecsv"]);
        let Some(Call::Catalog { fwhm, aperture, .. }) = Call::of_unit(&u) else { panic!("not a catalog") };
        assert_eq!((fwhm, aperture.as_str()), (4.0, "8"));
        let cmd = [
            "calibrate",
            "--map",
            "m.fits",
            "--instrument",
            "fors2",
            "--sky-p",
            "1.74",
            "--sky-chi",
            "-53.8",
            "--out",
            "c.fits",
        ];
        let want = Call::Calibrate {
            map: "m.fits".into(),
            instrument: "fors2".into(),
            sky_p: 1.74,
            sky_chi: -53.8,
            bin: 30,
            out: "c.fits".into(),
        };
        assert_eq!(Call::of_unit(&unit("calibrate", &cmd)), Some(want));
    }

    /// A command the runner does not know whole goes to the binary: an option it does not
    /// read, one given twice or without a value, a number that is none, a printed result, a
    /// kind that is not its command's, a command of another kind, no frames.
    #[test]
    fn a_command_not_known_whole_is_left_to_the_binary() {
        let base = ["reduce", "a.fits", "--instrument", "fors2", "--out", "m.fits"];
        assert!(Call::of_unit(&unit("reduce", &base)).is_some());
        let with = |extra: &[&str]| unit("reduce", &[&base[..], extra].concat());
        for extra in [&["--allow-incomplete"][..], &["--bin", "8", "--bin", "9"], &["--bin", "eight"], &["--json"]] {
            assert_eq!(Call::of_unit(&with(extra)), None, "{extra:?}");
        }
        let mut printed = unit("reduce", &base);
        printed.stdout = true;
        assert_eq!(Call::of_unit(&printed), None);
        assert_eq!(Call::of_unit(&unit("catalog", &base)), None);
        let za = ["zero-angle", "a.fits", "--instrument", "fors2", "--out", "z.json"];
        assert_eq!(Call::of_unit(&unit("zero-angle", &za)), None);
        assert_eq!(Call::of_unit(&unit("reduce", &["reduce", "--instrument", "fors2", "--out", "m.fits"])), None);
    }
}
