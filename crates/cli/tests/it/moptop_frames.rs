//! MOPTOP's frames as the Liverpool Telescope archive writes them, read by the built-in
//! `moptop` with no edit: two cameras of 1024 x 1024 px behind a turning plate, two turns of 16
//! rotor positions, one file per camera and position named `3_e_YYYYMMDD_R_N_P_1.fits`
//! (camera 1) and `4_e_...` (camera 2), both cameras writing INSTRUME = 'Moptop', the camera in
//! MOPCNUM, the turn in MOPRNUM, the position in MOPRPOS, the rotor's range in MOPRBEG and
//! MOPREND, and MOPRARC as the real headers give it (18.2 deg on camera 1, the arc swept; 22.5
//! deg on camera 2, the position's nominal range). Camera 2 is not mirrored: it sees camera 1's
//! sky through a map of scale 1.0017 and rotation 0.17 deg that puts (694.8, 346.9) at (715.8,
//! 322.9), the numbers of real frames. The frames are simulated, then given the archive's
//! names and keywords here; `catalog` gets them in the order a shell glob gives (every camera-1
//! file first) and measures every star against the simulator's truth. The instrument stands at
//! ROTSKYPA = -142 deg on the sky, as in the real frames: the stars' angles are the sky's, and
//! the catalog gives them north through east.

use crate::common;

use common::run;
use std::path::{Path, PathBuf};

/// The camera map's scale and rotation (deg), and one star's place on both cameras.
const SCALE: f64 = 1.0017;
const ROTATION_DEG: f64 = 0.17;
const STAR_CAM1: (f64, f64) = (694.8, 346.9);
const STAR_CAM2: (f64, f64) = (715.8, 322.9);
/// The arc each exposure sweeps (deg): 4 s at 4.5 deg/s, as MOPRARC gives it on camera 1.
const SWEEP_DEG: f64 = 18.2;
/// The frames' celestial WCS: a gnomonic projection about (RA, Dec) = CRVAL (deg) at 1-based
/// pixel CRPIX, 0.416" px turned by CROTA1 = 142 deg (the real frames' numbers).
const CRVAL: (f64, f64) = (250.4, 36.46);
const CRPIX: (f64, f64) = (512.5, 512.5);
const PIXEL_ARCSEC: f64 = 0.416;
const CROTA_DEG: f64 = 142.0;

/// The CD matrix (deg/px): east to the left at rotation 0, turned by CROTA_DEG.
fn cd() -> [[f64; 2]; 2] {
    let (s, r) = (PIXEL_ARCSEC / 3600.0, CROTA_DEG.to_radians());
    [[-s * r.cos(), s * r.sin()], [s * r.sin(), s * r.cos()]]
}

/// `[a, b, c, d, e, f]`: camera 1 px (x, y) -> camera 2 px (a x + b y + c, d x + e y + f), a
/// turn by ROTATION_DEG and a scale by SCALE through STAR_CAM1 -> STAR_CAM2.
fn camera_map() -> [f64; 6] {
    let (s, r) = (SCALE, ROTATION_DEG.to_radians());
    let (a, b, d, e) = (s * r.cos(), -s * r.sin(), s * r.sin(), s * r.cos());
    let c = STAR_CAM2.0 - (a * STAR_CAM1.0 + b * STAR_CAM1.1);
    let f = STAR_CAM2.1 - (d * STAR_CAM1.0 + e * STAR_CAM1.1);
    [a, b, c, d, e, f]
}

/// 40 stars on an 8 x 5 grid inside both cameras, P from 0.5 % to 5 %, chi all round:
/// `(x, y, p, chi_deg, flux_e)` on camera 1.
fn stars() -> Vec<(f64, f64, f64, f64, f64)> {
    (0..40)
        .map(|k| {
            let (i, j) = (k % 8, k / 8);
            let (x, y) = (130.0 + 108.3 * i as f64 + 0.7 * j as f64, 140.0 + 180.5 * j as f64 - 0.6 * i as f64);
            let p = 0.005 + 0.045 * ((7 * k) % 40) as f64 / 39.0;
            let chi = (11.0 + 47.0 * k as f64) % 180.0;
            (x, y, p, chi, 4e5 * (1.0 + (k % 3) as f64 * 0.5))
        })
        .collect()
}

/// The plate's middle angle (deg) at rotor position `pos` (1..16): each position's 22.5 deg,
/// the exposure's 18.2 deg sweep about its middle.
fn middle_deg(pos: usize) -> f64 {
    22.5 * (pos - 1) as f64 + 11.25
}

/// Set (or add) header cards of a FITS file, its data untouched: `(key, value)` with the value
/// as a FITS card holds it (`'Moptop'`, `2`, `18.2`). Written here, on the FITS standard's
/// 80-character cards and 2880-byte blocks, so that the frames' keywords do not come from the
/// code under test.
fn set_cards(path: &Path, cards: &[(&str, String)]) {
    let bytes = std::fs::read(path).unwrap();
    let mut header: Vec<String> = Vec::new();
    let mut end = None;
    for (i, c) in bytes.chunks(80).enumerate() {
        let card = std::str::from_utf8(c).unwrap();
        if card.trim_end() == "END" {
            end = Some(i);
            break;
        }
        header.push(card.to_string());
    }
    let data_start = ((end.unwrap() + 1) * 80).div_ceil(2880) * 2880;
    for (key, value) in cards {
        let card =
            if value.starts_with('\'') { format!("{key:<8}= {value}") } else { format!("{key:<8}= {value:>20}") };
        let card = format!("{card:<80}");
        match header.iter().position(|c| c[..8].trim_end() == *key) {
            Some(i) => header[i] = card,
            None => header.push(card),
        }
    }
    header.push(format!("{:<80}", "END"));
    let mut out = header.concat().into_bytes();
    out.resize(out.len().div_ceil(2880) * 2880, b' ');
    out.extend_from_slice(&bytes[data_start..]);
    std::fs::write(path, out).unwrap();
}

/// Simulate the two turns with the built-in file plus the true camera map (the simulator's
/// truth), then give each file the archive's name and keywords; the files in glob order.
fn archive_frames(dir: &Path) -> Vec<PathBuf> {
    let t = camera_map();
    let text = include_str!("../../../../instruments/moptop.toml").replacen(
        "max_residual_px = 0.5",
        &format!("transform = [{}, {}, {}, {}, {}, {}]\nmax_residual_px = 0.5", t[0], t[1], t[2], t[3], t[4], t[5]),
        1,
    );
    let sim_inst = dir.join("moptop_truth.toml");
    std::fs::write(&sim_inst, text).unwrap();
    // Two turns: positions 1..16, twice.
    let angles: Vec<String> = (0..32).map(|k| middle_deg(k % 16 + 1).to_string()).collect();
    let mut scene = format!(
        "instrument = \"{}\"\nfilter = \"R\"\nseed = 43\nexposure_s = 4\nsky_pa_deg = {}\nhwp_angles_deg = [{}]\nhwp_motion = {{ sweep_deg = {SWEEP_DEG} }}\n\
         [output]\nbitpix = -32\n[sky]\nbrightness_e = 80\np = 0.0\nchi_deg = 0\n[effects]\nphoton_noise = true\nread_noise = true\n",
        sim_inst.display(),
        -CROTA_DEG,
        angles.join(", ")
    );
    for (x, y, p, chi, f) in stars() {
        scene += &format!(
            "[[stars]]\nx = {x}\ny = {y}\ncoords = \"pixel\"\nflux_e = {f}\np = {p}\nchi_deg = {chi}\nfwhm_arcsec = 1.8\n"
        );
    }
    let scene_path = dir.join("moptop.scene.toml");
    std::fs::write(&scene_path, scene).unwrap();
    let out = dir.join("sim");
    let (code, _, err) = run(&["simulate".as_ref(), scene_path.as_os_str(), "--out".as_ref(), out.as_os_str()]);
    assert_eq!(code, 0, "{err}");
    assert!(!out.join("bias").exists(), "level-1 frames need no bias frames");
    let archive = dir.join("archive");
    std::fs::create_dir(&archive).unwrap();
    let mut files = Vec::new();
    for k in 0..32 {
        let (turn, pos) = (k / 16 + 1, k % 16 + 1);
        for (cam, arc) in [(1, SWEEP_DEG), (2, 22.5)] {
            let from = out.join(format!("frame_{k:02}_hwp{:05.1}_CAM{cam}.fits", middle_deg(pos)));
            let to = archive.join(format!("{}_e_20240315_7_{turn}_{pos}_1.fits", cam + 2));
            std::fs::rename(&from, &to).unwrap_or_else(|e| panic!("{}: {e}", from.display()));
            set_cards(
                &to,
                &[
                    ("INSTRUME", "'Moptop'".into()),
                    ("MOPCNUM", cam.to_string()),
                    ("MOPRNUM", turn.to_string()),
                    ("MOPRPOS", pos.to_string()),
                    ("MOPRARC", arc.to_string()),
                    ("MOPRRATE", "4.5".into()),
                    ("L1DARK", "'dark_master.fits'".into()),
                    ("L1FLAT", "'flat_master_R.fits'".into()),
                    ("CTYPE1", "'RA---TAN'".into()),
                    ("CTYPE2", "'DEC--TAN'".into()),
                    ("CRPIX1", CRPIX.0.to_string()),
                    ("CRPIX2", CRPIX.1.to_string()),
                    ("CRVAL1", CRVAL.0.to_string()),
                    ("CRVAL2", CRVAL.1.to_string()),
                    ("CD1_1", format!("{:e}", cd()[0][0])),
                    ("CD1_2", format!("{:e}", cd()[0][1])),
                    ("CD2_1", format!("{:e}", cd()[1][0])),
                    ("CD2_2", format!("{:e}", cd()[1][1])),
                    ("CROTA1", CROTA_DEG.to_string()),
                    ("ROTSKYPA", (-CROTA_DEG).to_string()),
                ],
            );
            files.push(to);
        }
    }
    // As `ls archive/*.fits` lists them: by name, every camera-1 file first.
    files.sort();
    assert!(files[..32].iter().all(|f| f.file_name().unwrap().to_string_lossy().starts_with("3_e_")));
    files
}

fn catalog(files: &[PathBuf], extra: &[&str]) -> (i32, String, String) {
    let mut args: Vec<std::ffi::OsString> = vec!["catalog".into()];
    args.extend(files.iter().map(|f| f.clone().into_os_string()));
    args.extend(["--instrument", "moptop"].iter().chain(extra).map(|a| a.into()));
    run(&args)
}

/// The must-show: the archive's frames in glob order, read by the built-in `moptop` as it is:
/// 64 files grouped into 32 exposures (reported), the plate ranges from MOPRBEG/MOPREND (16
/// positions of 18.2 deg, whatever MOPRARC says), the unmirrored camera map measured from the
/// stars (at least 36 of the 40 stars, residual below 0.2 px, the true map to 0.1 px at the
/// corners), every star's q, u within its errors of the simulator's (RMS pull near 1, none
/// beyond 4) and its RA, Dec from camera 1's WCS; without --instrument, INSTRUME names the file.
#[test]
fn archive_frames_in_glob_order_are_read_by_the_builtin_moptop() {
    let dir = tempfile::tempdir().unwrap();
    let files = archive_frames(dir.path());
    let (code, out, err) = catalog(&files, &["--json"]);
    assert_eq!(code, 0, "{err}");
    let cat: serde_json::Value = serde_json::from_str(&out).unwrap();
    let g = &cat["grouping"];
    assert_eq!((g["files"].as_u64(), g["exposures"].as_u64()), (Some(64), Some(32)), "{g}");
    assert_eq!(g["exposure_keywords"], serde_json::json!(["MOPRNUM", "MOPRPOS"]));
    assert_eq!(g["chip_keyword"], "MOPCNUM");
    let hwp: Vec<f64> = cat["hwp_deg"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    let want: Vec<f64> = (1..=16).map(middle_deg).collect();
    assert_eq!(hwp.len(), 16, "each position once (two turns summed): {hwp:?}");
    assert!(hwp.iter().zip(&want).all(|(a, b)| (a - b).abs() < 1e-9), "each position's middle: {hwp:?}");
    let ct = &cat["camera_transform"];
    let (rms, pairs) = (ct["residual_rms_px"].as_f64().unwrap(), ct["pairs"].as_u64().unwrap());
    assert!(rms < 0.2 && pairs >= 36, "camera map from {pairs} pairs, residual {rms} px");
    let m: Vec<f64> = ct["transform"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    let t = camera_map();
    for (u, v) in [(0.0, 0.0), (1023.0, 0.0), (0.0, 1023.0), (1023.0, 1023.0), STAR_CAM1] {
        let (x, y) = (m[0] * u + m[1] * v + m[2], m[3] * u + m[4] * v + m[5]);
        let (tx, ty) = (t[0] * u + t[1] * v + t[2], t[3] * u + t[4] * v + t[5]);
        assert!((x - tx).abs() < 0.1 && (y - ty).abs() < 0.1, "({u}, {v}) -> ({x}, {y}), truth ({tx}, {ty})");
    }
    let rows = cat["rows"].as_array().unwrap();
    let mut pulls = Vec::new();
    for (x, y, p, chi, _) in stars() {
        let num = |r: &serde_json::Value, k: &str| r[k].as_f64().unwrap_or(f64::NAN);
        let r = rows
            .iter()
            .find(|r| (num(r, "x") - x).hypot(num(r, "y") - y) < 1.5 && num(r, "q").is_finite())
            .unwrap_or_else(|| panic!("star ({x}, {y}) not measured"));
        let (q0, u0) = (p * (2.0 * chi.to_radians()).cos(), p * (2.0 * chi.to_radians()).sin());
        let (pq, pu) = ((num(r, "q") - q0) / num(r, "sigma_q"), (num(r, "u") - u0) / num(r, "sigma_u"));
        assert!(pq.abs() < 4.0 && pu.abs() < 4.0, "star ({x}, {y}): q {} vs {q0}, u {} vs {u0}", r["q"], r["u"]);
        pulls.extend([pq, pu]);
    }
    let rms_pull = (pulls.iter().map(|p| p * p).sum::<f64>() / pulls.len() as f64).sqrt();
    // RA, Dec from camera 1's WCS: a star's distance from CRVAL on the sky is atan of its
    // projected distance (the gnomonic projection's closed form), and its position angle the
    // direction the CD matrix gives its pixel offset.
    let mut with_sky = 0;
    for r in rows.iter().filter(|r| r["ra_deg"].is_number()) {
        let (ra, dec) = (r["ra_deg"].as_f64().unwrap().to_radians(), r["dec_deg"].as_f64().unwrap().to_radians());
        let (a0, d0) = (CRVAL.0.to_radians(), CRVAL.1.to_radians());
        let (dx, dy) = (r["x"].as_f64().unwrap() + 1.0 - CRPIX.0, r["y"].as_f64().unwrap() + 1.0 - CRPIX.1);
        let m = cd();
        let (xi, eta) = (m[0][0] * dx + m[0][1] * dy, m[1][0] * dx + m[1][1] * dy);
        let sep = (d0.sin() * dec.sin() + d0.cos() * dec.cos() * (ra - a0).cos()).acos();
        let want = xi.hypot(eta).to_radians().atan();
        assert!((sep - want).abs().to_degrees() * 3600.0 < 1e-4, "separation {sep} vs {want}");
        let pa = ((ra - a0).sin() * dec.cos()).atan2(d0.cos() * dec.sin() - d0.sin() * dec.cos() * (ra - a0).cos());
        let d_pa = (pa - xi.atan2(eta)).to_degrees().rem_euclid(360.0);
        assert!(d_pa.min(360.0 - d_pa) < 1e-6, "position angle {} vs {}", pa.to_degrees(), xi.atan2(eta).to_degrees());
        with_sky += 1;
    }
    assert_eq!(with_sky, rows.len(), "every row has its RA, Dec");
    eprintln!("MOPTOP archive frames: camera map residual {rms:.3} px from {pairs} pairs; RMS pull {rms_pull:.2}");
    assert!(rms_pull > 0.6 && rms_pull < 1.4, "RMS pull {rms_pull}");

    // Without --instrument the frames' INSTRUME = 'Moptop' names the built-in file, and the
    // console says how the files were grouped.
    let mut args: Vec<std::ffi::OsString> = vec!["catalog".into()];
    args.extend(files.iter().map(|f| f.clone().into_os_string()));
    let (code, out, err) = run(&args);
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("read as the built-in instrument moptop (INSTRUME = 'Moptop'"), "{err}");
    assert!(out.contains("64 chip files grouped into 32 exposures by MOPRNUM, MOPRPOS (chip by MOPCNUM)"), "{out}");
}

/// The same archive's mistakes, each refused with exit 2 naming the file: a camera-1 file whose
/// camera-2 partner is missing, a second file of one camera and exposure; and `reduce --bias` on level-1 frames
/// (bias corrected already) refused unless `--correct-again`.
#[test]
fn archive_mistakes_are_refused_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let files = archive_frames(dir.path());
    let lone = files.iter().position(|f| f.ends_with("4_e_20240315_7_2_5_1.fits")).unwrap();
    let mut short = files.clone();
    short.remove(lone);
    let (code, _, err) = catalog(&short, &[]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("3_e_20240315_7_2_5_1.fits") && err.contains("no file of chip CAM2"), "{err}");
    // A camera file and another of the same camera and exposure (its copy, one card changed).
    let copy = dir.path().join("archive/3_e_20240315_7_1_3_1_copy.fits");
    std::fs::copy(dir.path().join("archive/3_e_20240315_7_1_3_1.fits"), &copy).unwrap();
    set_cards(&copy, &[("EXPID", "'copy'".into())]);
    let mut twice = files.clone();
    twice.push(copy);
    let (code, _, err) = catalog(&twice, &[]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("3_e_20240315_7_1_3_1_copy.fits") && err.contains("MOPRNUM = 1, MOPRPOS = 3 again"), "{err}");
    let map = dir.path().join("map.fits");
    let bias = dir.path().join("bias.fits");
    std::fs::write(&bias, b"not read").unwrap();
    let reduce = |extra: &[&str]| {
        let mut args: Vec<std::ffi::OsString> = vec!["reduce".into()];
        args.extend(files.iter().map(|f| f.clone().into_os_string()));
        for a in ["--instrument", "moptop", "--out", map.to_str().unwrap(), "--bias", bias.to_str().unwrap()]
            .iter()
            .chain(extra)
        {
            args.push(a.into());
        }
        run(&args)
    };
    let (code, _, err) = reduce(&[]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("already bias corrected") && err.contains("--correct-again"), "{err}");
    let (code, _, err) = reduce(&["--correct-again"]);
    assert_eq!(code, 2, "{err}");
    assert!(!err.contains("already bias corrected") && err.contains("bias.fits"), "asked again: {err}");
    assert!(!map.exists());
}
