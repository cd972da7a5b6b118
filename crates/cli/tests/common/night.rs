//! Archive nights written by `instpol simulate` for a FORS2 shrunk to 160 x 216 px
//! (tests/data/night/tiny_fors2.toml): archive-like file names and ESO DPR keywords through the
//! scene's `[output]`, for the night tests (night.rs) and the hostile-input generator (its
//! `scan`, `run` and `trend` invocations).

use std::path::{Path, PathBuf};

/// The shrunk FORS2's instrument file.
pub fn tiny_fors2() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/night/tiny_fors2.toml")
}

/// One observation block of a night: its folder under `raw/`, filter, HWP angles, start, first
/// exposure number, DPR category/type/technique, target name and pointing, sky, stars.
pub struct Spec<'a> {
    pub dir: &'a str,
    pub filter: &'a str,
    pub angles: Vec<f64>,
    pub start_mjd: f64,
    pub first_exp: i64,
    pub dpr: [&'a str; 3],
    pub target: &'a str,
    pub ra_dec: (f64, f64),
    pub sky: Option<(f64, f64, f64)>,
    /// x, y (px), flux (e-), p, chi (deg)
    pub stars: Vec<(f64, f64, f64, f64, f64)>,
    pub instrume: Option<&'a str>,
    pub seed: u64,
}

impl<'a> Spec<'a> {
    /// Bias frames of the night (ESO DPR CALIB/BIAS/IMAGE, exposure numbers from 1), one per
    /// entry of `angles` (a bias has no plate angle of its own: it only numbers the frames).
    pub fn bias(angles: Vec<f64>, start_mjd: f64, seed: u64) -> Self {
        Spec {
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
        Spec {
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
}

/// `s` through the instrument file `instrument`, its field's radial pattern (percent), and
/// `extra` scene text (a `[telescope]` section) at the end.
pub fn simulate_scene(root: &Path, s: &Spec, instrument: &Path, pattern: [f64; 4], extra: &str) {
    let mut t = format!(
        "instrument = {:?}\nfilter = {:?}\nhwp_angles_deg = {:?}\nexposure_s = 30\nseed = {}\n",
        instrument.display().to_string(),
        s.filter,
        s.angles,
        s.seed
    );
    if let Some((b, p, chi)) = s.sky {
        t += &format!("[sky]\nbrightness_e = {b}\np = {p}\nchi_deg = {chi}\n");
    }
    for (x, y, f, p, chi) in &s.stars {
        t += &format!(
            "[[stars]]\nx = {x}\ny = {y}\ncoords = \"pixel\"\nflux_e = {f}\np = {p}\nchi_deg = {chi}\nfwhm_arcsec = 2.5\n"
        );
    }
    t += &format!(
        "[output]\narchive = {{ start_mjd = {}, cadence_s = 60 }}\nfirst_exposure_no = {}\n",
        s.start_mjd, s.first_exp
    );
    t += &format!(
        "[output.keywords]\n\"HIERARCH ESO DPR CATG\" = {:?}\n\"HIERARCH ESO DPR TYPE\" = {:?}\n\"HIERARCH ESO DPR TECH\" = {:?}\n\"HIERARCH ESO OBS TARG NAME\" = {:?}\nRA = {}\nDEC = {}\n",
        s.dpr[0], s.dpr[1], s.dpr[2], s.target, s.ra_dec.0, s.ra_dec.1
    );
    if let Some(i) = s.instrume {
        t += &format!("INSTRUME = {i:?}\n");
    }
    t += &format!(
        "[effects]\nphoton_noise = true\nread_noise = true\ninstpol = {{ kind = \"radial\", coeffs_percent = {pattern:?} }}\n"
    );
    t += extra;
    let scene = root.join(format!("{}.toml", s.dir));
    std::fs::write(&scene, t).unwrap();
    let out = root.join("raw").join(s.dir);
    let o =
        super::instpol().args(["simulate", scene.to_str().unwrap(), "--out", out.to_str().unwrap()]).output().unwrap();
    assert!(o.status.success(), "simulate {}: {}", s.dir, String::from_utf8_lossy(&o.stderr));
}
