//! FORS2-format raw frames: two chip files per exposure, prescan and
//! overscan, a bias level with a pattern, a flat-field pattern and 2x2 binning keywords, made
//! from known pixel values (`common::raw`). Reduced with a master bias and a master flat made by
//! `instpol master-bias` / `master-flat`, the Stokes map is the known sky's (Q0, U0) within the
//! bins' errors, and the intensity is the known I0 (the flat removed). Without --bias the
//! overscan still corrects the bias level; with an instrument that does not subtract the
//! overscan, the frames are refused, never reduced silently.

use crate::common;

use common::raw::{fors2_tiny_text, write_raw_set, I0, Q0, U0};
use common::run;

fn s(p: &std::path::Path) -> String {
    p.display().to_string()
}

/// The shrunk FORS2 instrument written to `d` (its path) and loaded.
fn tiny_instrument(d: &std::path::Path) -> (std::path::PathBuf, instrument::Instrument) {
    let p = d.join("fors2_tiny.toml");
    std::fs::write(&p, fors2_tiny_text()).unwrap();
    (p, common::raw::fors2_tiny())
}

#[test]
fn fors2_raw_frames_with_master_bias_and_flat_give_the_known_sky() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (inst_path, inst) = tiny_instrument(d);
    let set = write_raw_set(d, &inst);
    let ip = s(&inst_path);
    let mut a = vec!["master-bias".to_string()];
    a.extend(set.bias.iter().map(|p| s(p)));
    a.extend(["--instrument".into(), ip.clone(), "--out".into(), s(&d.join("BIAS.fits"))]);
    let (code, _, err) = run(&a);
    assert_eq!(code, 0, "{err}");
    let mut a = vec!["master-flat".to_string()];
    a.extend(set.flats.iter().map(|p| s(p)));
    a.extend(["--instrument".into(), ip.clone(), "--bias".into(), s(&d.join("BIAS.fits"))]);
    a.extend(["--out".into(), s(&d.join("FLAT.fits"))]);
    let (code, _, err) = run(&a);
    assert_eq!(code, 0, "{err}");

    // The master flat is the known pattern (normalized to its median), to the noise of 3
    // flats of 30000 e- (0.35% per pixel).
    let mf: Vec<f64> = {
        let mut f = fitsio::FitsFile::open(d.join("FLAT.fits")).unwrap();
        let h = f.primary_hdu().unwrap();
        assert_eq!(h.read_key::<String>(&mut f, "INSTRUME").unwrap(), "FORS2");
        let v: Vec<f32> = h.read_image(&mut f).unwrap();
        v.into_iter().map(f64::from).collect()
    };
    let truth = common::raw::flat(&inst);
    let gap = |p: usize| (32..36).contains(&(p / 64));
    let mut tm: Vec<f64> = truth.iter().enumerate().filter(|(p, _)| !gap(*p)).map(|(_, v)| *v).collect();
    let tmed = stokes::stats::robust::median(&mut tm, stokes::stats::robust::Middle::Mean);
    let mut dev = 0.0f64;
    for (p, (m, t)) in mf.iter().zip(&truth).enumerate() {
        if gap(p) {
            assert!(m.is_nan(), "gap pixel {p} of the master flat is {m}");
        } else {
            dev = dev.max((m - t / tmed).abs());
        }
    }
    assert!(dev < 0.02, "master flat off the known pattern by {dev}");

    // Reduce with both masters: the known sky within errors, the known intensity.
    let reduce = |extra: &[String], out: &str| -> (i32, String) {
        let mut a = vec!["reduce".to_string()];
        a.extend(set.science.iter().map(|p| s(p)));
        a.extend(["--instrument".into(), ip.clone(), "--bin".into(), "8".into(), "--out".into(), s(&d.join(out))]);
        a.extend(extra.iter().cloned());
        let (code, _, err) = run(&a);
        (code, err)
    };
    let masters = ["--bias".to_string(), s(&d.join("BIAS.fits")), "--flat".into(), s(&d.join("FLAT.fits"))];
    let (code, err) = reduce(&masters, "map.fits");
    assert_eq!(code, 0, "{err}");
    let m = skyfield::StokesMap::read_fits(&d.join("map.fits")).unwrap();
    check_sky(&m, true);

    // Without --bias and --flat: the overscan still removes the bias level (Q, U right), the
    // flat pattern stays in the intensity.
    let (code, err) = reduce(&[], "map_noflat.fits");
    assert_eq!(code, 0, "{err}");
    let m = skyfield::StokesMap::read_fits(&d.join("map_noflat.fits")).unwrap();
    check_sky(&m, false);

    // An instrument that does not subtract the overscan: frames still carrying their bias are
    // refused (naming the file and the level), never reduced silently.
    let no_scan = fors2_tiny_text().replace(
        "read_noise_e = \"HIERARCH ESO DET OUT1 RON\"",
        "read_noise_e = \"HIERARCH ESO DET OUT1 RON\"\nsubtract_overscan = false",
    );
    std::fs::write(&inst_path, no_scan).unwrap();
    let (code, err) = reduce(&[], "map_refused.fits");
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("sci0_CHIP1.fits") && err.contains("still carries its bias") && err.contains("--bias"),
        "{err}"
    );
    assert!(!d.join("map_refused.fits").exists());
    // ... and with the master bias they reduce to the same sky.
    let (code, err) = reduce(&masters, "map_bias_only.fits");
    assert_eq!(code, 0, "{err}");
    check_sky(&skyfield::StokesMap::read_fits(&d.join("map_bias_only.fits")).unwrap(), true);
}

/// Every valid bin within 5 sigma of (Q0, U0), their mean within 4 standard errors; with the
/// flat removed, the intensity (f_O + f_E) is uniform within 1% over the bins, else it carries
/// the flat's +-8% pattern.
fn check_sky(m: &skyfield::StokesMap, flat_removed: bool) {
    let v: Vec<usize> = (0..m.q.len()).filter(|&k| m.valid[k]).collect();
    assert!(v.len() >= 15, "{} valid bins", v.len());
    let (mut sq, mut su) = (0.0, 0.0);
    for &k in &v {
        assert!((m.q[k] - Q0).abs() < 5.0 * m.sigma_q[k], "bin {k}: Q {} +- {}", m.q[k], m.sigma_q[k]);
        assert!((m.u[k] - U0).abs() < 5.0 * m.sigma_u[k], "bin {k}: U {} +- {}", m.u[k], m.sigma_u[k]);
        sq += m.q[k];
        su += m.u[k];
    }
    let n = v.len() as f64;
    let se = v.iter().map(|&k| m.sigma_q[k]).sum::<f64>() / n / n.sqrt();
    assert!((sq / n - Q0).abs() < 4.0 * se && (su / n - U0).abs() < 4.0 * se, "mean Q {} U {}", sq / n, su / n);
    // A master flat is normalized to its median, so the intensity is I0 times a constant: flat
    // means I0's uniformity across the bins (and that constant is near 1).
    let mut iv: Vec<f64> = v.iter().map(|&k| m.intensity[k]).collect();
    let med = stokes::stats::robust::median(&mut iv, stokes::stats::robust::Middle::Mean);
    assert!((med / I0 - 1.0).abs() < 0.03, "median intensity {med} vs I0 {I0}");
    let worst = v.iter().map(|&k| (m.intensity[k] / med - 1.0).abs()).fold(0.0, f64::max);
    if flat_removed {
        assert!(worst < 0.01, "intensity off I0 by {worst}");
    } else {
        assert!(worst > 0.02, "the flat pattern should show without --flat: {worst}");
    }
}

/// EFOSC2 (shrunk): its 12 extra rows and columns are no usable overscan (EFOSC2 manual), so
/// the instrument declares the raw bias level instead: frames whose darkest pixels sit at it
/// are refused without a master bias, and reduce to the known sky with one.
#[test]
fn efosc2_frames_without_a_master_bias_are_refused() {
    use sim::raw::{write_raw_exposure, RawChip, RawExposure};
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let text = common::raw::efosc2_tiny_text();
    let ip = d.join("efosc2_tiny.toml");
    std::fs::write(&ip, &text).unwrap();
    let inst = instrument::Instrument::from_toml_str(&text, &ip).unwrap();
    let chip = [RawChip { bias_adu: 221.0, gain_e_per_adu: 1.18, read_noise_e: 11.0, scan: [0; 4] }];
    let mut sci = Vec::new();
    for (k, &a) in common::raw::ANGLES.iter().enumerate() {
        let e = common::raw::sky_electrons(&inst, a);
        let x = RawExposure {
            electrons: &e,
            hwp_deg: Some(a),
            filter: "V".into(),
            exptime_s: 5.0,
            exposure_no: k as i64,
            binning: None,
        };
        sci.extend(write_raw_exposure(&inst, &x, None, None, &chip, true, k as u64, d, &format!("e{k}")).unwrap());
    }
    let zero = vec![0.0; 64 * 64];
    let mut bias = Vec::new();
    for k in 0..4 {
        let x = RawExposure {
            electrons: &zero,
            hwp_deg: None,
            filter: "V".into(),
            exptime_s: 0.0,
            exposure_no: 9,
            binning: None,
        };
        bias.extend(write_raw_exposure(&inst, &x, None, None, &chip, false, 50 + k, d, &format!("b{k}")).unwrap());
    }
    let run_reduce = |extra: &[String]| {
        let mut a = vec!["reduce".to_string()];
        a.extend(sci.iter().map(|p| s(p)));
        a.extend(["--instrument".into(), s(&ip), "--bin".into(), "8".into(), "--out".into(), s(&d.join("m.fits"))]);
        a.extend(extra.iter().cloned());
        run(&a)
    };
    // Refused: the (unused) overscan sits at the bias level.
    let (code, _, err) = run_reduce(&[]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("e0_CCD40.fits") && err.contains("still carries its bias level") && err.contains("--bias"),
        "{err}"
    );
    // Refused also with no overscan at all: the darkest pixels (behind the mask) sit at the
    // declared raw bias.
    let bare: String = text.lines().filter(|l| !l.starts_with("overscan_")).collect::<Vec<_>>().join("\n");
    let bare_path = d.join("bare.toml");
    std::fs::write(&bare_path, &bare).unwrap();
    let bare_inst = instrument::Instrument::from_toml_str(&bare, &bare_path).unwrap();
    let e = common::raw::sky_electrons(&bare_inst, 0.0);
    let x = RawExposure {
        electrons: &e,
        hwp_deg: Some(0.0),
        filter: "V".into(),
        exptime_s: 5.0,
        exposure_no: 0,
        binning: None,
    };
    let f = write_raw_exposure(&bare_inst, &x, None, None, &chip, true, 7, d, "bare").unwrap();
    let (code, _, err) = run(&["reduce", &s(&f[0]), "--instrument", &s(&bare_path), "--out", &s(&d.join("x.fits"))]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("bare_CCD40.fits") && err.contains("raw bias of 220 ADU") && err.contains("--bias"), "{err}");
    let mut a = vec!["master-bias".to_string()];
    a.extend(bias.iter().map(|p| s(p)));
    a.extend(["--instrument".into(), s(&ip), "--out".into(), s(&d.join("B.fits"))]);
    let (code, _, err) = run(&a);
    assert_eq!(code, 0, "{err}");
    let (code, _, err) = run_reduce(&["--bias".into(), s(&d.join("B.fits"))]);
    assert_eq!(code, 0, "{err}");
    let m = skyfield::StokesMap::read_fits(&d.join("m.fits")).unwrap();
    let v: Vec<usize> = (0..m.q.len()).filter(|&k| m.valid[k]).collect();
    assert!(v.len() >= 10);
    for &k in &v {
        assert!((m.q[k] - Q0).abs() < 5.0 * m.sigma_q[k] && (m.u[k] - U0).abs() < 5.0 * m.sigma_u[k], "bin {k}");
    }
}

/// Chip files whose every prescan/overscan pixel is NaN (the file's only record of its 200 ADU
/// bias level): refused, naming the file and the regions, where the frames were reduced with
/// the bias in them (P 1.96 % at 33.0 deg for 2 % at 31.8 deg, exit 0). The same frames with
/// their scan pixels intact reduce.
/// The four exposures of the known sky as FORS2 chip files (two per exposure, F32, with scan
/// regions), in exposure order: `sci{k}_CHIP1`, `sci{k}_CHIP2`.
fn chip_exposures(d: &std::path::Path, inst: &instrument::Instrument) -> Vec<std::path::PathBuf> {
    use sim::raw::{write_chip_files, Readout};
    use skyfield::fits::{Bitpix, KeyValue};
    let mut files = Vec::new();
    for (k, &a) in common::raw::ANGLES.iter().enumerate() {
        let e = common::raw::sky_electrons(inst, a);
        let keys = vec![
            (inst.polarimetry.hwp_angle_keyword.clone(), KeyValue::F64(a), String::new()),
            (inst.polarimetry.filter_keyword.clone(), KeyValue::Str("v_HIGH".into()), String::new()),
            (inst.polarimetry.exptime_keyword.clone(), KeyValue::F64(10.0), String::new()),
        ];
        let readout = Readout { chips: &common::raw::CHIPS, exposure_no: k as i64, binning: None, bitpix: Bitpix::F32 };
        let mut rng = <rand_xoshiro::Xoshiro256PlusPlus as rand::SeedableRng>::seed_from_u64(k as u64);
        files.extend(
            write_chip_files(inst, &readout, &keys, true, &mut rng, d, &format!("sci{k}"), &mut |c, p, _| {
                e[p] / common::raw::CHIPS[c].gain_e_per_adu
            })
            .unwrap(),
        );
    }
    files
}

#[test]
fn chip_files_with_no_usable_overscan_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ip, inst) = tiny_instrument(d);
    let files = chip_exposures(d, &inst);
    let reduce = |out: &str| {
        let mut a = vec!["reduce".to_string(), "--instrument".into(), s(&ip), "--bin".into(), "8".into()];
        a.extend(["--out".into(), s(&d.join(out))]);
        a.extend(files.iter().map(|p| s(p)));
        run(&a)
    };
    let (code, _, err) = reduce("good.fits");
    assert_eq!(code, 0, "{err}");
    // Blank the 5 prescan and 5 overscan rows (64 px each) of the first chip file.
    {
        let mut f = fitsio::FitsFile::edit(&files[0]).unwrap();
        let hdu = f.primary_hdu().unwrap();
        let mut img: Vec<f32> = hdu.read_image(&mut f).unwrap();
        let rny = img.len() / 64;
        for (i, v) in img.iter_mut().enumerate() {
            let y = i / 64;
            if y < 5 || y >= rny - 5 {
                *v = f32::NAN;
            }
        }
        hdu.write_image(&mut f, &img).unwrap();
    }
    let (code, _, err) = reduce("bad.fits");
    assert_eq!(code, 2, "{err}");
    let name = files[0].file_name().unwrap().to_str().unwrap();
    assert!(err.contains(name) && err.contains("640 prescan/overscan pixels"), "{err}");
    assert!(!d.join("bad.fits").exists());
}

/// A saturated pixel of the second chip is reported with that chip's file: the reduction
/// counts bad pixels per exposure, so the note names every chip file of the exposure (it
/// named only the first, CHIP1, for a pixel of CHIP2).
#[test]
fn a_saturated_pixel_of_chip_2_is_reported_with_its_file() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ip, inst) = tiny_instrument(d);
    let files = chip_exposures(d, &inst);
    let chip2 = &files[1];
    assert!(s(chip2).contains("CHIP2"), "{}", chip2.display());
    {
        let mut f = fitsio::FitsFile::edit(chip2).unwrap();
        let hdu = f.primary_hdu().unwrap();
        let mut img: Vec<f32> = hdu.read_image(&mut f).unwrap();
        // A pixel well inside the image area (5 prescan rows and columns).
        img[20 * 64 + 20] = 1.0e7;
        hdu.write_image(&mut f, &img).unwrap();
    }
    let mut a = vec!["reduce".to_string(), "--instrument".into(), s(&ip), "--bin".into(), "8".into()];
    a.extend(["--out".into(), s(&d.join("map.fits"))]);
    a.extend(files.iter().map(|p| s(p)));
    let (code, _, err) = run(&a);
    assert_eq!(code, 0, "{err}");
    // One note, in the CHIP2 file alone, counting the one pixel (the frames are read from
    // disk by rows, counted per exposure there, and counted again per chip for the note).
    let lines: Vec<&str> = err.lines().filter(|l| l.contains("saturated")).collect();
    assert_eq!(lines.len(), 1, "{err}");
    assert!(lines[0].contains(chip2.file_name().unwrap().to_str().unwrap()), "{}", lines[0]);
    assert!(!lines[0].contains(files[0].file_name().unwrap().to_str().unwrap()), "{}", lines[0]);
    assert!(lines[0].contains(" 1 saturated pixels"), "{}", lines[0]);
}

/// A master flat records its filter and is used only for frames of that filter: flats of two
/// filters are not combined (naming both files and filters), the flat records FILTER =
/// 'R_SPECIAL' in its header, and `reduce` refuses that R flat for the v_HIGH frames, where it
/// took it without a word.
#[test]
fn master_flats_carry_their_filter_and_are_matched_to_the_frames() {
    use sim::raw::{write_raw_exposure, RawExposure};
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (inst_path, inst) = tiny_instrument(d);
    let set = write_raw_set(d, &inst);
    let ip = s(&inst_path);
    let lamp = vec![30000.0; inst.detector.nx * inst.detector.ny];
    let mut r_flats = Vec::new();
    for k in 0..3 {
        let x = RawExposure {
            electrons: &lamp,
            hwp_deg: Some(0.0),
            filter: "R_SPECIAL".into(),
            exptime_s: 1.0,
            exposure_no: 40 + k,
            binning: None,
        };
        r_flats.extend(
            write_raw_exposure(
                &inst,
                &x,
                None,
                None,
                &common::raw::CHIPS,
                true,
                400 + k as u64,
                d,
                &format!("rflat{k}"),
            )
            .unwrap(),
        );
    }
    let master_flat = |flats: &[std::path::PathBuf], out: &str| {
        let mut a = vec!["master-flat".to_string()];
        a.extend(flats.iter().map(|p| s(p)));
        a.extend(["--instrument".into(), ip.clone(), "--out".into(), s(&d.join(out))]);
        run(&a)
    };
    let mixed: Vec<_> = set.flats.iter().chain(&r_flats).cloned().collect();
    let (code, _, err) = master_flat(&mixed, "MIXED.fits");
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("v_HIGH") && err.contains("R_SPECIAL") && err.contains("rflat0"), "{err}");
    assert!(!d.join("MIXED.fits").exists());
    let (code, _, err) = master_flat(&r_flats, "RFLAT.fits");
    assert_eq!(code, 0, "{err}");
    let mut f = fitsio::FitsFile::open(d.join("RFLAT.fits")).unwrap();
    let h = f.primary_hdu().unwrap();
    assert_eq!(h.read_key::<String>(&mut f, "HIERARCH INSTPOL FILTER").unwrap(), "R_SPECIAL");
    let mut a = vec!["reduce".to_string(), "--instrument".into(), ip.clone(), "--bin".into(), "8".into()];
    a.extend(["--flat".into(), s(&d.join("RFLAT.fits")), "--out".into(), s(&d.join("m.fits"))]);
    a.extend(set.science.iter().map(|p| s(p)));
    let (code, _, err) = run(&a);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("RFLAT.fits") && err.contains("R_SPECIAL") && err.contains("v_HIGH"), "{err}");
}

/// A master records the binning and the chips of its frames (the instrument file's
/// `binning = [2, 2]` and chips CHIP1, CHIP2, as read from the file's text here), and `reduce`
/// refuses a master whose binning or chips are not those its instrument file reads the frames
/// with: frames binned 1 x 1 read through a 1 x 1 instrument file of the same size took the
/// 2 x 2 master without a word.
#[test]
fn masters_carry_their_binning_and_chips_and_are_matched_to_the_frames() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (inst_path, inst) = tiny_instrument(d);
    let text = fors2_tiny_text();
    assert!(
        text.contains("binning = [2, 2]") && text.contains("name = \"CHIP1\"") && text.contains("name = \"CHIP2\"")
    );
    let set = write_raw_set(d, &inst);
    let mut a = vec!["master-bias".to_string()];
    a.extend(set.bias.iter().map(|p| s(p)));
    a.extend(["--instrument".into(), s(&inst_path), "--out".into(), s(&d.join("BIAS.fits"))]);
    let (code, _, err) = run(&a);
    assert_eq!(code, 0, "{err}");
    let mut f = fitsio::FitsFile::open(d.join("BIAS.fits")).unwrap();
    let h = f.primary_hdu().unwrap();
    assert_eq!(h.read_key::<String>(&mut f, "HIERARCH INSTPOL BINNING").unwrap(), "2x2");
    assert_eq!(h.read_key::<String>(&mut f, "HIERARCH INSTPOL CHIPS").unwrap(), "CHIP1,CHIP2");
    // The same frames through their own instrument file take the master.
    let reduce = |ip: &std::path::Path, frames: &[std::path::PathBuf], out: &str| {
        let mut a = vec!["reduce".to_string(), "--instrument".into(), s(ip), "--bin".into(), "8".into()];
        a.extend(["--bias".into(), s(&d.join("BIAS.fits")), "--out".into(), s(&d.join(out))]);
        a.extend(frames.iter().map(|p| s(p)));
        run(&a)
    };
    let (code, _, err) = reduce(&inst_path, &set.science, "ok.fits");
    assert_eq!(code, 0, "{err}");
    // Frames binned 1 x 1, read through a 1 x 1 instrument file of the same size.
    let sub = d.join("bin1");
    std::fs::create_dir(&sub).unwrap();
    let ip1 = sub.join("fors2_1x1.toml");
    std::fs::write(&ip1, text.replace("binning = [2, 2]", "binning = [1, 1]")).unwrap();
    let inst1 = instrument::Instrument::from_file(&ip1).unwrap();
    let set1 = write_raw_set(&sub, &inst1);
    let (code, _, err) = reduce(&ip1, &set1.science, "bin1.fits");
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("BIAS.fits") && err.contains("BINNING 2x2") && err.contains("1x1"), "{err}");
    assert!(!d.join("bin1.fits").exists());
    // An instrument file whose chips are others (renamed here) refuses it too.
    let ipc = sub.join("fors2_chips.toml");
    std::fs::write(&ipc, text.replace("name = \"CHIP2\"", "name = \"CHIPB\"")).unwrap();
    let (code, _, err) = reduce(&ipc, &set.science, "chips.fits");
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("BIAS.fits") && err.contains("CHIPS CHIP1,CHIP2") && err.contains("CHIP1,CHIPB"), "{err}");
}

/// Pre/overscan sizes that are wrong but add up (7 + 3 rows for the chip's 5 + 5): two
/// image rows fall in the "prescan" and the bias was taken from them, with the light in it
/// (on sky frames q came out 16 % low, exit 0). The scan rows that hold light are seen and the
/// files refused, naming the row; with the right keywords the same files combine. (Flats:
/// light on every image row, so the two rows moved into the prescan hold light whatever the
/// mask.)
#[test]
fn scan_regions_that_hold_light_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ip, inst) = tiny_instrument(d);
    let set = write_raw_set(d, &inst);
    let flat = |out: &str| {
        let mut a = vec!["master-flat".to_string(), "--instrument".into(), s(&ip)];
        a.extend(["--out".into(), s(&d.join(out))]);
        a.extend(set.flats.iter().map(|p| s(p)));
        run(&a)
    };
    let (code, _, err) = flat("good.fits");
    assert_eq!(code, 0, "{err}");
    // The instrument file's scan sizes given as numbers that add up but are wrong.
    let wrong = fors2_tiny_text()
        .replace("prescan_y = \"HIERARCH ESO DET OUT1 PRSCY\"", "prescan_y = 7")
        .replace("overscan_y = \"HIERARCH ESO DET OUT1 OVSCY\"", "overscan_y = 3");
    assert_ne!(wrong, fors2_tiny_text());
    std::fs::write(&ip, wrong).unwrap();
    let (code, _, err) = flat("bad.fits");
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("flat0_") && err.contains("holds light") && err.contains("7 + 3 rows"), "{err}");
}

/// The same along x: frames written with 4 + 4 prescan/overscan columns, read by an instrument
/// file that says 6 + 2. Two image columns fall in the "prescan" and are seen holding light;
/// with the sizes they were written with the same files combine.
#[test]
fn scan_columns_that_hold_light_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let with_columns = |pre: u32, over: u32| {
        fors2_tiny_text()
            .replace("prescan_x = \"HIERARCH ESO DET OUT1 PRSCX\"", &format!("prescan_x = {pre}"))
            .replace("overscan_x = \"HIERARCH ESO DET OUT1 OVSCX\"", &format!("overscan_x = {over}"))
    };
    let written = with_columns(4, 4);
    assert_ne!(written, fors2_tiny_text());
    let inst = instrument::Instrument::from_toml_str(&written, std::path::Path::new("x.toml")).unwrap();
    let set = write_raw_set(d, &inst);
    let ip = d.join("inst.toml");
    let flat = |text: String, out: &str| {
        std::fs::write(&ip, text).unwrap();
        let mut a = vec!["master-flat".to_string(), "--instrument".into(), s(&ip)];
        a.extend(["--out".into(), s(&d.join(out))]);
        a.extend(set.flats.iter().map(|p| s(p)));
        run(&a)
    };
    let (code, _, err) = flat(written.clone(), "good.fits");
    assert_eq!(code, 0, "{err}");
    let (code, _, err) = flat(with_columns(6, 2), "bad.fits");
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("flat0_") && err.contains("column 4") && err.contains("holds light"), "{err}");
}
