//! Polarization angles on the sky on a rotator, end to end: one polarized standard (P = 4 %,
//! chi = 35 deg north through east) simulated with the instrument at three position angles on
//! the sky, its frames carrying the angle under a header keyword of sense -1 and offset 90 deg
//! (the instrument file's `[polarimetry.sky_angle]`), and catalogued. The truth is the scene's
//! chi: each set gives it within its errors, and the three agree with each other. Read by the
//! same instrument without `[polarimetry.sky_angle]`, the sets give the instrument's angles,
//! which differ by the turns (the closed form chi - PA). The same from each frame's WCS (a CD
//! matrix of the closed form for the +y axis's position angle); a set whose instrument turned
//! between exposures, a mirrored WCS and a scene that cannot say its angle are refused.

use sim::Scene;
use skyfield::catalog::{catalog_files, CatalogConfig};
use std::path::{Path, PathBuf};

const P: f64 = 0.04;
const CHI_SKY: f64 = 35.0;
/// The filter's HWP zero angle in the test's instrument, which the simulator applies too
/// (`hwp_chi_offset_from_filter`): both turns are applied together.
const ZERO: f64 = 2.5;
const STAR: (f64, f64) = (150.0, 160.0);

/// The 400 x 400 px maskless calcite instrument with a HWP zero angle in V, and `sky_angle`
/// (an inline `[polarimetry.sky_angle]` table, or nothing).
fn instrument(dir: &Path, name: &str, sky_angle: &str) -> PathBuf {
    let text = include_str!("../../../../instruments/calcite.toml")
        .replace("hwp_angle_keyword = \"\"", "hwp_angle_keyword = \"HWPANG\"")
        .replace("nx = 700", "nx = 400")
        .replace("ny = 700", "ny = 400")
        .replace("width_arcmin = 2.49", "width_arcmin = 1.43")
        .replace("height_arcmin = 2.49", "height_arcmin = 1.43")
        .replacen("lambda_eff_nm = 530.0", &format!("lambda_eff_nm = 530.0\nhwp_chi_offset_deg = {ZERO}"), 1)
        .replace("exptime_keyword = \"EXPTIME\"\n", &format!("exptime_keyword = \"EXPTIME\"\n{sky_angle}"));
    let p = dir.join(format!("{name}.toml"));
    std::fs::write(&p, text).unwrap();
    p
}

const BY_KEYWORD: &str = "sky_angle = { keyword = \"ROTSKYPA\", sense = -1, offset_deg = 90.0 }\n";
const BY_WCS: &str = "sky_angle = { from_wcs = true }\n";

/// The standard alone on a faint unpolarized sky, the instrument at `pa` deg; `keywords`: more
/// `[output.keywords]` lines.
fn scene(dir: &Path, inst: &Path, pa: f64, seed: u64, keywords: &str) -> Result<Scene, String> {
    let (x, y) = STAR;
    let body = format!(
        "instrument = \"{}\"\nfilter = \"V\"\nseed = {seed}\nsky_pa_deg = {pa}\n[output]\nbitpix = -64\n\
         [output.keywords]\n{keywords}[sky]\nbrightness_e = 50\np = 0.0\nchi_deg = 0\n\
         [effects]\nphoton_noise = true\nread_noise = true\nhwp_chi_offset_from_filter = true\n\
         [[stars]]\nx = {x}\ny = {y}\ncoords = \"pixel\"\nflux_e = 8e5\np = {P}\nchi_deg = {CHI_SKY}\nfwhm_arcsec = 0.9\n",
        inst.display()
    );
    Scene::from_toml_str(&body, &dir.join(format!("scene_{seed}.toml"))).map_err(|e| e.to_string())
}

fn simulate(dir: &Path, inst: &Path, pa: f64, seed: u64, keywords: &str) -> Vec<PathBuf> {
    let sc = scene(dir, inst, pa, seed, keywords).unwrap();
    sim::simulate(&sc, &dir.join(format!("frames_{seed}")), &|| {}).unwrap().frames
}

/// The standard's row of the catalog of `frames` read with `inst`: `(chi, sigma_chi)` deg, the
/// catalog's frame and its table's frame.
fn standard(frames: &[PathBuf], inst: &Path) -> Result<(f64, f64, mueller::Frame, mueller::Frame), String> {
    let inst = instrument::Instrument::load(inst.to_str().unwrap()).unwrap();
    let cfg = CatalogConfig {
        radius: skyfield::photometry::ApertureRadius::Px(8.0),
        annulus: Some((14.0, 24.0)),
        ..Default::default()
    };
    let (cat, _) =
        catalog_files(frames, &inst, &Default::default(), &cfg, Box::new(|| {})).map_err(|e| e.to_string())?;
    let r = cat.rows.iter().find(|r| (r.x - STAR.0).hypot(r.y - STAR.1) < 1.5).expect("the standard is found");
    assert!(r.chi_deg.is_finite(), "the standard is measured: flags {}, {}", r.flags, r.note);
    let frame = cat.product.as_ref().and_then(|p| p.frame()).expect("the catalog says its frame");
    let table = cat.to_table().frame(Path::new("catalog")).unwrap();
    Ok((r.chi_deg, r.sigma_chi_deg, frame, table))
}

/// A difference of two polarization angles (deg), in (-90, 90].
fn diff(a: f64, b: f64) -> f64 {
    mueller::wrap_half_pi((a - b).to_radians()).to_degrees()
}

/// The standard at position angles 0, 60 and -142 deg (MOPTOP's): on the sky each set gives
/// chi = 35 deg within 3 of its errors, and each pair agrees within 3 of their joint error;
/// the catalog's frame (and its table's) is the celestial one with the angle the scene set.
/// Read without `[polarimetry.sky_angle]` the same frames give 35 - PA (the instrument's
/// frame), within the same errors.
#[test]
fn one_standard_at_three_rotator_angles_agrees_on_the_sky() {
    let dir = tempfile::tempdir().unwrap();
    let rotator = instrument(dir.path(), "rotator", BY_KEYWORD);
    let plain = instrument(dir.path(), "plain", "");
    let mut on_sky = Vec::new();
    for (k, pa) in [0.0, 60.0, -142.0].into_iter().enumerate() {
        let frames = simulate(dir.path(), &rotator, pa, 21 + k as u64, "");
        let (chi, sigma, frame, table) = standard(&frames, &rotator).unwrap();
        eprintln!("PA {pa:7.1} deg: chi on the sky {chi:.3} +- {sigma:.3} deg");
        assert!(diff(chi, CHI_SKY).abs() < 3.0 * sigma, "PA {pa}: chi {chi} +- {sigma}, truth {CHI_SKY}");
        let want = mueller::Frame::Celestial { zero_angle_deg: ZERO, position_angle_deg: pa };
        match frame {
            mueller::Frame::Celestial { zero_angle_deg, position_angle_deg } => {
                assert!(zero_angle_deg == ZERO && (position_angle_deg - pa).abs() < 1e-9, "{frame:?}, want {want:?}")
            }
            f => panic!("PA {pa}: frame {f:?}, want {want:?}"),
        }
        assert_eq!(table, frame, "the table's columns say the catalog's frame");
        let (inst_chi, inst_sigma, inst_frame, _) = standard(&frames, &plain).unwrap();
        assert_eq!(inst_frame, mueller::Frame::Sky { zero_angle_deg: ZERO });
        assert!(
            diff(inst_chi, CHI_SKY - pa).abs() < 3.0 * inst_sigma,
            "PA {pa}: the instrument's chi {inst_chi} +- {inst_sigma}, closed form {}",
            CHI_SKY - pa
        );
        on_sky.push((pa, chi, sigma));
    }
    for (i, a) in on_sky.iter().enumerate() {
        for b in &on_sky[i + 1..] {
            let joint = a.2.hypot(b.2);
            assert!(diff(a.1, b.1).abs() < 3.0 * joint, "PA {} and {}: {} and {} (+- {joint})", a.0, b.0, a.1, b.1);
        }
    }
}

/// The `[output.keywords]` lines of a TAN WCS whose +y axis points at position angle `pa_y`
/// deg (north through east), north up and east left when `pa_y` = 0: the CROTA2 form of the
/// CD matrix, `CD1_1 = CDELT1 cos r`, `CD1_2 = -CDELT2 sin r`, `CD2_1 = CDELT1 sin r`,
/// `CD2_2 = CDELT2 cos r`, with CDELT1 = -s, CDELT2 = s and r = -pa_y (the +y axis then points
/// at east -s sin r over north s cos r, position angle -r); `mirror` flips the x axis (east
/// right).
fn wcs_keywords(pa_y: f64, mirror: bool) -> String {
    let s = 0.2 / 3600.0;
    let rho = (-pa_y).to_radians();
    let m = if mirror { -1.0 } else { 1.0 };
    let cd = [[-s * m * rho.cos(), -s * rho.sin()], [-s * m * rho.sin(), s * rho.cos()]];
    format!(
        "CTYPE1 = \"RA---TAN\"\nCTYPE2 = \"DEC--TAN\"\nCRPIX1 = 200.5\nCRPIX2 = 200.5\nCRVAL1 = 150.0\nCRVAL2 = -30.0\n\
         CD1_1 = {:e}\nCD1_2 = {:e}\nCD2_1 = {:e}\nCD2_2 = {:e}\n",
        cd[0][0], cd[0][1], cd[1][0], cd[1][1]
    )
}

/// From each frame's WCS: the standard at position angle 60 deg gives chi = 35 deg on the sky;
/// a WCS mirrored against the sky is refused naming the file and why.
#[test]
fn the_angle_is_read_from_each_frames_wcs() {
    let dir = tempfile::tempdir().unwrap();
    let wcs = instrument(dir.path(), "wcs", BY_WCS);
    let frames = simulate(dir.path(), &wcs, 60.0, 31, &wcs_keywords(60.0, false));
    let (chi, sigma, frame, _) = standard(&frames, &wcs).unwrap();
    assert!(diff(chi, CHI_SKY).abs() < 3.0 * sigma, "chi {chi} +- {sigma}, truth {CHI_SKY}");
    assert!(
        matches!(frame, mueller::Frame::Celestial { position_angle_deg, .. } if (position_angle_deg - 60.0).abs() < 1e-9)
    );
    let mirrored = simulate(dir.path(), &wcs, 60.0, 32, &wcs_keywords(60.0, true));
    let e = standard(&mirrored, &wcs).unwrap_err();
    assert!(e.contains(&*mirrored[0].to_string_lossy()) && e.contains("mirrored"), "{e}");
}

/// Exposures of one set at two position angles (the first two of a set at 0 deg, the last two
/// of one at 60 deg) are refused, naming a file of each and both angles; a scene whose
/// instrument does not say where its frames carry the angle, or that gives a telescope too,
/// is refused naming `sky_pa_deg`.
#[test]
fn a_set_that_turned_and_scenes_that_cannot_say_their_angle_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let rotator = instrument(dir.path(), "rotator", BY_KEYWORD);
    let a = simulate(dir.path(), &rotator, 0.0, 41, "");
    let b = simulate(dir.path(), &rotator, 60.0, 42, "");
    let mixed = vec![a[0].clone(), a[1].clone(), b[2].clone(), b[3].clone()];
    let e = standard(&mixed, &rotator).unwrap_err();
    assert!(e.contains("turned against the sky") && e.contains(&*b[2].to_string_lossy()), "{e}");
    assert!(e.contains("60.000") && e.contains("0.000"), "{e}");
    let plain = instrument(dir.path(), "plain", "");
    let e = scene(dir.path(), &plain, 30.0, 43, "").unwrap_err();
    assert!(e.contains("sky_pa_deg") && e.contains("[polarimetry.sky_angle]"), "{e}");
}
