//! Provenance: what made an output. The one provenance type of the workspace, written into the
//! primary header of every FITS file the workspace writes ([`stamp`]) and, by the CLI, into its
//! JSON output as a `provenance` object.
//!
//! A run has one provenance: the program (`instpol` and its version), the command line, the UTC
//! date, the instrument (name and a BLAKE3 hash of its definition) and every input file with a
//! BLAKE3 hash of its bytes (`blake3:<64 hex digits>`, what `b3sum` prints). The CLI fills it once per run ([`set_session`], [`add_input`],
//! [`set_instrument`]); every FITS writer then stamps it without each command passing it down.
//! A library caller that never sets it gets the program, version and date only.
//!
//! In FITS the provenance is written as keywords `PROGRAM`, `PROGVER`, `DATE` (the FITS
//! standard's file-creation date, UTC) and a block of `HISTORY` cards (a path and its hash do
//! not fit a 68-character keyword value), one line per item, long lines continued on the next
//! card after two spaces:
//!
//! ```text
//! HISTORY instpol 0.1.0 2026-11-23T23:59:59 UTC
//! HISTORY command: instpol reduce frames/a.fits frames/b.fits --instrument fors1 --out m
//! HISTORY   ap.fits
//! HISTORY instrument: fors1 blake3:5f1c...
//! HISTORY input 1: frames/a.fits blake3:9b0e...
//! ```
//!
//! Why BLAKE3 and not SHA-256 (used up to 0.1): a hash of every input is one more read of
//! every input, and it was the largest single cost of the commands that read many frames
//! (a fifth of a catalog's CPU time, a third of a raw FORS2 reduction's). BLAKE3 is a
//! cryptographic hash like SHA-256, so a provenance record still names its inputs beyond
//! doubt, and on this project's machines it hashes 2.5 times faster than SHA-256 with the
//! CPU's SHA instructions (bench/RESULTS.md). `b3sum` (the BLAKE3 team's tool) and Python's
//! `blake3` package reproduce the hashes.

use serde::{Deserialize, Serialize};

/// How to cite `instpol` and the paper it implements (Patat & Romaniello 2006, PASP 118, 146),
/// with BibTeX entries: the one text of the citation, which `instpol --version` prints after
/// the version and the Python package gives as `instpol.__citation__`. It agrees with
/// `CITATION.cff` at the repository's root (a test below compares the paper's fields).
pub fn citation() -> String {
    include_str!("citation.txt").replace("VERSION", env!("CARGO_PKG_VERSION"))
}

use std::io::Read;
use std::path::Path;
use std::sync::Mutex;

/// One input file and the hash of its bytes.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct InputFile {
    pub path: String,
    /// `blake3:<64 hex digits>` of the file's bytes (module docs).
    pub hash: String,
}

/// What made an output (module docs).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Provenance {
    /// Always `instpol`.
    pub program: String,
    pub version: String,
    /// The command line, arguments joined by spaces (empty for a library call).
    pub command_line: String,
    /// UTC date and time of the run, ISO 8601 (`YYYY-MM-DDThh:mm:ss`).
    pub date_utc: String,
    /// Instrument name, when the run used one.
    pub instrument: Option<String>,
    /// `blake3:<hex>` of the instrument's definition (its TOML text).
    pub instrument_hash: Option<String>,
    pub inputs: Vec<InputFile>,
}

impl Default for Provenance {
    fn default() -> Self {
        Self::new("")
    }
}

/// `blake3:<hex>` of bytes.
pub fn hash_hex(bytes: &[u8]) -> String {
    label(&blake3::hash(bytes))
}

fn label(h: &blake3::Hash) -> String {
    format!("blake3:{}", h.to_hex())
}

/// `blake3:<hex>` of a file's bytes, streamed (a frame set can be gigabytes).
pub fn hash_file(path: &Path) -> std::io::Result<String> {
    let mut f = std::fs::File::open(path)?;
    let mut h = blake3::Hasher::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = f.read(&mut buf)?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
    }
    Ok(label(&h.finalize()))
}

/// Days since 1970-01-01 to a proleptic Gregorian (year, month, day) (Hinnant's civil-from-days
/// algorithm, exact for every day the i64 range holds).
fn civil_from_days(z: i64) -> (i64, u32, u32) {
    let z = z + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let m = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    (yoe + era * 400 + i64::from(m <= 2), m, d)
}

/// Seconds since the Unix epoch as ISO 8601 UTC (`YYYY-MM-DDThh:mm:ss`), the form of the FITS
/// `DATE` keyword.
pub fn iso_utc(unix_seconds: i64) -> String {
    let (days, secs) = (unix_seconds.div_euclid(86_400), unix_seconds.rem_euclid(86_400));
    let (y, m, d) = civil_from_days(days);
    format!("{y:04}-{m:02}-{d:02}T{:02}:{:02}:{:02}", secs / 3600, secs % 3600 / 60, secs % 60)
}

fn now_utc() -> String {
    let s = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs() as i64).unwrap_or(0);
    iso_utc(s)
}

impl Provenance {
    /// The program, its version and the current UTC date, with `command_line`.
    pub fn new(command_line: &str) -> Self {
        Self {
            program: "instpol".into(),
            version: env!("CARGO_PKG_VERSION").into(),
            command_line: command_line.into(),
            date_utc: now_utc(),
            instrument: None,
            instrument_hash: None,
            inputs: Vec::new(),
        }
    }

    /// Add an input file with the hash of its bytes (once per path). A file that cannot be
    /// read is recorded with hash `unreadable` (its reader reports the real error).
    pub fn add_input(&mut self, path: &Path) {
        let p = path.display().to_string();
        if self.inputs.iter().any(|i| i.path == p) {
            return;
        }
        let hash = hash_file(path).unwrap_or_else(|_| "unreadable".into());
        self.inputs.push(InputFile { path: p, hash });
    }

    /// The instrument's name and the hash of its definition text.
    pub fn set_instrument(&mut self, name: &str, definition: &[u8]) {
        self.instrument = Some(name.into());
        self.instrument_hash = Some(hash_hex(definition));
    }

    /// The provenance as HISTORY lines (module docs), each at most 70 characters, the limit of
    /// a HISTORY card's text.
    pub fn history_lines(&self) -> Vec<String> {
        let mut items = vec![format!("{} {} {} UTC", self.program, self.version, self.date_utc)];
        if !self.command_line.is_empty() {
            items.push(format!("command: {}", self.command_line));
        }
        if let Some(n) = &self.instrument {
            items.push(format!("instrument: {n} {}", self.instrument_hash.as_deref().unwrap_or("")));
        }
        for (k, i) in self.inputs.iter().enumerate() {
            items.push(format!("input {}: {} {}", k + 1, i.path, i.hash));
        }
        let mut out = Vec::new();
        for it in items {
            // Printable ASCII only: a FITS header holds nothing else.
            let it: String = it.chars().map(|c| if (' '..='~').contains(&c) { c } else { '?' }).collect();
            let mut rest = it.as_str();
            let mut first = true;
            while !rest.is_empty() || first {
                let width = if first { 70 } else { 68 };
                let cut = rest.len().min(width);
                let (head, tail) = rest.split_at(cut);
                out.push(if first { head.to_string() } else { format!("  {head}") });
                rest = tail;
                first = false;
            }
        }
        out
    }

    /// Write the provenance into header `hdu` of `f`: `PROGRAM`, `PROGVER`, `DATE` (each
    /// updated if the header has it already) and the HISTORY block (module docs).
    pub fn write_fits(&self, f: &mut fitsio::FitsFile, hdu: &fitsio::hdu::FitsHdu) -> Result<(), String> {
        let mut status = 0;
        let c = |s: &str| std::ffi::CString::new(s).map_err(|e| e.to_string());
        // Updated rather than appended: a file that already has them (a catalog being
        // corrected in place of a copy) keeps one card of each.
        let keys = [
            ("PROGRAM", self.program.as_str(), "software that wrote this file"),
            ("PROGVER", self.version.as_str(), "version of that software"),
            ("DATE", self.date_utc.as_str(), "UTC date the file was written"),
        ];
        // SAFETY: `f` is open; `hdu` is made current first.
        unsafe {
            let mut ty = 0;
            fitsio::sys::ffmahd(f.as_raw(), hdu.number as i32 + 1, &mut ty, &mut status);
        }
        for (k, v, com) in keys {
            let (k, v, com) = (c(k)?, c(v)?, c(com)?);
            // SAFETY: an open file at the right HDU; NUL-terminated strings.
            unsafe { fitsio::sys::ffukys(f.as_raw(), k.as_ptr(), v.as_ptr(), com.as_ptr(), &mut status) };
        }
        for line in self.history_lines() {
            let l = c(&line)?;
            // SAFETY: as above.
            unsafe { fitsio::sys::ffphis(f.as_raw(), l.as_ptr(), &mut status) };
        }
        if status != 0 {
            return Err(format!("writing the provenance (CFITSIO status {status})"));
        }
        Ok(())
    }
}

/// What a product is: the instrument and filter it was measured with, the plate, the frame of
/// its `(q, u)`, the detector's geometry and the hashes of what it was made from. Carried by
/// every table the workspace writes (as keywords: FITS table keywords, ECSV `meta`, VOTable
/// `PARAM`s, CSV `# KEY = value` comment lines before the header: [`Product::pairs`]) and
/// given back by every reader ([`Product::from_pairs`]), so that a command combining a table
/// with a calibration can check that the two are of the same instrument, filter and plate
/// (`fit::correction::setup::check_compatible`). A table written by other software has none; every field
/// is optional because a product knows only what its maker knew.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Product {
    /// The instrument's name (its file's `name`, as FITS `INSTRUME`).
    pub instrument: Option<String>,
    /// `blake3:<hex>` of the instrument's definition (its TOML text).
    pub instrument_hash: Option<String>,
    /// The filter's name as the instrument file gives it.
    pub filter: Option<String>,
    /// The filter's central wavelength (micron).
    pub wavelength_um: Option<f64>,
    /// The wave plate: `half_wave` or `quarter_wave`.
    pub plate: Option<String>,
    /// The frame of the product's `(q, u)`: `None` unknown, else `mueller::Frame` in words
    /// ([`Product::frame`]).
    pub zero_angle_deg: Option<f64>,
    /// `true`: the values are at the plate, as demodulated; `false`: in the sky frame of
    /// `zero_angle_deg` (the celestial frame when `position_angle_deg` is given).
    pub at_plate: Option<bool>,
    /// The instrument's position angle on the sky (deg) the values were turned by into the
    /// celestial frame, north through east (`mueller::Frame::Celestial`, keyword `SKYPA`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub position_angle_deg: Option<f64>,
    /// The detector binning (x, y).
    pub binning: Option<(u32, u32)>,
    /// The detector's size (pixels, x by y) and pixel scale (arcsec per unbinned pixel).
    pub detector_px: Option<(usize, usize)>,
    pub pixel_scale_arcsec: Option<f64>,
    /// `blake3:<hex>` of each input it was made from, in order.
    pub inputs: Vec<String>,
    /// What differed between the data and a calibration that corrected them all the same
    /// (`--allow-mismatch`), in a few words; `None` when nothing did.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mismatch_allowed: Option<String>,
}

/// The keywords of a [`Product`] (FITS-keyword names: at most 8 characters), in writing order;
/// the inputs follow as `INHASH1`, `INHASH2`, ...
pub const PRODUCT_KEYS: [&str; 12] = [
    "INSTRUME", "INSTHASH", "FILTER", "WAVELEN", "PLATE", "FRAME", "HWPZERO", "SKYPA", "BINNING", "DETSIZE",
    "PIXSCALE", "MISMATCH",
];

impl Product {
    /// The frame of the product's `(q, u)`, when it says.
    pub fn frame(&self) -> Option<mueller::Frame> {
        match (self.at_plate, self.zero_angle_deg, self.position_angle_deg) {
            (Some(true), _, _) => Some(mueller::Frame::Plate),
            (Some(false), Some(z), Some(pa)) => {
                Some(mueller::Frame::Celestial { zero_angle_deg: z, position_angle_deg: pa })
            }
            (Some(false), Some(z), None) => Some(mueller::Frame::Sky { zero_angle_deg: z }),
            _ => None,
        }
    }

    /// Whether `key` is one of a product's keywords ([`PRODUCT_KEYS`] or `INHASH<n>`).
    pub fn is_key(key: &str) -> bool {
        let k = key.trim().to_ascii_uppercase();
        PRODUCT_KEYS.contains(&k.as_str())
            || k.strip_prefix("INHASH").is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
    }

    /// The product as keyword and text value pairs, the ones it knows, in [`PRODUCT_KEYS`]
    /// order, then one `INHASH<n>` per input (hex digits without the `blake3:` label: a FITS
    /// string value holds at most 68 characters). Numbers are written to round-trip (`{:?}`).
    pub fn pairs(&self) -> Vec<(String, String)> {
        let hex = |h: &str| h.strip_prefix("blake3:").unwrap_or(h).to_string();
        let mut out: Vec<(String, String)> = Vec::new();
        let mut put = |k: &str, v: Option<String>| {
            if let Some(v) = v {
                out.push((k.to_string(), v));
            }
        };
        put("INSTRUME", self.instrument.clone());
        put("INSTHASH", self.instrument_hash.as_deref().map(hex));
        put("FILTER", self.filter.clone());
        put("WAVELEN", self.wavelength_um.map(|w| format!("{w:?}")));
        put("PLATE", self.plate.clone());
        let sky = if self.position_angle_deg.is_some() { "celestial" } else { "sky" };
        put("FRAME", self.at_plate.map(|p| if p { "plate" } else { sky }.to_string()));
        put("HWPZERO", self.zero_angle_deg.map(|z| format!("{z:?}")));
        put("SKYPA", self.position_angle_deg.map(|a| format!("{a:?}")));
        put("BINNING", self.binning.map(|(x, y)| format!("{x}x{y}")));
        put("DETSIZE", self.detector_px.map(|(x, y)| format!("{x}x{y}")));
        put("PIXSCALE", self.pixel_scale_arcsec.map(|s| format!("{s:?}")));
        put("MISMATCH", self.mismatch_allowed.clone());
        for (k, h) in self.inputs.iter().enumerate() {
            out.push((format!("INHASH{}", k + 1), hex(h)));
        }
        out
    }

    /// A product read back from keyword and text pairs (any case; unknown keywords ignored);
    /// `None` when none of a product's keywords is there (a table written by other software).
    /// A value that does not parse is an error naming the keyword.
    pub fn from_pairs<'a>(pairs: impl IntoIterator<Item = (&'a str, &'a str)>) -> Result<Option<Self>, String> {
        let mut p = Product::default();
        let mut any = false;
        let mut inputs: Vec<(usize, String)> = Vec::new();
        let mut celestial = false;
        let num = |k: &str, v: &str| -> Result<f64, String> {
            v.trim().parse::<f64>().ok().filter(|x| x.is_finite()).ok_or_else(|| format!("{k} = '{v}' is not a number"))
        };
        let two = |k: &str, v: &str| -> Result<(u64, u64), String> {
            let bad = || format!("{k} = '{v}' is not of the form NxM");
            let (a, b) = v.trim().split_once(['x', 'X']).ok_or_else(bad)?;
            Ok((a.trim().parse().map_err(|_| bad())?, b.trim().parse().map_err(|_| bad())?))
        };
        for (k, v) in pairs {
            let key = k.trim().to_ascii_uppercase();
            if !Self::is_key(&key) {
                continue;
            }
            any = true;
            let text = v.trim().to_string();
            match key.as_str() {
                "INSTRUME" => p.instrument = Some(text),
                "INSTHASH" => p.instrument_hash = Some(format!("blake3:{text}")),
                "FILTER" => p.filter = Some(text),
                "WAVELEN" => p.wavelength_um = Some(num(&key, v)?),
                "PLATE" => p.plate = Some(text),
                "FRAME" => {
                    p.at_plate = Some(match text.to_ascii_lowercase().as_str() {
                        "plate" => true,
                        "sky" | "celestial" => false,
                        _ => return Err(format!("FRAME = '{v}' is none of 'plate', 'sky' and 'celestial'")),
                    });
                    celestial = text.eq_ignore_ascii_case("celestial");
                }
                "HWPZERO" => p.zero_angle_deg = Some(num(&key, v)?),
                "SKYPA" => p.position_angle_deg = Some(num(&key, v)?),
                "BINNING" => {
                    let (x, y) = two(&key, v)?;
                    p.binning = Some((x as u32, y as u32));
                }
                "DETSIZE" => {
                    let (x, y) = two(&key, v)?;
                    p.detector_px = Some((x as usize, y as usize));
                }
                "PIXSCALE" => p.pixel_scale_arcsec = Some(num(&key, v)?),
                "MISMATCH" => p.mismatch_allowed = Some(text),
                _ => {
                    let n: usize = key["INHASH".len()..].parse().map_err(|_| format!("{key}: not a numbered input"))?;
                    inputs.push((n, format!("blake3:{text}")));
                }
            }
        }
        if celestial != p.position_angle_deg.is_some() {
            return Err(if celestial {
                "FRAME = 'celestial' without SKYPA, the position angle it was turned by".to_string()
            } else {
                "SKYPA is given but FRAME is not 'celestial'".to_string()
            });
        }
        inputs.sort();
        p.inputs = inputs.into_iter().map(|(_, h)| h).collect();
        Ok(any.then_some(p))
    }

    /// The product of measurements made with `inst` in `filter` (its name, the hash of its
    /// definition when known, the filter's wavelength, the plate, the detector), in the frame
    /// given; inputs and binning are the caller's to add.
    pub fn of_instrument(inst: &instrument::Instrument, filter: &str, frame: Option<mueller::Frame>) -> Self {
        let f = inst.filter(filter).ok();
        Product {
            instrument: Some(inst.name.clone()),
            instrument_hash: inst.definition.as_deref().map(|t| hash_hex(t.as_bytes())),
            filter: Some(f.map_or_else(|| filter.to_string(), |f| f.name.clone())),
            wavelength_um: f.map(|f| f.lambda_eff_nm / 1000.0),
            plate: Some(inst.polarimetry.plate.name().to_string()),
            zero_angle_deg: frame.and_then(|f| f.zero_angle_deg()),
            at_plate: frame.map(|f| matches!(f, mueller::Frame::Plate)),
            position_angle_deg: frame.and_then(|f| f.position_angle_deg()),
            binning: None,
            detector_px: Some((inst.detector.nx, inst.detector.ny)),
            pixel_scale_arcsec: Some(inst.detector.pixel_scale_arcsec),
            inputs: Vec::new(),
            mismatch_allowed: None,
        }
    }

    /// The product of measurements made with `inst` in no one filter (a night's plan, a
    /// trend): [`Product::of_instrument`] without the filter and its wavelength.
    pub fn of_instrument_alone(inst: &instrument::Instrument) -> Self {
        Product { filter: None, wavelength_um: None, ..Product::of_instrument(inst, "", None) }
    }

    /// The product as written: one that lists no inputs gets the run's (the provenance's
    /// hashes), as every writer stamps the run's provenance without each command passing
    /// its inputs down.
    pub fn with_run_inputs(&self) -> Product {
        if !self.inputs.is_empty() {
            return self.clone();
        }
        let inputs = current().inputs.into_iter().map(|i| i.hash).collect();
        Product { inputs, ..self.clone() }
    }

    /// The product as it goes into `--json` and a report: the pairs as an object.
    pub fn describe(&self) -> String {
        self.pairs()
            .iter()
            .filter(|(k, _)| !k.starts_with("INHASH"))
            .map(|(k, v)| format!("{k}={v}"))
            .collect::<Vec<_>>()
            .join(" ")
    }
}

static SESSION: Mutex<Option<Provenance>> = Mutex::new(None);

impl Provenance {
    /// The provenance a command line starts with: `args` (the program's name first, then the
    /// command and its arguments) as the command line, and the instrument its `--instrument`
    /// names (a file, hashed, or a built-in definition by its lower-case name). The CLI starts
    /// every run with it, and `workflow::night` every unit it runs in process.
    pub fn of_command(args: &[String]) -> Provenance {
        let mut p = Provenance::new(&args.join(" "));
        let inst = args.iter().enumerate().find_map(|(i, a)| match a.strip_prefix("--instrument=") {
            Some(v) => Some(v.to_string()),
            None if a == "--instrument" => args.get(i + 1).cloned(),
            None => None,
        });
        if let Some(name) = inst {
            if let Ok(bytes) = std::fs::read(&name) {
                p.set_instrument(&name, &bytes);
            } else if let Some(text) = instrument::builtin_source(&name) {
                p.set_instrument(&name.to_ascii_lowercase(), text.as_bytes());
            }
        }
        p
    }
}

/// The tag of the temporaries of the [`scoped`] run (`crate::fits::temp_beside`).
static SCOPE_TAG: Mutex<Option<String>> = Mutex::new(None);

/// The tag of the temporaries of the [`scoped`] run now running, if any.
pub(crate) fn scope_tag() -> Option<String> {
    SCOPE_TAG.lock().unwrap_or_else(|e| e.into_inner()).clone()
}

/// Held while a [`scoped`] session runs: one at a time in a process, since the session, its
/// pending hashes and the temporaries' tag are the process's.
static SCOPE: Mutex<()> = Mutex::new(());

/// Run `work` as a run of its own within this process: with `p` as the session's provenance
/// and `tag` as the tag of the temporaries it writes (`.instpol-<tag>.*`, as the environment
/// variable `INSTPOL_TEMP_TAG` gives a command); returns what it returned and the provenance
/// it ended with (its inputs with their hashes). The session before is restored after. Scoped
/// runs take their turn: a second waits for the first to end. What `workflow::night` runs a
/// plan's unit in process with, so that the unit's products record its own command and inputs.
pub fn scoped<R>(p: Provenance, tag: Option<&str>, work: impl FnOnce() -> R) -> (R, Provenance) {
    let _turn = SCOPE.lock().unwrap_or_else(|e| e.into_inner());
    settle();
    let before = SESSION.lock().unwrap_or_else(|e| e.into_inner()).replace(p);
    *SCOPE_TAG.lock().unwrap_or_else(|e| e.into_inner()) = tag.map(str::to_string);
    let out = work();
    let ended = current();
    *SCOPE_TAG.lock().unwrap_or_else(|e| e.into_inner()) = None;
    *SESSION.lock().unwrap_or_else(|e| e.into_inner()) = before;
    (out, ended)
}

/// Start the run's provenance with its command line (the CLI calls this once, first).
pub fn set_session(p: Provenance) {
    *SESSION.lock().unwrap_or_else(|e| e.into_inner()) = Some(p);
}

/// Add an input file to the run's provenance (hashing it); no effect before [`set_session`].
pub fn add_input(path: &Path) {
    if let Some(p) = SESSION.lock().unwrap_or_else(|e| e.into_inner()).as_mut() {
        p.add_input(path);
    }
}

/// [`add_input`] for several files, in the order given. They are hashed in the background
/// (on as many threads as there are cores) while the command reads and computes, and
/// [`current`] waits for the hashes: hashing 256 MB of frames before a catalog's work was a
/// fifth of its time, and the work it overlaps reads the same files anyway.
pub fn add_inputs(paths: &[&Path]) {
    let files = register(paths);
    if files.is_empty() {
        return;
    }
    let worker = std::thread::spawn(move || {
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get()).min(files.len()).max(1);
        let chunk = files.len().div_ceil(threads);
        std::thread::scope(|sc| {
            let parts: Vec<_> = files
                .chunks(chunk)
                .map(|c| {
                    sc.spawn(move || {
                        c.iter()
                            .map(|(n, p)| (n.clone(), hash_file(p).unwrap_or_else(|_| "unreadable".into())))
                            .collect::<Vec<_>>()
                    })
                })
                .collect();
            parts.into_iter().flat_map(|h| h.join().unwrap_or_default()).collect()
        })
    });
    PENDING.lock().unwrap_or_else(|e| e.into_inner()).push(worker);
}

/// [`add_inputs`] for files the command itself reads whole and in order: each gets its place
/// in the inputs now and its hash from [`record_hash`] as the command reads it (one read of
/// the file instead of two); a file not recorded by the time the provenance is read is hashed
/// then, so the provenance is the same either way.
pub fn add_inputs_read_in_order(paths: &[&Path]) {
    register(paths);
}

/// Give each of `paths` not yet among the session's inputs its place in their order, its hash
/// to come; returns those (name and path). Nothing before [`set_session`].
fn register(paths: &[&Path]) -> Vec<(String, std::path::PathBuf)> {
    let mut fresh = Vec::new();
    if let Some(p) = SESSION.lock().unwrap_or_else(|e| e.into_inner()).as_mut() {
        for path in paths {
            let name = path.display().to_string();
            if !p.inputs.iter().any(|i| i.path == name) {
                p.inputs.push(InputFile { path: name.clone(), hash: String::new() });
                fresh.push((name, path.to_path_buf()));
            }
        }
    }
    fresh
}

/// The hash of an input registered by [`add_inputs_read_in_order`], computed by its reader
/// ([`StreamHash`]); no effect for a path not waiting for one.
pub fn record_hash(path: &Path, hash: String) {
    fill(&path.display().to_string(), hash);
}

/// Write `hash` into the input named `name` if it still waits for its hash.
fn fill(name: &str, hash: String) {
    if let Some(p) = SESSION.lock().unwrap_or_else(|e| e.into_inner()).as_mut() {
        if let Some(i) = p.inputs.iter_mut().find(|i| i.path == name && i.hash.is_empty()) {
            i.hash = hash;
        }
    }
}

/// True when the run's provenance waits for `path`'s hash from its reader.
pub fn wants_hash(path: &Path) -> bool {
    let name = path.display().to_string();
    SESSION
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .as_ref()
        .is_some_and(|p| p.inputs.iter().any(|i| i.path == name && i.hash.is_empty()))
}

/// A file's hash fed piece by piece as it is read (`blake3:<hex>`, as [`hash_file`]).
#[derive(Default)]
pub struct StreamHash(blake3::Hasher);

impl StreamHash {
    pub fn update(&mut self, bytes: &[u8]) {
        self.0.update(bytes);
    }
    pub fn finish(self) -> String {
        label(&self.0.finalize())
    }
}

/// Hashes being computed by [`add_inputs`].
type Hashes = Vec<(String, String)>;
static PENDING: Mutex<Vec<std::thread::JoinHandle<Hashes>>> = Mutex::new(Vec::new());

/// Wait for the background hashes and write them into the session's inputs.
fn settle() {
    let workers: Vec<_> = std::mem::take(&mut *PENDING.lock().unwrap_or_else(|e| e.into_inner()));
    for w in workers {
        for (path, hash) in w.join().unwrap_or_default() {
            fill(&path, hash);
        }
    }
    // Every worker has answered: a hash still missing (a file its reader did not read whole,
    // a worker that failed) is computed now, or the file said unreadable.
    let missing: Vec<String> = SESSION
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .as_ref()
        .map(|p| p.inputs.iter().filter(|i| i.hash.is_empty()).map(|i| i.path.clone()).collect())
        .unwrap_or_default();
    for path in missing {
        fill(&path, hash_file(Path::new(&path)).unwrap_or_else(|_| "unreadable".into()));
    }
}

/// Record the run's instrument; no effect before [`set_session`].
pub fn set_instrument(name: &str, definition: &[u8]) {
    if let Some(p) = SESSION.lock().unwrap_or_else(|e| e.into_inner()).as_mut() {
        p.set_instrument(name, definition);
    }
}

/// The run's provenance, or a fresh one (program, version, date) when none was set.
pub fn current() -> Provenance {
    settle();
    SESSION.lock().unwrap_or_else(|e| e.into_inner()).clone().unwrap_or_default()
}

/// Stamp the run's provenance ([`current`]) into the primary header of `f`: every FITS writer
/// of the workspace calls this before closing its file.
pub fn stamp(f: &mut fitsio::FitsFile) -> Result<(), String> {
    let ph = f.primary_hdu().map_err(|e| e.to_string())?;
    current().write_fits(f, &ph)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A scoped run records its own command and inputs (the BLAKE3 team's vector of "abc"),
    /// tags its temporaries with its tag, and leaves no session behind: after it, the
    /// provenance is the default one again and temporaries are untagged.
    #[test]
    fn a_scoped_run_has_its_own_provenance_and_tag() {
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("a.txt");
        std::fs::write(&input, b"abc").unwrap();
        let name = |t: tempfile::NamedTempFile| t.path().file_name().unwrap().to_string_lossy().to_string();
        let (temp, p) = scoped(Provenance::new("instpol reduce a.txt"), Some("reduce-1"), || {
            add_input(&input);
            name(crate::fits::temp_beside(&dir.path().join("m.fits"), ".tmp").unwrap())
        });
        assert!(temp.starts_with(".instpol-reduce-1."), "{temp}");
        assert_eq!(p.command_line, "instpol reduce a.txt");
        let want = "blake3:6437b3ac38465133ffb63b75273a8db548c558465d79db03fd359c6cd5bd9d85";
        assert_eq!(p.inputs, vec![InputFile { path: input.display().to_string(), hash: want.into() }]);
        assert!(current().command_line.is_empty() && current().inputs.is_empty());
        if std::env::var(crate::fits::TEMP_TAG_ENV).is_err() {
            let after = name(crate::fits::temp_beside(&dir.path().join("m.fits"), ".tmp").unwrap());
            assert!(!after.starts_with(".instpol-reduce-1."), "{after}");
        }
    }

    #[test]
    fn blake3_of_known_vectors() {
        // The BLAKE3 team's test vectors (test_vectors.json: input byte i is i mod 251), checked
        // with Python's `blake3` package, a separate implementation, as were "abc" and "".
        let input = |n: usize| (0..n).map(|i| (i % 251) as u8).collect::<Vec<u8>>();
        assert_eq!(hash_hex(b""), "blake3:af1349b9f5f9a1a6a0404dea36dcc9499bcb25c9adc112b7cc9a93cae41f3262");
        assert_eq!(hash_hex(b"abc"), "blake3:6437b3ac38465133ffb63b75273a8db548c558465d79db03fd359c6cd5bd9d85");
        assert_eq!(hash_hex(&input(1025)), "blake3:d00278ae47eb27b34faecf67b4fe263f82d5412916c1ffd97c8cb7fb814b8444");
        // 31 chunks: several tree levels, and the streamed form (pieces not on chunk bounds).
        let big = input(31744);
        let want = "blake3:62b6960e1a44bcc1eb1a611a8d6235b6b4b78f32e7abc4fb4c6cdcce94895c47";
        assert_eq!(hash_hex(&big), want);
        let mut h = StreamHash::default();
        for piece in big.chunks(1000) {
            h.update(piece);
        }
        assert_eq!(h.finish(), want);
    }

    /// A product in the celestial frame says it (`FRAME = 'celestial'` with `SKYPA`) and is
    /// read back as that frame; `SKYPA` without that frame, or that frame without `SKYPA`, is
    /// refused naming what is missing.
    #[test]
    fn the_celestial_frame_goes_through_the_keywords() {
        let frame = mueller::Frame::Celestial { zero_angle_deg: 2.5, position_angle_deg: -142.0 };
        let p = Product {
            at_plate: Some(false),
            zero_angle_deg: Some(2.5),
            position_angle_deg: Some(-142.0),
            ..Default::default()
        };
        let pairs = p.pairs();
        assert!(
            pairs.contains(&("FRAME".into(), "celestial".into())) && pairs.contains(&("SKYPA".into(), "-142.0".into()))
        );
        let back = Product::from_pairs(pairs.iter().map(|(k, v)| (k.as_str(), v.as_str()))).unwrap().unwrap();
        assert_eq!(back.frame(), Some(frame));
        let e = Product::from_pairs([("FRAME", "celestial"), ("HWPZERO", "0")]).unwrap_err();
        assert!(e.contains("without SKYPA"), "{e}");
        let e = Product::from_pairs([("FRAME", "sky"), ("HWPZERO", "0"), ("SKYPA", "3")]).unwrap_err();
        assert!(e.contains("SKYPA"), "{e}");
    }

    #[test]
    fn iso_dates_at_known_epochs() {
        assert_eq!(iso_utc(0), "1970-01-01T00:00:00");
        // 2000-02-29 (a leap day in a century leap year): 951782400 s (POSIX date -d).
        assert_eq!(iso_utc(951_782_400 + 3661), "2000-02-29T01:01:01");
        // 2100 is not a leap year: 2100-03-01 is 4107542400 s.
        assert_eq!(iso_utc(4_107_542_400 - 1), "2100-02-28T23:59:59");
        assert_eq!(iso_utc(-1), "1969-12-31T23:59:59");
    }

    #[test]
    fn history_lines_fit_a_card_and_keep_every_character() {
        let mut p = Provenance::new(&format!("instpol reduce {}", "frames/very_long_name_".repeat(8)));
        p.set_instrument("fors1", b"abc");
        let lines = p.history_lines();
        assert!(lines.iter().all(|l| l.len() <= 70), "{lines:?}");
        let joined: String = lines.iter().map(|l| l.strip_prefix("  ").unwrap_or(l)).collect();
        assert!(joined.contains(&p.command_line));
        assert!(joined.contains("instrument: fors1 blake3:6437b3ac"));
    }

    /// The citation says what `CITATION.cff` says of the paper (its title, journal, volume,
    /// issue, pages, year and DOI, each read from the file) and of the software (title and
    /// version), so that the two cannot drift apart.
    #[test]
    fn citation_agrees_with_citation_cff() {
        let cff = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../../CITATION.cff")).unwrap();
        let field = |indent: &str, key: &str| -> String {
            let line = cff
                .lines()
                .find(|l| l.starts_with(&format!("{indent}{key}:")))
                .unwrap_or_else(|| panic!("CITATION.cff has no '{indent}{key}:'"));
            line.split_once(':').unwrap().1.trim().trim_matches('"').to_string()
        };
        let c = citation();
        let paper = "    ";
        for key in ["title", "journal", "doi", "year", "volume"] {
            let v = field(paper, key);
            assert!(c.contains(&v), "the citation lacks the paper's {key} '{v}' of CITATION.cff");
        }
        let (start, end) = (field(paper, "start"), field(paper, "end"));
        assert!(c.contains(&format!("pages   = {{{start}--{end}}}")), "pages {start}--{end}");
        assert!(c.contains(&format!("number  = {{{}}}", field(paper, "issue"))));
        assert!(c.contains(&field("", "title")), "the software's title");
        assert_eq!(field("", "version"), env!("CARGO_PKG_VERSION"), "CITATION.cff's version");
        assert!(c.contains(&format!("version = {{{}}}", env!("CARGO_PKG_VERSION"))));
        assert!(c.contains("PASP 118, 146") && !c.contains("VERSION"));
    }
}
