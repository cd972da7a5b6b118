//! A night of archive frames, simulated: observation blocks ([`Block`]: bias frames, sky
//! flats, empty fields, standards, targets) each written as a scene with archive-like file
//! names and ESO DPR keywords (the scene's `[output]`) and simulated into `raw/<block>/`, for
//! the shrunk FORS2 of `instruments/tiny_fors2.toml` (160 x 216 px, two chips), so that a night
//! of about a hundred exposures is written and run in seconds.
//!
//! [`archive_night`] is the night `instpol simulate --night` writes and `docs/nights.md` walks
//! through (`instpol scan`, `run`, `trend`, `report`); the night tests
//! (`crates/cli/tests/it/night.rs`) write the same blocks through [`Block::simulate`], and
//! nights of their own.

use crate::{Error, Plan, Scene, Simulated};
use std::path::{Path, PathBuf};

/// The shrunk FORS2's instrument file (`instruments/tiny_fors2.toml`).
pub const TINY_FORS2: &str = include_str!("../../../instruments/tiny_fors2.toml");

/// The file name [`write_archive_night`] gives the instrument file in the night's folder.
pub const INSTRUMENT_FILE: &str = "tiny_fors2.toml";

/// The night's date: MJD 58546 is 2019-03-04.
pub const NIGHT_MJD: f64 = 58546.0;

/// The instrument's radial pattern in every frame of [`archive_night`] (percent, the
/// coefficients of powers 0 to 3 of the distance from the centre in arcmin).
pub const PATTERN_PERCENT: [f64; 4] = [0.0, 0.1, 0.3, 0.05];

/// The HWP angles of one cycle of four (deg).
pub const Q4: [f64; 4] = [0.0, 22.5, 45.0, 67.5];

/// Right ascension and declination (deg) of the standards of `instruments/standards.toml` the
/// night observes.
pub const HD110984: (f64, f64) = ((12.0 + 46.0 / 60.0 + 44.9 / 3600.0) * 15.0, -(61.0 + 11.0 / 60.0 + 11.0 / 3600.0));
pub const HD14069: (f64, f64) = ((2.0 + 16.0 / 60.0 + 45.16 / 3600.0) * 15.0, 7.0 + 41.0 / 60.0 + 11.1 / 3600.0);
pub const HD64299: (f64, f64) = ((7.0 + 52.0 / 60.0 + 25.55 / 3600.0) * 15.0, -(23.0 + 17.0 / 60.0 + 45.9 / 3600.0));
pub const HD161056: (f64, f64) = ((17.0 + 43.0 / 60.0 + 47.0 / 3600.0) * 15.0, -(7.0 + 4.0 / 60.0 + 47.0 / 3600.0));

/// The sky fields of [`archive_night`]: target, sky `P` (percent) and `chi` (deg), as
/// `instpol scan --sky` and `--sky-table` take them.
pub const SKY_FIELDS: [(&str, f64, f64); 4] =
    [("EMPTY-V1", 1.74, -53.8), ("EMPTY-V2", 1.74, -53.8), ("EMPTY-I1", 1.74, -53.8), ("EMPTY-I2", 1.74, -53.8)];

/// One observation block of a night: its folder under `raw/`, filter, HWP angles (deg), start
/// (MJD), first exposure number, DPR category/type/technique, target name and pointing (deg),
/// sky (`brightness_e`, `p`, `chi_deg`), stars, another instrument's name when not the
/// instrument file's, and the scene's seed.
#[derive(Debug, Clone)]
pub struct Block<'a> {
    pub dir: &'a str,
    pub filter: &'a str,
    pub angles: Vec<f64>,
    pub start_mjd: f64,
    pub first_exp: i64,
    pub dpr: [&'a str; 3],
    pub target: &'a str,
    pub ra_dec: (f64, f64),
    pub sky: Option<(f64, f64, f64)>,
    /// x, y (px), flux (e-), p (fraction), chi (deg)
    pub stars: Vec<(f64, f64, f64, f64, f64)>,
    pub instrume: Option<&'a str>,
    pub seed: u64,
}

impl<'a> Block<'a> {
    /// Bias frames of the night (ESO DPR CALIB/BIAS/IMAGE, exposure numbers from 1), one per
    /// entry of `angles` (a bias has no plate angle of its own: it only numbers the frames).
    pub fn bias(angles: Vec<f64>, start_mjd: f64, seed: u64) -> Self {
        Block {
            dir: "bias",
            filter: "v_HIGH",
            angles,
            start_mjd,
            first_exp: 1,
            dpr: ["CALIB", "BIAS", "IMAGE"],
            target: "BIAS",
            ra_dec: (0.0, 0.0),
            sky: None,
            stars: vec![],
            instrume: None,
            seed,
        }
    }

    /// Sky flats in `filter` (CALIB/FLAT,SKY/IMAGE, an unpolarized 20000 e- sky) into `dir`.
    pub fn sky_flat(
        dir: &'a str,
        filter: &'a str,
        angles: Vec<f64>,
        start_mjd: f64,
        first_exp: i64,
        seed: u64,
    ) -> Self {
        Block {
            dir,
            filter,
            angles,
            start_mjd,
            first_exp,
            dpr: ["CALIB", "FLAT,SKY", "IMAGE"],
            target: "FLAT",
            ra_dec: (0.0, 0.0),
            sky: Some((20000.0, 0.0, 0.0)),
            stars: vec![],
            instrume: None,
            seed,
        }
    }

    /// The block as scene TOML: through the instrument file `instrument`, its field's radial
    /// pattern `pattern` (percent), photon and read noise, 30 s exposures a minute apart, and
    /// `extra` scene text (a `[telescope]` section) at the end.
    pub fn scene_text(&self, instrument: &Path, pattern: [f64; 4], extra: &str) -> String {
        let mut t = format!(
            "instrument = {:?}\nfilter = {:?}\nhwp_angles_deg = {:?}\nexposure_s = 30\nseed = {}\n",
            instrument.display().to_string(),
            self.filter,
            self.angles,
            self.seed
        );
        if let Some((b, p, chi)) = self.sky {
            t += &format!("[sky]\nbrightness_e = {b}\np = {p}\nchi_deg = {chi}\n");
        }
        for (x, y, f, p, chi) in &self.stars {
            t += &format!(
                "[[stars]]\nx = {x}\ny = {y}\ncoords = \"pixel\"\nflux_e = {f}\np = {p}\nchi_deg = {chi}\nfwhm_arcsec = 2.5\n"
            );
        }
        t += &format!(
            "[output]\narchive = {{ start_mjd = {}, cadence_s = 60 }}\nfirst_exposure_no = {}\n",
            self.start_mjd, self.first_exp
        );
        t += &format!(
            "[output.keywords]\n\"HIERARCH ESO DPR CATG\" = {:?}\n\"HIERARCH ESO DPR TYPE\" = {:?}\n\"HIERARCH ESO DPR TECH\" = {:?}\n\"HIERARCH ESO OBS TARG NAME\" = {:?}\nRA = {}\nDEC = {}\n",
            self.dpr[0], self.dpr[1], self.dpr[2], self.target, self.ra_dec.0, self.ra_dec.1
        );
        if let Some(i) = self.instrume {
            t += &format!("INSTRUME = {i:?}\n");
        }
        t += &format!(
            "[effects]\nphoton_noise = true\nread_noise = true\ninstpol = {{ kind = \"radial\", coeffs_percent = {pattern:?} }}\n"
        );
        t + extra
    }

    /// Write the block's scene ([`Block::scene_text`]) to `root/<dir>.toml` and simulate it
    /// into `root/raw/<dir>/`, as `instpol simulate SCENE --out DIR` does.
    pub fn simulate(&self, root: &Path, instrument: &Path, pattern: [f64; 4], extra: &str) -> Result<Simulated, Error> {
        let path = root.join(format!("{}.toml", self.dir));
        let text = self.scene_text(instrument, pattern, extra);
        write_text(&path, &text)?;
        let scene = Scene::from_toml_str(&text, &path)?;
        Plan::build(&scene)?.write(&root.join("raw").join(self.dir), &|| ())
    }
}

/// Write `text` to `path` durably (a temporary beside it, fsynced, renamed:
/// `skyfield::durable`).
fn write_text(path: &Path, text: &str) -> Result<(), Error> {
    let err = |e: std::io::Error| Error::File { path: path.into(), message: format!("cannot write: {e}") };
    let mut tmp = skyfield::fits::temp_beside(path, ".tmp").map_err(err)?;
    std::io::Write::write_all(&mut tmp, text.as_bytes()).map_err(err)?;
    skyfield::durable::finish(tmp.into_temp_path(), path).map_err(err)
}

/// An archive night of the shrunk FORS2 (MJD [`NIGHT_MJD`]): 5 bias frames, 5 sky flats in
/// each of v_HIGH and I_BESS, 2 empty fields per filter (the [`SKY_FIELDS`], sky polarization
/// 1.74 % at -53.8 deg), 2 polarized standards in v_HIGH (HD 110984, and HD 161056 named
/// `STD-2` by its headers, to be matched by position) and an unpolarized one in each filter
/// (HD 14069, HD 64299), each star 50 px below the pointing; a target (NGC 1234: three stars
/// of 2 %, 1 % and 0 %) at 16 angles observed twice, an aborted set of 3 angles, and 4
/// exposures of another instrument (HAWKI).
pub fn archive_night() -> Vec<Block<'static>> {
    let night = NIGHT_MJD;
    let std_pointing = |(ra, dec): (f64, f64)| (ra, dec + 50.0 / 3600.0); // the star 50 px below the centre
    let mut blocks = vec![Block::bias(vec![0.0, 22.5, 45.0, 67.5, 90.0], night + 0.80, 1)];
    for (k, f) in ["v_HIGH", "I_BESS"].into_iter().enumerate() {
        blocks.push(Block::sky_flat(
            ["flat_v", "flat_i"][k],
            f,
            vec![0.0, 22.5, 45.0, 67.5, 90.0],
            night + 0.81 + 0.005 * k as f64,
            11 + 10 * k as i64,
            2 + k as u64,
        ));
    }
    let filters = ["v_HIGH", "v_HIGH", "I_BESS", "I_BESS"];
    for (k, (name, p, chi)) in SKY_FIELDS.into_iter().enumerate() {
        blocks.push(Block {
            dir: ["ev1", "ev2", "ei1", "ei2"][k],
            filter: filters[k],
            angles: Q4.to_vec(),
            start_mjd: night + 0.83 + 0.01 * k as f64,
            first_exp: 31 + 10 * k as i64,
            dpr: ["SCIENCE", "OBJECT", "POLARIMETRY"],
            target: name,
            ra_dec: (150.0 + 10.0 * k as f64, -30.0),
            sky: Some((3000.0, p / 100.0, chi)),
            stars: vec![],
            instrume: None,
            seed: 10 + k as u64,
        });
    }
    let star = |p: f64, chi: f64| vec![(79.5, 57.5, 4e5, p, chi)];
    let standards = [
        ("std1", "v_HIGH", "HD110984", HD110984, star(0.057, 91.65)),
        ("std2", "v_HIGH", "STD-2", HD161056, star(0.0403, 66.93)),
        ("std3", "v_HIGH", "HD 14069", HD14069, star(0.0, 0.0)),
        ("std4", "I_BESS", "HD64299", HD64299, star(0.0, 0.0)),
    ];
    for (k, (dir, filter, target, pos, stars)) in standards.into_iter().enumerate() {
        blocks.push(Block {
            dir,
            filter,
            angles: Q4.to_vec(),
            start_mjd: night + 0.87 + 0.01 * k as f64,
            first_exp: 71 + 10 * k as i64,
            dpr: ["CALIB", "STD", "POLARIMETRY"],
            target,
            ra_dec: std_pointing(pos),
            sky: Some((300.0, 0.0, 0.0)),
            stars,
            instrume: None,
            seed: 20 + k as u64,
        });
    }
    let angles16: Vec<f64> = (0..16).map(|i| i as f64 * 22.5).collect();
    let field = vec![(40.0, 33.5, 2e5, 0.02, 30.0), (110.0, 130.5, 3e5, 0.01, 120.0), (60.0, 178.0, 1e5, 0.0, 0.0)];
    // The cycle of 16 angles and its repeat, 16 min later; an aborted set; another instrument.
    let later = [
        ("target", angles16.clone(), night + 0.91, 111, "NGC 1234", (49.0, -20.0), field.clone(), None, 30),
        ("target_again", angles16, night + 0.9212, 127, "NGC 1234", (49.0, -20.0), field.clone(), None, 33),
        ("aborted", vec![0.0, 22.5, 45.0], night + 0.95, 151, "NGC 5678", (51.0, -21.0), field, None, 31),
        ("hawki", Q4.to_vec(), night + 0.96, 161, "X", (52.0, -21.0), vec![], Some("HAWKI"), 32),
    ];
    for (dir, angles, start_mjd, first_exp, target, ra_dec, stars, instrume, seed) in later {
        blocks.push(Block {
            dir,
            filter: "v_HIGH",
            angles,
            start_mjd,
            first_exp,
            dpr: ["SCIENCE", "OBJECT", "POLARIMETRY"],
            target,
            ra_dec,
            sky: Some((500.0, 0.0, 0.0)),
            stars,
            instrume,
            seed,
        });
    }
    blocks
}

/// What [`write_archive_night`] wrote.
#[derive(Debug, Clone, serde::Serialize)]
pub struct WrittenNight {
    /// The instrument file (`DIR/tiny_fors2.toml`), for `instpol scan --instrument`.
    pub instrument: PathBuf,
    /// The folder of raw frames (`DIR/raw`), for `instpol scan`.
    pub raw: PathBuf,
    /// The sky fields as `instpol scan --sky-table` reads them (`DIR/skies.csv`).
    pub sky_table: PathBuf,
    /// One scene file per block (`DIR/<block>.toml`).
    pub scenes: Vec<PathBuf>,
    /// Every frame file written (chip files), and the blocks' truth files.
    pub frames: Vec<PathBuf>,
    pub truths: Vec<PathBuf>,
}

/// Write [`archive_night`] into `dir`: the instrument file, one scene per block, the frames
/// under `raw/` and the sky-field table (module docs). `dir` must be empty or absent: a
/// night's folder is written whole, never into another night.
pub fn write_archive_night(dir: &Path) -> Result<WrittenNight, Error> {
    let err = |message: String| Error::File { path: dir.into(), message };
    if let Ok(mut entries) = std::fs::read_dir(dir) {
        if entries.next().is_some() {
            return Err(err("is not empty: a simulated night is written into a new or empty folder".into()));
        }
    } else if dir.exists() {
        return Err(err("is not a folder".into()));
    }
    let existed = dir.exists();
    std::fs::create_dir_all(dir).map_err(|e| err(format!("cannot create: {e}")))?;
    let written = write_into(dir);
    if written.is_err() {
        // The folder was empty or absent: a failed night (a full disk at frame 90) leaves
        // nothing that looks like a night to the next command.
        for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
            let p = e.path();
            let _ = if p.is_dir() { std::fs::remove_dir_all(&p) } else { std::fs::remove_file(&p) };
        }
        if !existed {
            let _ = std::fs::remove_dir(dir);
        }
    }
    written
}

/// The files of [`write_archive_night`] into the existing folder `dir`.
fn write_into(dir: &Path) -> Result<WrittenNight, Error> {
    let instrument = dir.join(INSTRUMENT_FILE);
    write_text(&instrument, TINY_FORS2)?;
    let mut table = String::from("target,p_percent,chi_deg\n");
    for (t, p, chi) in SKY_FIELDS {
        table += &format!("{t},{p},{chi}\n");
    }
    let sky_table = dir.join("skies.csv");
    write_text(&sky_table, &table)?;
    let (mut scenes, mut frames, mut truths) = (vec![], vec![], vec![]);
    for b in archive_night() {
        let s = b.simulate(dir, &instrument, PATTERN_PERCENT, "")?;
        scenes.push(dir.join(format!("{}.toml", b.dir)));
        frames.extend(s.frames);
        truths.push(s.truth);
    }
    Ok(WrittenNight { instrument, raw: dir.join("raw"), sky_table, scenes, frames, truths })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every block of the night is a valid scene of the shrunk FORS2, and no two blocks share a
    /// folder, an exposure number or a minute of the night (the archive names are the start
    /// times, one exposure a minute: two blocks at one time would write one file twice).
    #[test]
    fn the_archive_nights_blocks_are_valid_scenes_apart_in_numbers_and_time() {
        let dir = tempfile::tempdir().unwrap();
        let inst = dir.path().join(INSTRUMENT_FILE);
        std::fs::write(&inst, TINY_FORS2).unwrap();
        let blocks = archive_night();
        let mut exposures = std::collections::BTreeSet::new();
        let mut minutes = std::collections::BTreeSet::new();
        let mut dirs = std::collections::BTreeSet::new();
        for b in &blocks {
            let path = dir.path().join(format!("{}.toml", b.dir));
            Scene::from_toml_str(&b.scene_text(&inst, PATTERN_PERCENT, ""), &path).unwrap();
            assert!(dirs.insert(b.dir), "{} twice", b.dir);
            for k in 0..b.angles.len() as i64 {
                assert!(exposures.insert(b.first_exp + k), "{}: exposure {} twice", b.dir, b.first_exp + k);
                let minute = ((b.start_mjd - NIGHT_MJD) * 1440.0).round() as i64 + k;
                assert!(minutes.insert(minute), "{}: minute {minute} of the night twice", b.dir);
            }
        }
        assert_eq!(blocks.len(), 15);
    }
}
