//! A night on a Nasmyth instrument at the level of pixel frames: scenes with
//! a `[telescope]` (an aluminium M3 of known factor and offset, La Silla, each exposure's
//! hour angles) simulated by `instpol simulate`; the frames' headers carry the parallactic
//! angles under the instrument's keywords. Standards measured from the frames (`instpol
//! photometry`, angles from the headers) give the mirror back through `instpol
//! fit-standards`; a sky-field set of frames gives the paper's field pattern back through
//! `instpol calibrate` once the sky is passed through the fitted telescope, and a wrong one
//! when it is not.

use crate::common;

use common::{fits_in, instpol};
use std::path::{Path, PathBuf};

const TELESCOPE: &str = r#"
[telescope]
focus = "nasmyth"
site_latitude_deg = -29.26
parang_start_keyword = "HIERARCH ESO TEL PARANG START"
parang_end_keyword = "HIERARCH ESO TEL PARANG END"
rotator_keyword = "HIERARCH ESO ADA POSANG"

[[telescope.mirrors]]
name = "M3"
metal = "aluminium"
aoi_deg = 45.0
"#;

/// The truth: Wiersema factor and offset (deg) of the simulated M3.
const FACTOR: f64 = 0.86;
const OFFSET_DEG: f64 = 40.0;

/// The instrument file `inst` with its own `[telescope]` tables (FORS1: Cassegrain) replaced
/// by the Nasmyth one above.
fn with_telescope(inst: &Path) -> PathBuf {
    let mut text = String::new();
    let mut skip = false;
    for line in std::fs::read_to_string(inst).unwrap().lines() {
        let t = line.trim_start();
        if t.starts_with('[') {
            skip = t.starts_with("[telescope") || t.starts_with("[[telescope");
        }
        if !skip {
            text += line;
            text.push('\n');
        }
    }
    let text = text + TELESCOPE;
    let p = inst.with_file_name("nasmyth.toml");
    std::fs::write(&p, text).unwrap();
    p
}

fn simulate(scene: &str, dir: &Path, name: &str) -> Vec<PathBuf> {
    let s = dir.join(format!("{name}.toml"));
    std::fs::write(&s, scene).unwrap();
    let out = dir.join(name);
    let o = instpol().arg("simulate").arg(&s).arg("--out").arg(&out).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    fits_in(&out)
}

/// A header keyword as a number, read here with fitsio (not with the library under test).
fn key(path: &Path, k: &str) -> f64 {
    let mut f = fitsio::FitsFile::open(path).unwrap();
    let h = f.primary_hdu().unwrap();
    h.read_key::<f64>(&mut f, k).unwrap_or_else(|e| panic!("{}: {k}: {e}", path.display()))
}

/// The set's mean parallactic angle (deg) from the headers: the middle of the first start and
/// the last end.
fn set_angle(frames: &[PathBuf]) -> f64 {
    let a = key(&frames[0], "HIERARCH ESO TEL PARANG START");
    let b = key(frames.last().unwrap(), "HIERARCH ESO TEL PARANG END");
    let b = a + (b - a + 540.0).rem_euclid(360.0) - 180.0;
    0.5 * (a + b)
}

#[test]
fn frames_of_a_night_give_the_mirror_and_the_field_back() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();

    // --- standards: unpolarized stars through the night (128 px, 0.2"/px) ---
    let tiny = with_telescope(&common::tiny_fors1(d, 12.0, 4));
    let lambda_um =
        instrument::Instrument::load(tiny.to_str().unwrap()).unwrap().filter("V").unwrap().lambda_eff_nm / 1000.0;
    let mut csv = String::from("star,parallactic_deg,q,sigma_q,u,sigma_u,wavelength_um,filter\n");
    let pointings: [(f64, f64); 12] = [
        (-70.0, -70.0),
        (-70.0, 60.0),
        (-50.0, -45.0),
        (-50.0, 35.0),
        (-10.0, -50.0),
        (-10.0, -15.0),
        (-10.0, 20.0),
        (-10.0, 55.0),
        (10.0, -40.0),
        (10.0, 30.0),
        (-30.0, -60.0),
        (-30.0, 65.0),
    ];
    for (i, &(dec, ha)) in pointings.iter().enumerate() {
        let scene = format!(
            "instrument = {:?}\nfilter = \"V\"\nseed = {}\nexposure_s = 20\n[output]\nbitpix = -64\n\
             [[stars]]\nx = 64\ny = 34\ncoords = \"pixel\"\nflux_e = 4e6\nfwhm_arcsec = 1.6\n\
             [effects]\nphoton_noise = true\n\
             [telescope]\nfactor = {FACTOR}\noffset_deg = {OFFSET_DEG}\ndec_deg = {dec}\nha_start_deg = {ha}\noverhead_s = 5\n",
            tiny.display().to_string(),
            100 + i
        );
        let frames = simulate(&scene, d, &format!("std{i}"));
        assert_eq!(frames.len(), 4);
        // The headers hold the parallactic angle of the truth file, in the instrument's sense.
        let truth: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(frames[0].parent().unwrap().join("truth.json")).unwrap())
                .unwrap();
        let t0 = truth["frames"][0]["parallactic_start_deg"].as_f64().unwrap();
        assert!((key(&frames[0], "HIERARCH ESO TEL PARANG START") - t0).abs() < 1e-9);
        // ... and that angle is the spherical triangle's (closed form, written here):
        // tan q = sin H / (tan(phi) cos(dec) - sin(dec) cos H).
        let (phi, de, h) = (f64::to_radians(-29.26), dec.to_radians(), ha.to_radians());
        let q = h.sin().atan2(phi.tan() * de.cos() - de.sin() * h.cos()).to_degrees();
        assert!((q - t0).abs() < 1e-9, "{q} vs {t0}");
        let o = instpol()
            .arg("photometry")
            .args(&frames)
            .args(["--x", "64", "--y", "34", "--aperture", "10", "--annulus", "14,24", "--json", "--instrument"])
            .arg(&tiny)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        let g = |k: &str| j[k].as_f64().unwrap();
        csv += &format!(
            "S{i},{},{},{},{},{},{lambda_um},V\n",
            set_angle(&frames),
            g("q"),
            g("sigma_q"),
            g("u"),
            g("sigma_u")
        );
    }
    let cat = d.join("standards.csv");
    std::fs::write(&cat, &csv).unwrap();
    let tel = d.join("tel.fits");
    let o = instpol()
        .arg("fit-standards")
        .arg(&cat)
        .args(["--model", "wiersema", "--json", "--instrument"])
        .arg(&tiny)
        .arg("--output")
        .arg(&tel)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let p = |name: &str| {
        let p = j[0]["params"].as_array().unwrap().iter().find(|p| p["name"] == name).unwrap();
        (p["value"].as_f64().unwrap(), p["sigma_value"].as_f64().unwrap())
    };
    let ((fa, sfa), (off, soff)) = (p("factor"), p("offset"));
    eprintln!(
        "frames: factor {fa:.4} +- {sfa:.4} ({FACTOR}), offset {off:.3} +- {soff:.3} deg ({OFFSET_DEG}), chi2/dof {}",
        j[0]["chi2_dof"]
    );
    assert!((fa - FACTOR).abs() < 3.0 * sfa && sfa < 0.05, "factor {fa} +- {sfa}");
    assert!((off - OFFSET_DEG).abs() < 3.0 * soff && soff < 1.0, "offset {off} +- {soff}");
    assert!(j[0]["chi2_dof"].as_f64().unwrap() < 2.5, "{}", j[0]);

    // --- a sky field through the same telescope (512 px of 0.8") ---
    let small = d.join("small.toml");
    std::fs::write(&small, common::SMALL.toml()).unwrap();
    let small = with_telescope(&small);
    let scene = format!(
        "instrument = {:?}\nfilter = \"V\"\nseed = 5\nexposure_s = 20\n[output]\nbitpix = -32\n\
         [sky]\nbrightness_e = 40000.0\np = 0.0174\nchi_deg = -53.8\n\
         [effects]\nphoton_noise = true\n[effects.instpol]\nkind = \"radial\"\ncoeffs_percent = [0.0, 0.012, 0.046, 0.002]\n\
         [telescope]\nfactor = {FACTOR}\noffset_deg = {OFFSET_DEG}\ndec_deg = -40\nha_start_deg = 30\noverhead_s = 5\n",
        small.display().to_string()
    );
    let frames = simulate(&scene, d, "sky");
    // The sky as it reaches the instrument over the set's track, through the FITTED model.
    let fitted = fit::files::calibration::load(&tel).unwrap().telescope.unwrap();
    let it = instrument::Instrument::load(small.to_str().unwrap()).unwrap().telescope.unwrap();
    let track = fit::telescope::cal::frames_track(&frames, &it).unwrap();
    assert!((track.start.to_degrees() - key(&frames[0], "HIERARCH ESO TEL PARANG START")).abs() < 1e-9);
    let chi = f64::to_radians(-53.8);
    let (qs, us) =
        fitted.band("V").unwrap().sky_through(0.0174 * (2.0 * chi).cos(), 0.0174 * (2.0 * chi).sin(), track).unwrap();
    let calibrate = |p: f64, chi_deg: f64, out: &str| -> serde_json::Value {
        let mut c = instpol();
        c.arg("calibrate").args(&frames).arg("--instrument").arg(&small);
        c.args(["--sky-p", &format!("{}", 100.0 * p), "--sky-chi", &format!("{chi_deg}"), "--bin", "8", "--json"]);
        c.arg("--out").arg(d.join(out));
        let o = c.output().unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        serde_json::from_slice(&o.stdout).unwrap()
    };
    let v = [0.012e-2, 0.046e-2, 0.002e-2];
    let j = calibrate(qs.hypot(us), 0.5 * us.atan2(qs).to_degrees(), "cal_tel.fits");
    let c: Vec<f64> = serde_json::from_value(j["coefficients"].clone()).unwrap();
    let e: Vec<f64> = serde_json::from_value(j["sigma_coefficients"].clone()).unwrap();
    eprintln!(
        "sky field, telescope removed: c = {c:?} +- {e:?} (truth {v:?}); sky at the instrument p = {:.4}",
        qs.hypot(us)
    );
    for k in 0..3 {
        assert!(((c[k] - v[k]) / e[k]).abs() < 4.0, "c{} {} +- {} vs {}", k + 1, c[k], e[k], v[k]);
    }
    // Without the telescope term (the sky as catalogued) the pattern is wrong.
    let j = calibrate(0.0174, -53.8, "cal_sky.fits");
    let c: Vec<f64> = serde_json::from_value(j["coefficients"].clone()).unwrap();
    let e: Vec<f64> = serde_json::from_value(j["sigma_coefficients"].clone()).unwrap();
    eprintln!("sky field, telescope ignored: c = {c:?} +- {e:?}, chi2/dof {}", j["chi2_dof"]);
    let worst = (0..3).map(|k| ((c[k] - v[k]) / e[k]).abs()).fold(0.0, f64::max);
    let chi2 = j["chi2_dof"].as_f64().unwrap_or(0.0);
    assert!(worst > 10.0 || chi2 > 10.0, "the field came out right without the telescope: {c:?} {chi2}");
}

/// A telescope calibration of the truth mirror fitted by `instpol fit-standards` to 30
/// standards drawn from the closed form of an unpolarized star through M3 (q = P cos 2(offset -
/// pa), u = -P sin 2(offset - pa), P from the Fresnel reflection of the factor-scaled index)
/// with Gaussian noise of 3e-4.
fn telescope_calibration(d: &Path, inst: &Path) -> PathBuf {
    telescope_calibration_with_noise(d, inst, 3e-4, None)
}

/// [`telescope_calibration`] with standards of Gaussian noise `noise` (their stated errors stay
/// 3e-4), taken at rotator angle `rotator_deg` when given (the model is then fitted with rotator
/// angles; these standards' rotator is not in their q, u, so its offset comes out turned).
fn telescope_calibration_with_noise(d: &Path, inst: &Path, noise: f64, rotator_deg: Option<f64>) -> PathBuf {
    let lambda_um =
        instrument::Instrument::load(inst.to_str().unwrap()).unwrap().filter("V").unwrap().lambda_eff_nm / 1000.0;
    let n = mueller::mirror::MetalTable::builtin("aluminium").unwrap().index(lambda_um).unwrap();
    let p = mueller::mirror::reflect(n * FACTOR, &[], 1000.0 * lambda_um, std::f64::consts::FRAC_PI_4)
        .unwrap()
        .polarization;
    // Gaussian noise (Box-Muller on a 64-bit xorshift; the CLI's tests carry no rand crate).
    let mut state = 0x9E37_79B9_7F4A_7C15u64;
    let mut uniform = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        ((state >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    };
    let mut gauss = move || noise * (-2.0 * uniform().ln()).sqrt() * (std::f64::consts::TAU * uniform()).cos();
    let mut csv = String::from("star,parallactic_deg,q,sigma_q,u,sigma_u,wavelength_um,filter");
    csv += if rotator_deg.is_some() { ",rotator_deg\n" } else { "\n" };
    for k in 0..30 {
        let pa = -170.0 + 11.7 * k as f64;
        let a = 2.0 * (OFFSET_DEG - pa).to_radians();
        csv += &format!("W{k},{pa},{},3e-4,{},3e-4,{lambda_um},V", p * a.cos() + gauss(), -p * a.sin() + gauss());
        csv += &rotator_deg.map_or("\n".to_string(), |r| format!(",{r}\n"));
    }
    let tag = rotator_deg.map_or(String::new(), |r| format!("_rot{r}"));
    let cat = d.join(format!("closed_form{tag}.csv"));
    std::fs::write(&cat, csv).unwrap();
    let tel = d.join(format!("tel_closed{tag}.fits"));
    let o = instpol()
        .arg("fit-standards")
        .arg(&cat)
        .args(["--model", "wiersema", "--instrument"])
        .arg(inst)
        .arg("--output")
        .arg(&tel)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    tel
}

fn validate(cal: &Path, inst: &Path, frames: &[PathBuf], extra: &[&str]) -> (i32, String, String) {
    let o = instpol()
        .arg("validate")
        .arg("--cal")
        .arg(cal)
        .arg("--instrument")
        .arg(inst)
        .args(frames)
        .args(["--x", "64", "--y", "34", "--aperture", "10", "--annulus", "14,24"])
        .args(extra)
        .output()
        .unwrap();
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stdout).into(),
        String::from_utf8_lossy(&o.stderr).into(),
    )
}

#[test]
fn validate_applies_the_telescope_at_the_frames_parallactic_angles() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let tiny = with_telescope(&common::tiny_fors1(d, 12.0, 4));
    let tel = telescope_calibration(d, &tiny);
    let schema: serde_json::Value =
        serde_json::from_str(include_str!("../../../../schemas/validate-telescope.schema.json")).unwrap();
    // One unpolarized standard at two parallactic angles (east and west of the meridian).
    let mut pas = vec![];
    for (i, ha) in [-50.0f64, 40.0].into_iter().enumerate() {
        let scene = format!(
            "instrument = {:?}\nfilter = \"V\"\nseed = {}\nexposure_s = 20\n[output]\nbitpix = -64\n\
             [[stars]]\nx = 64\ny = 34\ncoords = \"pixel\"\nflux_e = 4e6\nfwhm_arcsec = 1.6\n\
             [effects]\nphoton_noise = true\n\
             [telescope]\nfactor = {FACTOR}\noffset_deg = {OFFSET_DEG}\ndec_deg = -10\nha_start_deg = {ha}\noverhead_s = 5\n",
            tiny.display().to_string(),
            300 + i
        );
        let frames = simulate(&scene, d, &format!("val{i}"));
        let (code, out, err) = validate(&tel, &tiny, &frames, &["--json"]);
        assert_eq!(code, 0, "PASS expected at hour angle {ha}: {out} {err}");
        let j: serde_json::Value = serde_json::from_str(&out).unwrap();
        eprintln!(
            "validate at HA {ha}: corrected_pull {} (uncorrected {})",
            j["corrected_pull"], j["uncorrected_pull"]
        );
        // The key set is the schema's, no more, no less.
        let mut keys: Vec<&str> = j.as_object().unwrap().keys().map(|k| k.as_str()).collect();
        let mut want: Vec<&str> = schema["required"].as_array().unwrap().iter().map(|k| k.as_str().unwrap()).collect();
        keys.sort();
        want.sort();
        assert_eq!(keys, want);
        assert_eq!(j["pass"], true);
        // The star showed the mirror's few percent, which the correction removed.
        assert!(j["uncorrected_pull"].as_f64().unwrap() > 20.0, "{j}");
        assert!(j["measured_q"].as_f64().unwrap().hypot(j["measured_u"].as_f64().unwrap()) > 0.02, "{j}");
        let pa = j["parallactic_start_deg"].as_f64().unwrap();
        assert!((pa - key(&frames[0], "HIERARCH ESO TEL PARANG START")).abs() < 1e-9);
        pas.push(pa);
        // A wrong angle (by hand, 45 deg off) fails with exit code 1.
        let (code, _, err) = validate(&tel, &tiny, &frames, &["--parang", &format!("{}", pa + 45.0)]);
        assert_eq!(code, 1, "{err}");
        assert!(err.contains("FAIL"), "{err}");
    }
    assert!((pas[0] - pas[1]).abs() > 60.0, "two different parallactic angles: {pas:?}");

    // Without the telescope model (a field-only calibration: the paper's V field of FORS1)
    // the star fails.
    let field = d.join("field.fits");
    common::fors1_radial_calibration("V", common::V_COEFFS).save(&field).unwrap();
    let frames = fits_in(&d.join("val0"));
    let (code, _, err) = validate(&field, &tiny, &frames, &[]);
    assert_eq!(code, 1, "{err}");

    // Frames without the angle in their headers are refused, naming frame and keyword.
    let scene = format!(
        "instrument = {:?}\nfilter = \"V\"\nseed = 9\n[output]\nbitpix = -64\n\
         [[stars]]\nx = 64\ny = 34\ncoords = \"pixel\"\nflux_e = 4e6\nfwhm_arcsec = 1.6\n",
        tiny.display().to_string()
    );
    let frames = simulate(&scene, d, "noangle");
    let (code, _, err) = validate(&tel, &tiny, &frames, &[]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("HIERARCH ESO TEL PARANG START") && err.contains(&*frames[0].to_string_lossy()), "{err}");
    assert!(err.contains("--parang"), "{err}");
}

#[test]
fn fit_standards_takes_the_mirror_from_the_instrument_and_warns_on_an_override() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // An instrument whose M3 carries 20 nm of alumina.
    let base = with_telescope(&common::tiny_fors1(d, 12.0, 4));
    let text = std::fs::read_to_string(&base).unwrap().replace(
        "name = \"M3\"\nmetal = \"aluminium\"\naoi_deg = 45.0\n",
        "name = \"M3\"\nmetal = \"aluminium\"\naoi_deg = 45.0\noverlayer = \"alumina\"\noverlayer_thickness_nm = 20.0\n",
    );
    assert!(text.contains("overlayer_thickness_nm = 20.0"));
    let inst = d.join("coated.toml");
    std::fs::write(&inst, text).unwrap();
    // Standards from the closed form of that mirror (Fresnel + thin film, here) with factor 0.93.
    let lambda_um = 0.554;
    let n = mueller::mirror::MetalTable::builtin("aluminium").unwrap().index(lambda_um).unwrap();
    let layer = mueller::thinfilm::Layer::new(mueller::mirror::alumina_index(lambda_um), 20.0);
    let p = mueller::mirror::reflect(n * 0.93, &[layer], 1000.0 * lambda_um, std::f64::consts::FRAC_PI_4)
        .unwrap()
        .polarization;
    let mut csv = String::from("star,parallactic_deg,q,sigma_q,u,sigma_u,wavelength_um,filter\n");
    for k in 0..24 {
        let pa = -170.0 + 14.5 * k as f64;
        let a = 2.0 * (OFFSET_DEG - pa).to_radians();
        let e = 2e-4 * (((k * 7) % 5) as f64 - 2.0) / 2.0;
        csv += &format!("W{k},{pa},{},2e-4,{},2e-4,{lambda_um},V\n", p * a.cos() + e, -p * a.sin() - e);
    }
    let cat = d.join("coated.csv");
    std::fs::write(&cat, csv).unwrap();
    let run = |extra: &[&str]| {
        let o = instpol()
            .arg("fit-standards")
            .arg(&cat)
            .args(["--model", "wiersema", "--json", "--instrument"])
            .arg(&inst)
            .args(extra)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        (j, String::from_utf8_lossy(&o.stderr).into_owned())
    };
    let (j, _) = run(&[]);
    assert_eq!(j[0]["mirror_source"], "instrument");
    assert_eq!(j[0]["overlayer_nm"].as_f64(), Some(20.0));
    let f = j[0]["params"].as_array().unwrap().iter().find(|p| p["name"] == "factor").unwrap().clone();
    let (fa, sfa) = (f["value"].as_f64().unwrap(), f["sigma_value"].as_f64().unwrap());
    assert!((fa - 0.93).abs() < 3.0 * sfa.max(1e-4), "factor {fa} +- {sfa}");
    // --metal overrides the instrument's (bare) and says so loudly; the factor then absorbs the
    // layer and moves.
    let (k, err) = run(&["--metal", "aluminium"]);
    assert!(err.contains("OVERRIDES") && err.contains("20 nm"), "{err}");
    assert_eq!(k[0]["mirror_source"], "--metal");
    let g =
        k[0]["params"].as_array().unwrap().iter().find(|p| p["name"] == "factor").unwrap()["value"].as_f64().unwrap();
    assert!((g - 0.93).abs() > 10.0 * sfa.max(1e-4), "bare-metal factor {g} vs {fa}");
}

/// A Stokes map image read here with fitsio (not with the library under test).
fn map_image(path: &Path, name: &str) -> Vec<f64> {
    let mut f = fitsio::FitsFile::open(path).unwrap();
    let h = f.hdu(name).unwrap_or_else(|e| panic!("{}: {name}: {e}", path.display()));
    h.read_image(&mut f).unwrap()
}

/// Median over the valid bins of (value - truth) / sigma.
fn median_pull(v: &[f64], s: &[f64], valid: &[f64], truth: f64) -> f64 {
    let mut p: Vec<f64> =
        (0..v.len()).filter(|&k| valid[k] > 0.5 && s[k] > 0.0).map(|k| (v[k] - truth) / s[k]).collect();
    assert!(p.len() > 20, "{} valid bins", p.len());
    p.sort_by(f64::total_cmp);
    p[p.len() / 2]
}

/// A sky field seen through the M3 reduced to a Stokes map: `instpol correct` with the fitted
/// telescope model and the frames' parallactic track (--parang, read from their headers here)
/// gives the sky's q, u back in every bin, where the uncorrected map is tens of sigma off.
/// `reduce` recorded the same track in the map (PARANG1, PARANG2), so `correct` needs no
/// --parang and writes the same map. A map without a track and no --parang, or --parang on a
/// field-only calibration, is refused and nothing is written.
#[test]
fn correct_removes_the_telescope_from_a_stokes_map() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let small = d.join("small.toml");
    std::fs::write(&small, common::SMALL.toml()).unwrap();
    let small = with_telescope(&small);
    // Standards 100 times less noisy than their stated errors: the model's own error is then
    // far below a bin's, and the corrected bins must scatter about the sky as their errors say.
    let tel = telescope_calibration_with_noise(d, &small, 3e-6, None);
    let (p, chi_deg) = (0.0174, -53.8f64);
    let scene = format!(
        "instrument = {:?}\nfilter = \"V\"\nseed = 17\nexposure_s = 20\n[output]\nbitpix = -32\n\
         [sky]\nbrightness_e = 40000.0\np = {p}\nchi_deg = {chi_deg}\n\
         [effects]\nphoton_noise = true\n\
         [telescope]\nfactor = {FACTOR}\noffset_deg = {OFFSET_DEG}\ndec_deg = -40\nha_start_deg = 30\noverhead_s = 5\n",
        small.display().to_string()
    );
    let frames = simulate(&scene, d, "skymap");
    let map = d.join("map.fits");
    let o = instpol()
        .arg("reduce")
        .args(&frames)
        .arg("--instrument")
        .arg(&small)
        .args(["--bin", "30", "--out"])
        .arg(&map)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let start = key(&frames[0], "HIERARCH ESO TEL PARANG START");
    let end = key(frames.last().unwrap(), "HIERARCH ESO TEL PARANG END");
    assert!((key(&map, "PARANG1") - start).abs() < 1e-9 && (key(&map, "PARANG2") - end).abs() < 1e-9);
    // The frames in another order (the headers hold no time to sort them by) give the same
    // track: the span of their angles in the sense they move.
    let mut shuffled = frames.clone();
    shuffled.reverse();
    shuffled.swap(0, 1);
    let map2 = d.join("map_shuffled.fits");
    let o = instpol()
        .arg("reduce")
        .args(&shuffled)
        .arg("--instrument")
        .arg(&small)
        .args(["--bin", "30", "--out"])
        .arg(&map2)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!((key(&map2, "PARANG1") - start).abs() < 1e-9 && (key(&map2, "PARANG2") - end).abs() < 1e-9);
    assert!((end - start).abs() > 0.05, "the set turned by {} deg only", end - start);
    let corrected = d.join("map_corr.fits");
    let correct = |extra: &[&str], cal: &Path| {
        instpol()
            .arg("correct")
            .arg("--cal")
            .arg(cal)
            .arg("--in")
            .arg(&map)
            .arg("--out")
            .arg(&corrected)
            .args(extra)
            .output()
            .unwrap()
    };
    let parang = format!("{start},{end}");
    let o = correct(&["--parang", &parang, "--json"], &tel);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["telescope_model"], "wiersema", "{j}");
    assert_eq!(j["telescope_band"], "V", "{j}");
    let (q_true, u_true) = (p * (2.0 * chi_deg.to_radians()).cos(), p * (2.0 * chi_deg.to_radians()).sin());
    let valid = map_image(&map, "VALID");
    let pulls = |path: &Path| {
        let (q, u) = (map_image(path, "Q"), map_image(path, "U"));
        let (sq, su) = (map_image(path, "SIGMA_Q"), map_image(path, "SIGMA_U"));
        (median_pull(&q, &sq, &valid, q_true), median_pull(&u, &su, &valid, u_true))
    };
    let (pq, pu) = pulls(&corrected);
    let (rq, ru) = pulls(&map);
    let med_off = |path: &Path, name: &str, truth: f64| {
        let mut v: Vec<f64> =
            map_image(path, name).iter().zip(&valid).filter(|(_, ok)| **ok > 0.5).map(|(x, _)| x - truth).collect();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let (dq, du) = (med_off(&corrected, "Q", q_true), med_off(&corrected, "U", u_true));
    eprintln!(
        "against the sky: corrected median offsets ({dq:.1e}, {du:.1e}), pulls ({pq:.2}, {pu:.2}); uncorrected pulls ({rq:.0}, {ru:.0})"
    );
    // With --parang the set is taken as one track. What remains (measured 1.5e-5, 7.7e-5) is
    // there before the correction: the uncorrected bins differ from the model's sky_through
    // over the whole track by as much (7.5e-5, 4.4e-5), as the four exposures, demodulated
    // together, saw the mirror at their own parallactic angles, not at the track's average.
    // It stays below a bin's error; the exposures' own tracks (below) remove it.
    assert!(dq.abs() < 1.5e-4 && du.abs() < 1.5e-4, "corrected map off the sky by ({dq}, {du})");
    assert!(pq.abs() < 1.0 && pu.abs() < 1.0, "corrected map off the sky: pulls {pq}, {pu}");
    assert!(rq.abs().max(ru.abs()) > 10.0, "the telescope left no mark on the map: pulls {rq}, {ru}");
    // The track is recorded in the output, as given.
    let mut f = fitsio::FitsFile::open(&corrected).unwrap();
    let h = f.primary_hdu().unwrap();
    assert!((h.read_key::<f64>(&mut f, "PARANG1").unwrap() - start).abs() < 1e-9);
    assert!((h.read_key::<f64>(&mut f, "PARANG2").unwrap() - end).abs() < 1e-9);
    assert_eq!(h.read_key::<String>(&mut f, "TELMODEL").unwrap(), "wiersema");

    // The map also recorded each exposure's HWP angle and track (the frames' headers): without
    // --parang the telescope is undone exposure by exposure, as the four exposures were
    // demodulated together, and what the average track left is gone.
    assert_eq!(key(&map, "NEXPTRK"), frames.len() as f64);
    for (k, f) in frames.iter().enumerate() {
        let s = key(f, "HIERARCH ESO TEL PARANG START");
        assert!((key(&map, &format!("XPAS{}", k + 1)) - s).abs() < 1e-9, "exposure {k}");
    }
    std::fs::remove_file(&corrected).unwrap();
    let o = correct(&["--json"], &tel);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let (eq, eu) = (med_off(&corrected, "Q", q_true), med_off(&corrected, "U", u_true));
    let (epq, epu) = pulls(&corrected);
    eprintln!("exposure by exposure: median offsets ({eq:.1e}, {eu:.1e}), pulls ({epq:.2}, {epu:.2})");
    assert!(eq.hypot(eu) < 0.25 * dq.hypot(du), "by exposure ({eq}, {eu}) against the average track ({dq}, {du})");
    assert!(epq.abs() < 0.2 && epu.abs() < 0.2, "by exposure: pulls {epq}, {epu}");
    {
        let mut f = fitsio::FitsFile::open(&corrected).unwrap();
        let h = f.primary_hdu().unwrap();
        let meth = h.read_key::<String>(&mut f, "CORRMETH").unwrap();
        assert!(meth.contains("exposure by exposure, 4"), "{meth}");
    }
    std::fs::remove_file(&corrected).unwrap();
    // Reduced as an instrument that names no parallactic keywords, the map has no track:
    // refused without --parang, naming it, nothing written.
    let plain = d.join("plain.toml");
    std::fs::write(&plain, common::SMALL.toml()).unwrap();
    let o = instpol()
        .arg("reduce")
        .args(&frames)
        .arg("--instrument")
        .arg(&plain)
        .args(["--bin", "30", "--out"])
        .arg(&map)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = correct(&[], &tel);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("--parang") && err.contains("map.fits"), "{err}");
    assert!(!corrected.exists());
    // A field-only calibration takes no track.
    let field = d.join("field.fits");
    common::fors1_radial_calibration("V", common::V_COEFFS).save(&field).unwrap();
    let o = correct(&["--parang", &parang], &field);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("--parang") && err.contains("telescope model"), "{err}");
    assert!(!corrected.exists());
}

/// A catalog whose stars all come from the same frames (as `instpol catalog` writes them, with
/// no parallactic-angle column) takes the frames' one track from --parang: the same corrected
/// columns, to the digit, as the catalog that carries the track in parang_deg and
/// parang_end_deg on every row. Both at once is refused, as is neither.
#[test]
fn correct_gives_a_catalog_without_angles_the_frames_track() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let tiny = with_telescope(&common::tiny_fors1(d, 12.0, 4));
    let tel = telescope_calibration(d, &tiny);
    let rows = [(0.031, -0.012), (0.004, 0.022), (-0.018, -0.027)];
    let (mut with, mut bare) = (
        String::from("x,y,q,u,sigma_q,sigma_u,parang_deg,parang_end_deg\n"),
        String::from("x,y,q,u,sigma_q,sigma_u\n"),
    );
    for (k, (q, u)) in rows.iter().enumerate() {
        with += &format!("{k},0,{q},{u},2e-4,2e-4,-41.5,-37.25\n");
        bare += &format!("{k},0,{q},{u},2e-4,2e-4\n");
    }
    let (cw, cb) = (d.join("with.csv"), d.join("bare.csv"));
    std::fs::write(&cw, with).unwrap();
    std::fs::write(&cb, bare).unwrap();
    let correct_with = |cal: &Path, input: &Path, out: &str, extra: &[&str]| {
        let o = instpol()
            .arg("correct")
            .arg("--cal")
            .arg(cal)
            .arg("--in")
            .arg(input)
            .arg("--out")
            .arg(d.join(out))
            .args(extra)
            .output()
            .unwrap();
        (o.status.code(), String::from_utf8_lossy(&o.stderr).to_string())
    };
    let correct = |input: &Path, out: &str, extra: &[&str]| correct_with(&tel, input, out, extra);
    assert_eq!(correct(&cw, "a.csv", &[]).0, Some(0));
    assert_eq!(correct(&cb, "b.csv", &["--parang", "-41.5,-37.25"]).0, Some(0));
    let columns = |f: &str| -> Vec<Vec<String>> {
        let mut r = csv::ReaderBuilder::new().comment(Some(b'#')).from_path(d.join(f)).unwrap();
        let h = r.headers().unwrap().clone();
        let want = ["q0", "u0", "sigma_q0", "sigma_u0", "q_inst", "u_inst"];
        let idx: Vec<usize> =
            want.iter().map(|n| h.iter().position(|x| x == *n).unwrap_or_else(|| panic!("{f}: no {n}"))).collect();
        r.records().map(|rec| idx.iter().map(|&i| rec.as_ref().unwrap()[i].to_string()).collect()).collect()
    };
    let (a, b) = (columns("a.csv"), columns("b.csv"));
    assert_eq!(a.len(), 3);
    assert_eq!(a, b);
    // The mirror's few percent were removed: the rows moved.
    assert!(a.iter().zip(&rows).all(|(r, (q, _))| (r[0].parse::<f64>().unwrap() - q).abs() > 1e-3), "{a:?}");
    let (code, err) = correct(&cw, "c.csv", &["--parang", "-41.5"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("use one"), "{err}");
    let (code, err) = correct(&cb, "c.csv", &[]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("--parang") && err.contains("parang_deg"), "{err}");
    assert!(!d.join("c.csv").exists());

    // A model fitted with rotator angles needs the rows' rotator angle: never an assumed 0.
    let tel_rot = telescope_calibration_with_noise(d, &tiny, 3e-4, Some(12.0));
    let correct_rot = |input: &Path, out: &str, extra: &[&str]| correct_with(&tel_rot, input, out, extra);
    let (code, err) = correct_rot(&cw, "r.csv", &[]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("rotator_deg") && err.contains("--rotator"), "{err}");
    assert!(!d.join("r.csv").exists());
    let (code, err) = correct_rot(&cb, "r.csv", &["--parang", "-41.5,-37.25"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("--rotator"), "{err}");
    // Given, for every row, as --rotator or as a column: the same rows.
    assert_eq!(correct_rot(&cw, "r1.csv", &["--rotator", "12"]).0, Some(0));
    // The catalog with parang columns, plus one more column of one value on every row.
    let plus_column = |name: &str, value: &str, file: &str| -> PathBuf {
        let mut text = String::new();
        for (k, l) in std::fs::read_to_string(&cw).unwrap().lines().enumerate() {
            text += &format!("{l},{}\n", if k == 0 { name } else { value });
        }
        std::fs::write(d.join(file), text).unwrap();
        d.join(file)
    };
    let cr = plus_column("rotator_deg", "12", "with_rot.csv");
    assert_eq!(correct_rot(&cr, "r2.csv", &[]).0, Some(0));
    assert_eq!(correct_rot(&cb, "r3.csv", &["--parang", "-41.5,-37.25", "--rotator", "12"]).0, Some(0));
    let (r1, r2, r3) = (columns("r1.csv"), columns("r2.csv"), columns("r3.csv"));
    assert_eq!(r1, r2);
    assert_eq!(r1, r3);
    // The rotator counts: another angle gives other rows.
    assert_eq!(correct_rot(&cw, "r4.csv", &["--rotator", "40"]).0, Some(0));
    assert_ne!(r1, columns("r4.csv"));

    // A catalog whose q, u carry a HWP zero angle is in the sky frame, where the telescope
    // model lives (fit::telescope::cal module docs): without a field model nothing is turned,
    // and nothing needs saying (this warned before the chain had one frame).
    let cz = plus_column("hwp_chi_offset_deg", "2.5", "zero.csv");
    let (code, err) = correct(&cz, "z.csv", &[]);
    assert_eq!(code, Some(0), "{err}");
    assert!(!err.contains("WARNING"), "{err}");
    let (code, err) = correct(&cw, "z2.csv", &[]);
    assert_eq!(code, Some(0), "{err}");
    assert_eq!(columns("z.csv"), columns("z2.csv"));
}

/// Ideal frames (`stars` as scene text) through the meridian 5 deg from the zenith on the tiny
/// FORS1 put on the Nasmyth focus: 8 exposures of 60 s at 8 HWP angles, the parallactic angle
/// turning by 3 deg from one to the next; with a telescope model fitted to noise-free
/// standards. With `zero_angle_deg` not 0 the instrument's V filter has that HWP zero angle
/// and the frames are taken through such a plate. Returns the instrument file, the model and
/// the frames.
fn meridian(d: &Path, seed: u64, stars: &str, zero_angle_deg: f64) -> (PathBuf, PathBuf, Vec<PathBuf>) {
    let mut tiny = with_telescope(&common::tiny_fors1(d, 12.0, 4));
    let mut effects = String::new();
    if zero_angle_deg != 0.0 {
        let text = std::fs::read_to_string(&tiny).unwrap();
        let v = "name = \"V\"\naliases = [\"V_BESS\"]\nlambda_eff_nm = 554.0\n";
        assert!(text.contains(v), "the V filter of FORS1's file");
        let text = text.replace(v, &format!("{v}hwp_chi_offset_deg = {zero_angle_deg:?}\n"));
        tiny = tiny.with_file_name("nasmyth_zero_angle.toml");
        std::fs::write(&tiny, text).unwrap();
        effects = "[effects]\nhwp_chi_offset_from_filter = true\n".into();
    }
    let tel = telescope_calibration_with_noise(d, &tiny, 0.0, None);
    let scene = format!(
        "instrument = {:?}\nfilter = \"V\"\nseed = {seed}\nexposure_s = 60\n\
         hwp_angles_deg = [0, 22.5, 45, 67.5, 90, 112.5, 135, 157.5]\n[output]\nbitpix = -64\n{stars}{effects}\
         [telescope]\nfactor = {FACTOR}\noffset_deg = {OFFSET_DEG}\ndec_deg = -24\nha_start_deg = -2.5\noverhead_s = 20\n",
        tiny.display().to_string()
    );
    let frames = simulate(&scene, d, &format!("meridian{seed}"));
    (tiny, tel, frames)
}

/// An unpolarized standard observed through the meridian close to the zenith (8 exposures at
/// 8 HWP angles, the parallactic angle turning by tens of degrees from one to the next), on
/// ideal frames and with a model fitted to noise-free standards: `validate` undoes the
/// telescope exposure by exposure from the frames' headers (JSON `exposures` = 8) and finds
/// the star unpolarized to a few 1e-6, where the set's one track (`--parang`, the same headers'
/// first start and last end) leaves a residual many times larger.
#[test]
fn validate_undoes_the_telescope_exposure_by_exposure() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let stars = "[[stars]]\nx = 64\ny = 34\ncoords = \"pixel\"\nflux_e = 4e6\nfwhm_arcsec = 1.6\n";
    let (tiny, tel, frames) = meridian(d, 41, stars, 0.0);
    let starts: Vec<f64> = frames.iter().map(|f| key(f, "HIERARCH ESO TEL PARANG START")).collect();
    let run = |extra: &[&str]| -> serde_json::Value {
        let mut args = vec!["--json"];
        args.extend_from_slice(extra);
        let (code, out, err) = validate(&tel, &tiny, &frames, &args);
        assert!(code == 0 || code == 1, "{err}");
        serde_json::from_str(&out).unwrap_or_else(|e| panic!("{e}: {out} {err}"))
    };
    let by_exposure = run(&[]);
    assert_eq!(by_exposure["exposures"], 8, "{by_exposure}");
    let resid = |j: &serde_json::Value| j["corrected_q"].as_f64().unwrap().hypot(j["corrected_u"].as_f64().unwrap());
    let track = format!(
        "{},{}",
        by_exposure["parallactic_start_deg"].as_f64().unwrap(),
        by_exposure["parallactic_end_deg"].as_f64().unwrap()
    );
    let one = run(&["--parang", &track]);
    assert_eq!(one["exposures"], 0, "{one}");
    let (r_ex, r_one) = (resid(&by_exposure), resid(&one));
    eprintln!("parallactic starts {starts:?}: residual exposure by exposure {r_ex:.2e}, one track {r_one:.2e}");
    // The telescope put a few percent on the star (what is being undone).
    assert!(by_exposure["measured_q"].as_f64().unwrap().hypot(by_exposure["measured_u"].as_f64().unwrap()) > 0.01);
    assert!(r_ex < 1e-5, "exposure by exposure: {by_exposure}");
    assert!(r_one > 10.0 * r_ex, "one track {r_one:.2e} vs exposure by exposure {r_ex:.2e}");
}

/// Stars observed through the meridian close to the zenith (the sequence of
/// [`validate_undoes_the_telescope_exposure_by_exposure`]), on ideal frames, with a model
/// fitted to noise-free standards: `catalog --cal` undoes the telescope exposure by exposure
/// from the frames' headers and gives every star's intrinsic polarization back to 1e-5
/// (an unpolarized one and one of 3 % at 20 deg), where `instpol correct` of the same catalog
/// over the set's one track (`--parang`, the headers' first start and last end) leaves 1e-3.
#[test]
fn catalog_undoes_the_telescope_exposure_by_exposure() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let stars = "[[stars]]\nx = 34\ny = 34\ncoords = \"pixel\"\nflux_e = 4e6\nfwhm_arcsec = 1.6\n\
                 [[stars]]\nx = 94\ny = 34\ncoords = \"pixel\"\nflux_e = 4e6\nfwhm_arcsec = 1.6\np = 0.03\nchi_deg = 20\n";
    let (tiny, tel, frames) = meridian(d, 43, stars, 0.0);
    let cat_args = |extra: &[&str]| {
        let mut c = instpol();
        c.arg("catalog").args(&frames).arg("--instrument").arg(&tiny);
        c.args(["--fwhm", "4", "--aperture", "10", "--annulus", "14,24"]).args(extra);
        c
    };
    // `instpol correct --cal TEL --in INPUT --out OUT --coords arcmin EXTRA...`.
    let correct = |input: &Path, out: &Path, extra: &[&str]| {
        let mut c = instpol();
        c.args(["correct", "--cal"]).arg(&tel).arg("--in").arg(input).arg("--out").arg(out);
        c.args(["--coords", "arcmin"]).args(extra).output().unwrap()
    };
    let o = cat_args(&["--json"]).arg("--cal").arg(&tel).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["telescope_exposures"], 8, "{}", j["telescope_exposures"]);
    assert_eq!(j["telescope_band"], "V");
    // Each star's intrinsic (q, u): the unpolarized one at x = 34, 3 % at 20 deg at x = 94.
    let truth =
        |x: f64| if x < 64.0 { (0.0, 0.0) } else { (0.03 * 40f64.to_radians().cos(), 0.03 * 40f64.to_radians().sin()) };
    let rows = j["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 2, "{}", j["rows"]);
    let mut worst_ex = 0.0f64;
    for (r, c) in rows.iter().zip(j["corrected"].as_array().unwrap()) {
        let (q, u) = truth(r["x"].as_f64().unwrap());
        let off = (c["q0"].as_f64().unwrap() - q).hypot(c["u0"].as_f64().unwrap() - u);
        worst_ex = worst_ex.max(off);
    }
    // The same catalog written, then corrected over the set's one track.
    let table = d.join("stars.csv");
    let o = cat_args(&["--out", table.to_str().unwrap()]).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let pa0 = key(&frames[0], "HIERARCH ESO TEL PARANG START");
    let pa1 = key(frames.last().unwrap(), "HIERARCH ESO TEL PARANG END");
    let one = d.join("one.csv");
    let o = correct(&table, &one, &["--parang", &format!("{pa0},{pa1}")]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let mut rdr = csv::ReaderBuilder::new().comment(Some(b'#')).from_path(&one).unwrap();
    let h = rdr.headers().unwrap().clone();
    let col = |name: &str| h.iter().position(|c| c == name).unwrap();
    let mut worst_one = 0.0f64;
    for rec in rdr.records() {
        let rec = rec.unwrap();
        let v = |name: &str| rec[col(name)].parse::<f64>().unwrap();
        let (q, u) = truth(v("x"));
        worst_one = worst_one.max((v("q0") - q).hypot(v("u0") - u));
    }
    eprintln!("catalog --cal exposure by exposure: worst star off by {worst_ex:.2e}; one track: {worst_one:.2e}");
    assert!(worst_ex < 1e-5, "exposure by exposure: {worst_ex:.2e}");
    assert!(worst_one > 10.0 * worst_ex && worst_one > 1e-4, "one track {worst_one:.2e}");

    // Written as ECSV, FITS or VOTable, the catalog records its exposures' angles, and `instpol
    // correct` (no --parang) undoes the telescope as `catalog --cal` did, to 1e-12 (the angles
    // go through degrees in the file). A CSV table has no place for them: refused, naming
    // the formats that have.
    let by_x = |x: f64| {
        let i = rows.iter().position(|r| (r["x"].as_f64().unwrap() - x).abs() < 1e-9).unwrap();
        let c = &j["corrected"][i];
        (c["q0"].as_f64().unwrap(), c["u0"].as_f64().unwrap())
    };
    for ext in ["ecsv", "fits", "vot"] {
        let t = d.join(format!("stars.{ext}"));
        let o = cat_args(&["--out", t.to_str().unwrap()]).output().unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let out = d.join(format!("corr_{ext}.csv"));
        let o = correct(&t, &out, &[]);
        assert!(o.status.success(), "{ext}: {}", String::from_utf8_lossy(&o.stderr));
        assert!(String::from_utf8_lossy(&o.stdout).contains("exposure by exposure (8"), "{ext}");
        let mut rdr = csv::ReaderBuilder::new().comment(Some(b'#')).from_path(&out).unwrap();
        let h = rdr.headers().unwrap().clone();
        let col = |name: &str| h.iter().position(|c| c == name).unwrap();
        for rec in rdr.records() {
            let rec = rec.unwrap();
            let v = |name: &str| rec[col(name)].parse::<f64>().unwrap();
            let (q, u) = by_x(v("x"));
            assert!(
                (v("q0") - q).abs() < 1e-12 && (v("u0") - u).abs() < 1e-12,
                "{ext}: {} {} vs {q} {u}",
                v("q0"),
                v("u0")
            );
        }
    }
    // The JSON summary says so, and its keys are the schema's (closed: no key it lacks).
    let o = correct(&d.join("stars.ecsv"), &d.join("corr_json.ecsv"), &["--json"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let sj: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(sj["telescope_exposures"], 8, "{sj}");
    let schema: serde_json::Value =
        serde_json::from_str(include_str!("../../../../schemas/correct.schema.json")).unwrap();
    for k in sj.as_object().unwrap().keys() {
        assert!(schema["properties"].get(k).is_some(), "correct --json key '{k}' is not in its schema");
    }
    let o = correct(&table, &d.join("csv_refused.csv"), &[]);
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("no recorded parallactic angles") && err.contains("ECSV, FITS and VOTable"), "{err}");
}

/// The sequence of [`validate_undoes_the_telescope_exposure_by_exposure`] through a half-wave
/// plate whose zero angle is 7 deg (the instrument file's V filter says so, the frames are
/// taken through it), with the telescope model fitted to standards in the sky frame (as
/// photometry, catalogs and published standards give them): `validate` (the star measured at
/// the plate) and `catalog --cal` (the catalog's q, u carry the zero angle) both give an
/// unpolarized star and one of 3 % at 20 deg back to 1e-10 (ideal frames: 4e-16 measured).
/// With the measurement turned into the models' frame but the exposures' plate angles not,
/// `validate` left 9e-4; before either, about 2 sin(7 deg) x 3.6 % = 9e-3 (and warned).
#[test]
fn the_chain_undoes_the_telescope_through_a_hwp_zero_angle() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let stars = "[[stars]]\nx = 34\ny = 34\ncoords = \"pixel\"\nflux_e = 4e6\nfwhm_arcsec = 1.6\n\
                 [[stars]]\nx = 94\ny = 34\ncoords = \"pixel\"\nflux_e = 4e6\nfwhm_arcsec = 1.6\np = 0.03\nchi_deg = 20\n";
    let (tiny, tel, frames) = meridian(d, 47, stars, 7.0);
    let truth = |x: f64| {
        if x < 64.0 {
            (0.0, 0.0)
        } else {
            (0.03 * 40f64.to_radians().cos(), 0.03 * 40f64.to_radians().sin())
        }
    };
    // validate: the unpolarized star (x = 34), measured at the plate.
    let o = instpol()
        .arg("validate")
        .arg("--cal")
        .arg(&tel)
        .arg("--instrument")
        .arg(&tiny)
        .args(&frames)
        .args(["--x", "34", "--y", "34", "--aperture", "10", "--annulus", "14,24", "--json"])
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(0), "{out} {err}");
    let j: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(j["exposures"], 8, "{j}");
    assert_eq!(j["hwp_chi_offset_deg"], 7.0, "{j}");
    let r = j["corrected_q"].as_f64().unwrap().hypot(j["corrected_u"].as_f64().unwrap());
    let measured = j["measured_q"].as_f64().unwrap().hypot(j["measured_u"].as_f64().unwrap());
    eprintln!("validate through a 7 deg zero angle: measured {measured:.2e}, corrected {r:.2e}");
    assert!(measured > 0.01, "{j}");
    assert!(r < 1e-10, "validate: {j}");
    assert!(!err.contains("zero angle"), "no caveat is left to give: {err}");
    // catalog --cal: both stars.
    let o = instpol()
        .arg("catalog")
        .args(&frames)
        .arg("--instrument")
        .arg(&tiny)
        .args(["--fwhm", "4", "--aperture", "10", "--annulus", "14,24", "--json", "--cal"])
        .arg(&tel)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let rows = j["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 2, "{}", j["rows"]);
    for (r, c) in rows.iter().zip(j["corrected"].as_array().unwrap()) {
        let (q, u) = truth(r["x"].as_f64().unwrap());
        let off = (c["q0"].as_f64().unwrap() - q).hypot(c["u0"].as_f64().unwrap() - u);
        eprintln!("catalog --cal through a 7 deg zero angle: star at x = {}: off by {off:.2e}", r["x"]);
        assert!(off < 1e-10, "catalog --cal: {r} {c}");
    }
    // zero-angle on these Nasmyth frames measures the mirror's turn with the plate's: it says so.
    let o = instpol()
        .arg("zero-angle")
        .args(&frames)
        .arg("--instrument")
        .arg(&tiny)
        .args(["--x", "94", "--y", "34", "--chi-deg", "20", "--aperture", "10", "--annulus", "14,24"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("WARNING") && err.contains("Nasmyth") && err.contains("fit-standards"), "{err}");
}

/// A sky field through the M3 and a half-wave plate whose zero angle is 7 deg, on ideal frames
/// of a small instrument file (not a built-in one): `reduce` records the filter's zero angle in
/// the map (`HWPZERO`), and `correct` with a telescope model alone (fitted to noise-free
/// standards in the sky frame) turns the map into the sky frame by it and undoes the telescope
/// exposure by exposure: every valid bin gives the sky back to 1e-9, and the corrected map
/// records the zero angle applied (`CORRHWP`).
#[test]
fn correct_turns_a_map_by_its_recorded_zero_angle() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let v = "lambda_eff_nm = 554.0\n";
    let text = common::MINI.toml();
    assert!(text.contains(v));
    let mini = d.join("mini.toml");
    std::fs::write(&mini, text.replace(v, &format!("{v}hwp_chi_offset_deg = 7.0\n"))).unwrap();
    let mini = with_telescope(&mini);
    let tel = telescope_calibration_with_noise(d, &mini, 0.0, None);
    let (p, chi_deg) = (0.0174, -53.8f64);
    let scene = format!(
        "instrument = {:?}\nfilter = \"V\"\nseed = 19\nexposure_s = 20\n[output]\nbitpix = -64\n\
         [sky]\nbrightness_e = 40000.0\np = {p}\nchi_deg = {chi_deg}\n\
         [effects]\nhwp_chi_offset_from_filter = true\n\
         [telescope]\nfactor = {FACTOR}\noffset_deg = {OFFSET_DEG}\ndec_deg = -40\nha_start_deg = 30\noverhead_s = 5\n",
        mini.display().to_string()
    );
    let frames = simulate(&scene, d, "zero_sky");
    let map = d.join("map.fits");
    let o = instpol()
        .arg("reduce")
        .args(&frames)
        .arg("--instrument")
        .arg(&mini)
        .args(["--bin", "8", "--out"])
        .arg(&map)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(key(&map, "HWPZERO"), 7.0);
    let corrected = d.join("map_corr.fits");
    let o = instpol()
        .args(["correct", "--cal"])
        .arg(&tel)
        .arg("--in")
        .arg(&map)
        .arg("--out")
        .arg(&corrected)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(!err.contains("warning"), "{err}");
    assert_eq!(key(&corrected, "CORRHWP"), 7.0);
    // Its Q, U carry the zero angle now: no HWPZERO says they lack one.
    let mut f = fitsio::FitsFile::open(&corrected).unwrap();
    let h = f.primary_hdu().unwrap();
    assert!(h.read_key::<f64>(&mut f, "HWPZERO").is_err(), "a corrected map records HWPZERO");
    let (q_true, u_true) = (p * (2.0 * chi_deg.to_radians()).cos(), p * (2.0 * chi_deg.to_radians()).sin());
    let valid = map_image(&map, "VALID");
    let (q, u) = (map_image(&corrected, "Q"), map_image(&corrected, "U"));
    let (q_raw, u_raw) = (map_image(&map, "Q"), map_image(&map, "U"));
    let mut worst = 0.0f64;
    let mut n = 0;
    for k in (0..valid.len()).filter(|&k| valid[k] > 0.5) {
        worst = worst.max((q[k] - q_true).hypot(u[k] - u_true));
        // The uncorrected map is tens of 1e-3 off: the mirror and the plate's turn.
        assert!((q_raw[k] - q_true).hypot(u_raw[k] - u_true) > 5e-3, "bin {k}: the telescope left no mark");
        n += 1;
    }
    eprintln!("map through a 7 deg zero angle: {n} bins, worst off the sky by {worst:.2e}");
    assert!(n > 20, "{n} valid bins");
    assert!(worst < 1e-9, "corrected map off the sky by {worst:e}");

    // The same map without its record (as maps before HWPZERO): MINI is no built-in
    // instrument, so its zero angle is unknown here; correct says so loudly and takes 0.
    let mut m = skyfield::StokesMap::read_fits(&map).unwrap();
    m.hwp_zero_angle_deg = None;
    let bare = d.join("bare.fits");
    m.write_fits(&bare).unwrap();
    let out = d.join("bare_corr.fits");
    let o =
        instpol().args(["correct", "--cal"]).arg(&tel).arg("--in").arg(&bare).arg("--out").arg(&out).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains("warning") && err.contains("HWPZERO") && err.contains("MINI") && err.contains("taken as 0"),
        "{err}"
    );
    assert_eq!(key(&out, "CORRHWP"), 0.0);
}
