//! `instpol correct` end to end: catalogs (CSV and FITS tables) and Stokes maps corrected with a
//! calibration file, checked against the forward model (`M_I` of `eq:instpol`, then the HWP
//! zero angle), and the third-party FORS2 maps in /work/shared/data/fors2-instpol/.

use crate::common;

use common::V_COEFFS as V;
use fit::models::model::FieldModel;
use fit::Calibration;
use fitsio::tables::{ColumnDataType, ColumnDescription};
use fitsio::FitsFile;
use std::path::{Path, PathBuf};

const OFFSET_DEG: f64 = 1.5;

fn v_calibration() -> Calibration {
    Calibration { lambda_nm: 554.0, hwp_chi_offset_deg: OFFSET_DEG, ..common::fors1_radial_calibration("V", V) }
}

/// What the reduction reports for a star of intrinsic `(p0, chi0)` at `(x, y)` arcmin: `M_I` of
/// the field applied (`eq:instpol`), then the plate's zero angle (chi measured smaller by the
/// offset).
fn observed(cal: &Calibration, x: f64, y: f64, p0: f64, chi0: f64) -> (f64, f64) {
    let a = cal.eval(x, y);
    let (q1, u1) = fit::standards::forward(a.q, a.u, p0 * (2.0 * chi0).cos(), p0 * (2.0 * chi0).sin());
    fit::correction::correct::rotate_chi(q1, u1, -OFFSET_DEG.to_radians())
}

fn run(args: &[&str]) -> std::process::Output {
    common::instpol().args(args).output().unwrap()
}

/// `instpol correct --cal CAL --in INPUT --out OUT EXTRA...`, which must succeed.
fn correct(cal: &Path, input: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec!["correct", "--cal", cal.to_str().unwrap(), "--in", input.to_str().unwrap()];
    args.extend(["--out", out.to_str().unwrap()]);
    args.extend(extra);
    let o = run(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    o
}

fn read_csv(path: &Path) -> (Vec<String>, Vec<Vec<String>>) {
    let mut r = csv::ReaderBuilder::new().comment(Some(b'#')).from_path(path).unwrap();
    let h = r.headers().unwrap().iter().map(String::from).collect();
    let rows = r.records().map(|x| x.unwrap().iter().map(String::from).collect()).collect();
    (h, rows)
}

fn col(h: &[String], name: &str) -> usize {
    h.iter().position(|c| c == name).unwrap_or_else(|| panic!("no column {name} in {h:?}"))
}

/// A CSV catalog of a 1% star at many positions (pixel coordinates, p up to 1.36% at the
/// corners) comes back with P0 = 1% and its chi0 everywhere; every input column is kept.
#[test]
fn csv_catalog_round_trip_in_pixels() {
    let dir = tempfile::tempdir().unwrap();
    let cal = v_calibration();
    let calp = dir.path().join("v.fits");
    cal.save(&calp).unwrap();
    let mut text = String::from("# a comment line\nid,x,y,q,u,sigma_q,sigma_u,mag\n");
    let mut truth = vec![];
    let mut k = 0;
    for i in 0..7 {
        for j in 0..7 {
            let (px, py) = (2.0 + 2043.0 * i as f64 / 6.0, 2.0 + 2043.0 * j as f64 / 6.0);
            let (x, y) = ((px - 1023.5) * 0.2 / 60.0, (py - 1023.5) * 0.2 / 60.0);
            let chi0 = 0.37 * k as f64 % std::f64::consts::PI;
            let (q, u) = observed(&cal, x, y, 0.01, chi0);
            text.push_str(&format!("star{k},{px},{py},{q:e},{u:e},0.0005,0.0005,17.{k}\n"));
            truth.push(chi0);
            k += 1;
        }
    }
    let inp = dir.path().join("cat.csv");
    std::fs::write(&inp, text).unwrap();
    let out = dir.path().join("out.csv");
    let o = correct(&calp, &inp, &out, &["--coords", "pixel", "--json"]);
    let js: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(js["n_rows"], 49);
    assert_eq!(js["n_extrapolated"], 0);
    assert_eq!(js["estimator"], "mas");
    let (h, rows) = read_csv(&out);
    for c in
        ["id", "x", "y", "q", "u", "sigma_q", "sigma_u", "mag", "p0", "chi0_deg", "p0_mas", "sigma_p0", "extrapolated"]
    {
        col(&h, c);
    }
    for (r, chi0) in rows.iter().zip(&truth) {
        let f = |n: &str| r[col(&h, n)].parse::<f64>().unwrap();
        assert!((f("p0") - 0.01).abs() < 1e-9, "{r:?}");
        let d = (f("chi0_deg") - chi0.to_degrees()).rem_euclid(180.0);
        assert!(d.min(180.0 - d) < 1e-6, "chi0 {} vs {}", f("chi0_deg"), chi0.to_degrees());
        // The bias-corrected P0 at SNR 20 is a little below P0.
        assert!(f("p0_mas") < f("p0") && f("p0_mas") > 0.009);
        assert!(r[col(&h, "id")].starts_with("star") && r[col(&h, "mag")].starts_with("17."));
    }
    // The first-order method is measurably wrong at the corners (p ~ 1.4%, P0 = 1%).
    let out2 = dir.path().join("out2.csv");
    let o = run(&[
        "correct",
        "--cal",
        calp.to_str().unwrap(),
        "--in",
        inp.to_str().unwrap(),
        "--out",
        out2.to_str().unwrap(),
        "--coords",
        "pixel",
        "--method",
        "first-order",
    ]);
    assert!(o.status.success());
    let (h2, rows2) = read_csv(&out2);
    let worst = rows2.iter().map(|r| (r[col(&h2, "p0")].parse::<f64>().unwrap() - 0.01).abs()).fold(0.0, f64::max);
    assert!(worst > 3e-5, "eq:approx error at the corners {worst}");
}

/// Outside the field: exit 2 naming the line and no output file; with --allow-extrapolation a
/// warning, the row flagged and its errors inflated.
#[test]
fn outside_the_field_and_extrapolation() {
    let dir = tempfile::tempdir().unwrap();
    let calp = dir.path().join("v.fits");
    v_calibration().save(&calp).unwrap();
    let inp = dir.path().join("cat.csv");
    std::fs::write(&inp, "x,y,q,u,sigma_q,sigma_u\n1.0,1.0,0.001,0.0,1e-4,1e-4\n3.6,0.0,0.01,0.0,1e-4,1e-4\n").unwrap();
    let out = dir.path().join("out.csv");
    let args =
        ["correct", "--cal", calp.to_str().unwrap(), "--in", inp.to_str().unwrap(), "--out", out.to_str().unwrap()];
    let o = run(&args);
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.lines().any(|l| l.starts_with("error:"))
            && err.contains("row 2")
            && err.contains("outside the calibrated field"),
        "{err}"
    );
    assert!(!out.exists(), "no half-written output");
    let mut a = args.to_vec();
    a.push("--allow-extrapolation");
    let o = run(&a);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stderr).contains("warning: 1 of 2 positions"));
    let (h, rows) = read_csv(&out);
    assert_eq!(rows[0][col(&h, "extrapolated")], "0");
    assert_eq!(rows[1][col(&h, "extrapolated")], "1");
    // Inflation: the model has no coefficient covariance, so sigma_q0 ~ sqrt(1e-8 + (0.5 p)^2 ...).
    let s = rows[1][col(&h, "sigma_q0")].parse::<f64>().unwrap();
    let p = (V[0] * 3.6 + V[1] * 3.6 * 3.6 + V[2] * 3.6f64.powi(3)).abs();
    assert!(s > 0.4 * p && s < 0.7 * p, "sigma_q0 {s}, p {p}");
    // Bad input names the column and the line.
    std::fs::write(&inp, "x,y,q,u,sigma_q,sigma_u\n1.0,1.0,abc,0.0,1e-4,1e-4\n").unwrap();
    let o = run(&args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.code() == Some(2) && err.contains("line 2") && err.contains("'q'"), "{err}");
    std::fs::write(&inp, "x,y,q,u,sigma_u\n1.0,1.0,0.0,0.0,1e-4\n").unwrap();
    let err = String::from_utf8_lossy(&run(&args).stderr).to_string();
    assert!(err.contains("no column 'sigma_q'"), "{err}");
}

/// A FITS binary-table catalog: every HDU, keyword and column kept, corrected columns appended.
#[test]
fn fits_table_catalog() {
    let dir = tempfile::tempdir().unwrap();
    let cal = v_calibration();
    let calp = dir.path().join("v.fits");
    cal.save(&calp).unwrap();
    let pos = [(-3.0, -3.0), (2.5, -3.2), (0.5, 0.2), (-1.0, 2.9)];
    let (mut xs, mut ys, mut qs, mut us, mut ids) = (vec![], vec![], vec![], vec![], vec![]);
    for (k, &(x, y)) in pos.iter().enumerate() {
        let (q, u) = observed(&cal, x, y, 0.0, 0.0); // unpolarized stars
        xs.push(x);
        ys.push(y);
        qs.push(q);
        us.push(u);
        ids.push(k as i32 + 100);
    }
    let inp = dir.path().join("cat.fits");
    {
        let mut f = FitsFile::create(&inp).open().unwrap();
        f.primary_hdu().unwrap().write_key(&mut f, "OBSERVER", "test").unwrap();
        let cols: Vec<fitsio::tables::ConcreteColumnDescription> = ["ID", "X", "Y", "Q", "U", "SIGMA_Q", "SIGMA_U"]
            .iter()
            .map(|n| {
                let t = if *n == "ID" { ColumnDataType::Int } else { ColumnDataType::Double };
                ColumnDescription::new(*n).with_type(t).create().unwrap()
            })
            .collect();
        let h = f.create_table("STARS".to_string(), &cols).unwrap();
        h.write_col(&mut f, "ID", &ids).unwrap();
        for (n, v) in [("X", &xs), ("Y", &ys), ("Q", &qs), ("U", &us)] {
            h.write_col(&mut f, n, v).unwrap();
        }
        h.write_col(&mut f, "SIGMA_Q", &[1e-4; 4]).unwrap();
        h.write_col(&mut f, "SIGMA_U", &[1e-4; 4]).unwrap();
    }
    let out = dir.path().join("out.fits");
    correct(&calp, &inp, &out, &["--estimator", "as"]);
    let mut f = FitsFile::open(&out).unwrap();
    assert_eq!(f.primary_hdu().unwrap().read_key::<String>(&mut f, "OBSERVER").unwrap(), "test");
    let h = f.hdu("STARS").unwrap();
    assert_eq!(h.read_col::<i32>(&mut f, "ID").unwrap(), ids);
    let q0: Vec<f64> = h.read_col(&mut f, "q0").unwrap();
    let u0: Vec<f64> = h.read_col(&mut f, "u0").unwrap();
    let pas: Vec<f64> = h.read_col(&mut f, "p0_as").unwrap();
    let qi: Vec<f64> = h.read_col(&mut f, "q_inst").unwrap();
    for k in 0..4 {
        assert!(q0[k].abs() < 1e-12 && u0[k].abs() < 1e-12, "row {k}: {} {}", q0[k], u0[k]);
        assert_eq!(pas[k], 0.0, "as gives 0 below sigma");
        assert!(qi[k].abs() > 0.0 || pos[k].0.abs() == pos[k].1.abs());
    }
}

/// A Stokes map of an unpolarized sky seen through the V field is corrected to zero in every
/// bin, with the calibration's error added to the map's.
#[test]
fn stokes_map_corrected_bin_by_bin() {
    use skyfield::{BinGeometry, StokesMap};
    let dir = tempfile::tempdir().unwrap();
    let mut cal = v_calibration();
    cal.hwp_chi_offset_deg = 0.0;
    let calp = dir.path().join("v.fits");
    cal.save(&calp).unwrap();
    let g = BinGeometry::covering(256, 0, 0, 2048, 2048, 0.2);
    let mut m = StokesMap::empty(g.clone(), "FORS1", "V", vec![0.0, 22.5, 45.0, 67.5]);
    for j in 0..g.ny {
        for i in 0..g.nx {
            let k = j * g.nx + i;
            let (x, y) = g.centre_arcmin(i, j);
            let a = cal.eval(x, y);
            m.q[k] = a.q;
            m.u[k] = a.u;
            m.sigma_q[k] = 1e-4;
            m.sigma_u[k] = 1e-4;
            m.cov_qu[k] = 0.0;
            m.sigma_q_phot[k] = 1e-4;
            m.sigma_u_phot[k] = 1e-4;
            (m.p[k], m.chi[k]) = stokes::polarization(a.q, a.u);
            m.n_pixels[k] = 100;
            m.intensity[k] = 1e4;
            m.intensity_snr[k] = 100.0;
            m.valid[k] = k != 5;
        }
    }
    let inp = dir.path().join("map.fits");
    m.write_fits(&inp).unwrap();
    let out = dir.path().join("map_corr.fits");
    let o = correct(&calp, &inp, &out, &["--json"]);
    let js: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(js["kind"], "Stokes map");
    assert_eq!(js["n_rows"], 63);
    // A map of another filter is refused, naming both; --allow-mismatch overrides.
    let mut mb = m.clone();
    mb.filter = "B".into();
    let inb = dir.path().join("map_b.fits");
    mb.write_fits(&inb).unwrap();
    let outb = dir.path().join("map_b_corr.fits");
    let args =
        ["correct", "--cal", calp.to_str().unwrap(), "--in", inb.to_str().unwrap(), "--out", outb.to_str().unwrap()];
    let o = run(&args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.code() == Some(2) && err.contains("FORS1 B map") && err.contains("FORS1 V"), "{err}");
    assert!(!outb.exists());
    let mut a2 = args.to_vec();
    a2.push("--allow-mismatch");
    assert!(run(&a2).status.success());
    // The corrected map records what was allowed, as a corrected catalog does.
    let mismatch = StokesMap::read_fits(&outb).unwrap().product.and_then(|p| p.mismatch_allowed);
    assert_eq!(mismatch.as_deref(), Some("data FORS1 B, calibration FORS1 V"));
    let c = StokesMap::read_fits(&out).unwrap();
    let mut f = FitsFile::open(&out).unwrap();
    assert_eq!(f.primary_hdu().unwrap().read_key::<String>(&mut f, "INSTCORR").unwrap(), "v.fits");
    // The corrected map corrected again would lose the instrumental polarization twice (every
    // bin would move by -(q_i, u_i) once more): refused, naming INSTCORR, nothing written; and
    // it is no sky-field input to calibrate on either.
    let twice = dir.path().join("map_corr2.fits");
    let o = run(&[
        "correct",
        "--cal",
        calp.to_str().unwrap(),
        "--in",
        out.to_str().unwrap(),
        "--out",
        twice.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.code() == Some(2) && err.contains("INSTCORR") && err.contains("twice"), "{err}");
    assert!(!twice.exists());
    let o = run(&[
        "calibrate",
        "--map",
        out.to_str().unwrap(),
        "--sky-p",
        "0",
        "--sky-chi",
        "0",
        "--out",
        twice.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.code() == Some(2) && err.contains("INSTCORR"), "{err}");
    assert!(!twice.exists());
    for k in 0..g.len() {
        if k == 5 {
            assert!(!c.valid[k]);
            continue;
        }
        assert!(c.q[k].abs() < 1e-12 && c.u[k].abs() < 1e-12 && c.p[k] < 1e-12, "bin {k}");
        assert!(c.sigma_q[k] >= 1e-4);
    }
}

fn fors2_dir() -> Option<PathBuf> {
    crate::common::shared_data::shared_data("fors2-instpol", &["v_HIGH_inlaQ_bin10.fits"], "the FORS2 map corrections")
}

/// The real FORS2 v_HIGH maps (Gonzalez-Gaitan et al. 2020), imported as a calibration: a
/// catalog whose q, u equal the map's own instrumental values at its positions comes out with
/// q0, u0 ~ 0, and a polarized star through the map is recovered.
#[test]
fn fors2_map_calibration_corrects_its_own_instrumental_values() {
    let Some(d) = fors2_dir() else { return };
    let dir = tempfile::tempdir().unwrap();
    let calp = dir.path().join("fors2_v.fits");
    let args = common::import_fors2_v_args(&d, &calp);
    let o = run(&args.iter().map(String::as_str).collect::<Vec<_>>());
    if !o.status.success() {
        // import-map is tested on its own (tests/it/import_map.rs); say so rather than pass silently.
        panic!("instpol import-map failed (needed for this test): {}", String::from_utf8_lossy(&o.stderr));
    }
    let cal = Calibration::load(&calp).unwrap();
    let reg = cal.region;
    let mut text = String::from("x,y,q,u,sigma_q,sigma_u\n");
    let mut n = 0;
    for i in 0..25 {
        for j in 0..25 {
            let x = reg.x_min + (reg.x_max - reg.x_min) * (i as f64 + 0.5) / 25.0;
            let y = reg.y_min + (reg.y_max - reg.y_min) * (j as f64 + 0.5) / 25.0;
            if !cal.contains(x, y) {
                continue;
            }
            let a = cal.eval(x, y);
            let (q, u) = fit::correction::correct::rotate_chi(a.q, a.u, -cal.hwp_chi_offset_deg.to_radians());
            text.push_str(&format!("{x},{y},{q:e},{u:e},1e-4,1e-4\n"));
            n += 1;
        }
    }
    assert!(n > 200, "only {n} positions inside the FORS2 map");
    let inp = dir.path().join("cat.csv");
    std::fs::write(&inp, text).unwrap();
    let out = dir.path().join("out.csv");
    correct(&calp, &inp, &out, &[]);
    let (h, rows) = read_csv(&out);
    let mut pmax_inst = 0.0f64;
    for r in &rows {
        let f = |c: &str| r[col(&h, c)].parse::<f64>().unwrap();
        assert!(f("q0").abs() < 1e-12 && f("u0").abs() < 1e-12, "{r:?}");
        pmax_inst = pmax_inst.max(f("q_inst").hypot(f("u_inst")));
        // The map's own errors are propagated.
        assert!(f("sigma_q0") > 1e-4);
    }
    // Published: the FORS2 pattern reaches about 1.4% at the field edges.
    assert!(pmax_inst > 0.008 && pmax_inst < 0.03, "max instrumental p {pmax_inst}");

    // A native calibration of the same field: the radial model fitted to the same data
    // (`instpol fit`, free centre). The same catalog through it: q0, u0 are the map's
    // departures from the smooth model, at the level of the fit's own RMS residual.
    let radp = dir.path().join("fors2_v_radial.fits");
    let o = run(&["fit", calp.to_str().unwrap(), "--free-centre", "--out", radp.to_str().unwrap()]);
    assert!(o.status.success(), "instpol fit: {}", String::from_utf8_lossy(&o.stderr));
    let rad = Calibration::load(&radp).unwrap();
    let out2 = dir.path().join("out_radial.csv");
    correct(&radp, &inp, &out2, &["--allow-extrapolation"]);
    let (h2, rows2) = read_csv(&out2);
    let (mut s2, mut n2) = (0.0, 0.0);
    for (r, r2) in rows.iter().zip(&rows2) {
        let f = |c: &str| r2[col(&h2, c)].parse::<f64>().unwrap();
        let g = |c: &str| r[col(&h, c)].parse::<f64>().unwrap();
        // Both paths removed an instrumental polarization of the same size and direction.
        assert!((f("q_inst") - g("q_inst")).abs() < 0.004 && (f("u_inst") - g("u_inst")).abs() < 0.004, "{r2:?}");
        s2 += f("q0").powi(2) + f("u0").powi(2);
        n2 += 2.0;
    }
    let rms = (s2 / n2).sqrt();
    eprintln!(
        "FORS2 v_HIGH: map vs fitted radial model, RMS of corrected q0, u0 = {rms:.2e}; fit RMS residual {:.2e}",
        rad.rms_residual
    );
    assert!(rms < 2.0 * rad.rms_residual.max(2e-4), "RMS {rms} vs fit RMS residual {}", rad.rms_residual);
}

/// A catalog whose q, u already carry the instrument's HWP zero angle (the column
/// `hwp_chi_offset_deg` that `instpol catalog` writes) is not turned by it twice: with a
/// calibration of the same zero angle (3.5 deg) and no field, q0, u0 equal q, u; without the
/// column (q, u as measured) they are turned by 2 x 3.5 deg (chi + 3.5 deg), computed here.
#[test]
fn a_catalog_in_the_sky_frame_is_not_turned_twice() {
    let d = tempfile::tempdir().unwrap();
    let mut cal = common::fors1_radial_calibration("V", [0.0, 0.0, 0.0]);
    cal.hwp_chi_offset_deg = 3.5;
    let calp = d.path().join("cal.fits");
    cal.save(&calp).unwrap();
    let (q, u) = (0.02, -0.01);
    let run_one = |with_column: bool| -> (f64, f64) {
        let (head, row) = if with_column {
            ("x,y,q,u,sigma_q,sigma_u,hwp_chi_offset_deg", format!("1,1,{q},{u},0.001,0.001,3.5"))
        } else {
            ("x,y,q,u,sigma_q,sigma_u", format!("1,1,{q},{u},0.001,0.001"))
        };
        let inp = d.path().join(format!("in{with_column}.csv"));
        std::fs::write(&inp, format!("{head}\n{row}\n")).unwrap();
        let out = d.path().join(format!("out{with_column}.csv"));
        correct(&calp, &inp, &out, &[]);
        let (h, rows) = read_csv(&out);
        let get = |k: &str| rows[0][col(&h, k)].parse::<f64>().unwrap();
        (get("q0"), get("u0"))
    };
    let (q0, u0) = run_one(true);
    assert!((q0 - q).abs() < 1e-15 && (u0 - u).abs() < 1e-15, "{q0} {u0}");
    let (q0, u0) = run_one(false);
    let a = (2.0 * 3.5f64).to_radians();
    let (qr, ur) = (q * a.cos() - u * a.sin(), q * a.sin() + u * a.cos());
    assert!((q0 - qr).abs() < 1e-12 && (u0 - ur).abs() < 1e-12, "{q0} {u0} vs {qr} {ur}");
    // Rows that say different zero angles are not one catalog: refused, naming the row and the
    // column, nothing written.
    let inp = d.path().join("mixed.csv");
    std::fs::write(
        &inp,
        format!(
            "x,y,q,u,sigma_q,sigma_u,hwp_chi_offset_deg\n1,1,{q},{u},0.001,0.001,3.5\n1,1,{q},{u},0.001,0.001,1.5\n"
        ),
    )
    .unwrap();
    let out = d.path().join("mixed_out.csv");
    let args =
        ["correct", "--cal", calp.to_str().unwrap(), "--in", inp.to_str().unwrap(), "--out", out.to_str().unwrap()];
    let o = run(&args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("mixed.csv") && err.contains("row 2") && err.contains("hwp_chi_offset_deg"), "{err}");
    assert!(!out.exists());
}

/// A catalog says what it is: `instpol catalog` writes its instrument, filter, plate and frame
/// into every table format (CSV comment lines, ECSV meta, FITS keywords, VOTable PARAMs), the
/// table reader gives them back, and `instpol correct` refuses a calibration of another filter
/// naming both (a catalog measured in I corrected with a V calibration went through with exit
/// 0), corrects with `--allow-mismatch` saying so, and corrects with its own filter's.
#[test]
fn a_catalog_of_another_filter_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let inst = common::tiny_fors1(dir.path(), 8.0, 20);
    let scene = format!(
        "instrument = \"{}\"\nfilter = \"I\"\nseed = 3\nhwp_angles_deg = [0, 22.5, 45, 67.5]\n[output]\nbitpix = -64\n[sky]\nbrightness_e = 50\n[effects]\nphoton_noise = true\n[[stars]]\nx = 64\ny = 40\ncoords = \"pixel\"\nflux_e = 1.5e6\np = 0.02\nchi_deg = 30\nfwhm_arcsec = 0.8\n",
        inst.display()
    );
    let sp = dir.path().join("scene.toml");
    std::fs::write(&sp, scene).unwrap();
    let frames_dir = dir.path().join("f");
    let o = run(&["simulate", sp.to_str().unwrap(), "--out", frames_dir.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let (cal_v, cal_i) = (dir.path().join("cal_V.fits"), dir.path().join("cal_I.fits"));
    common::fors1_radial_calibration("V", V).save(&cal_v).unwrap();
    common::fors1_radial_calibration("I", V).save(&cal_i).unwrap();
    let frames: Vec<String> = common::fits_in(&frames_dir).iter().map(|p| p.display().to_string()).collect();
    let def_hash = skyfield::provenance::hash_hex(&std::fs::read(&inst).unwrap());
    for ext in ["csv", "ecsv", "fits", "vot"] {
        let cat = dir.path().join(format!("stars.{ext}"));
        let mut args: Vec<&str> = vec!["catalog"];
        args.extend(frames.iter().map(String::as_str));
        args.extend(["--instrument", inst.to_str().unwrap(), "--fwhm", "4", "--aperture", "6", "--annulus", "8,12"]);
        args.extend(["--out", cat.to_str().unwrap()]);
        let o = run(&args);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        // The file holds the keywords as text a person or another reader sees.
        let bytes = std::fs::read(&cat).unwrap();
        let text = String::from_utf8_lossy(&bytes);
        assert!(text.contains("INSTRUME") && text.contains("FILTER"), "{ext}: no product keywords");
        let t = skyfield::table::Table::read(&cat, None).unwrap();
        let p = t.product.as_ref().unwrap_or_else(|| panic!("{ext}: no product read back"));
        assert_eq!(p.instrument.as_deref(), Some("FORS1"), "{ext}");
        assert_eq!(p.filter.as_deref(), Some("I"), "{ext}");
        assert_eq!(p.plate.as_deref(), Some("half_wave"), "{ext}");
        assert_eq!(p.instrument_hash.as_deref(), Some(def_hash.as_str()), "{ext}: the instrument file's BLAKE3");
        assert_eq!(p.frame(), Some(mueller::Frame::Sky { zero_angle_deg: 0.0 }), "{ext}");
        assert_eq!(p.inputs.len(), frames.len() + 1, "{ext}: the frames' and the instrument's hashes");
        let out = dir.path().join(format!("c.{ext}"));
        let args = ["correct", "--in", cat.to_str().unwrap(), "--out", out.to_str().unwrap(), "--coords", "pixel"];
        let refused = run(&[&args[..], &["--cal", cal_v.to_str().unwrap()]].concat());
        let err = String::from_utf8_lossy(&refused.stderr);
        assert_eq!(refused.status.code(), Some(2), "{ext}: {err}");
        assert!(err.contains("FORS1 I catalog") && err.contains("FORS1 V"), "{ext}: {err}");
        assert!(!out.exists(), "{ext}: an output was written");
        let forced = run(&[&args[..], &["--cal", cal_v.to_str().unwrap(), "--allow-mismatch"]].concat());
        let err = String::from_utf8_lossy(&forced.stderr);
        assert!(forced.status.success(), "{ext}: {err}");
        assert!(err.contains("warning: --allow-mismatch") && err.contains("filter I"), "{ext}: {err}");
        // The output records what was allowed, in every format (a FITS catalog is copied with
        // its columns appended and MISMATCH set on its table; it once kept only the input's
        // keywords), once, and keeps the rest of what the catalog says.
        let c = skyfield::table::Table::read(&out, None).unwrap();
        let m = c.product.as_ref().and_then(|p| p.mismatch_allowed.clone());
        assert_eq!(m.as_deref(), Some("data FORS1 I, calibration FORS1 V"), "{ext}");
        assert_eq!(c.product.and_then(|p| p.filter).as_deref(), Some("I"), "{ext}");
        let text = String::from_utf8_lossy(&std::fs::read(&out).unwrap()).into_owned();
        assert_eq!(text.matches("MISMATCH").count(), 1, "{ext}: MISMATCH written once");
        std::fs::remove_file(&out).unwrap();
        let own = run(&[&args[..], &["--cal", cal_i.to_str().unwrap()]].concat());
        assert!(own.status.success(), "{ext}: {}", String::from_utf8_lossy(&own.stderr));
        // The corrected table still says what it is.
        let c = skyfield::table::Table::read(&out, None).unwrap();
        assert_eq!(c.product.and_then(|p| p.filter).as_deref(), Some("I"), "{ext}");
    }
}

/// A table that does not say what it is (written by other software) is corrected with a
/// warning that nothing could be checked.
#[test]
fn a_table_without_product_keywords_is_corrected_with_a_warning() {
    let dir = tempfile::tempdir().unwrap();
    let cal = dir.path().join("v.fits");
    v_calibration().save(&cal).unwrap();
    let input = dir.path().join("in.csv");
    std::fs::write(&input, "x,y,q,u,sigma_q,sigma_u\n0.5,0.5,0.01,0.0,0.001,0.001\n").unwrap();
    let out = dir.path().join("out.csv");
    let o = correct(&cal, &input, &out, &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("does not say which instrument and filter"), "{err}");
}

/// A calibration of two field elements, a stressed lens then the V radial field
/// (`fit::files::elements`): `correct` gives back each star's `(q, u)`, made here by the lens's
/// retarder (`mueller::retarder` of its retardance and axis, `mueller::causes::stressed_lens`),
/// `M_I(p, phi)` of `eq:instpol` (`mueller::partial_polarizer`) and the zero angle in turn, and
/// its summary says the two were inverted together.
#[test]
fn a_calibration_of_two_field_elements_corrects_rows_through_both() {
    use fit::files::elements::Element;
    let dir = tempfile::tempdir().unwrap();
    let cal = v_calibration();
    let (edge, radius, centre, offset) = (50f64.to_radians(), 3.0, [0.3, -0.4], 0.2);
    let lens = field::StressedLens {
        retardance_edge: edge,
        radius_arcmin: radius,
        centre_arcmin: centre,
        axis_offset: offset,
    };
    let cal_path = dir.path().join("two.fits");
    cal.save_with_elements(&cal_path, &[Element::StressedLens(lens), Element::Model], |_, _| Ok(())).unwrap();
    let stars: [(f64, f64, f64, f64); 3] = [(1.2, -0.8, 0.03, 0.4), (-2.5, 2.0, 0.01, 1.9), (2.9, 2.7, 0.05, 2.6)];
    let mut csv = String::from("x,y,q,u,sigma_q,sigma_u\n");
    for &(x, y, p0, chi0) in &stars {
        let (d, ax) = mueller::causes::stressed_lens(x, y, edge, radius, centre, offset);
        let a = cal.eval(x, y);
        let m_i = mueller::partial_polarizer(a.q.hypot(a.u), 0.5 * a.u.atan2(a.q));
        let s =
            m_i * mueller::retarder(d, ax) * mueller::stokes_qu(1.0, p0 * (2.0 * chi0).cos(), p0 * (2.0 * chi0).sin());
        let (sn, cs) = (2.0 * OFFSET_DEG.to_radians()).sin_cos();
        let (q, u) = (s[1] / s[0], s[2] / s[0]);
        csv += &format!("{x},{y},{},{},1e-4,1e-4\n", cs * q + sn * u, -sn * q + cs * u);
    }
    let input = dir.path().join("rows.csv");
    std::fs::write(&input, csv).unwrap();
    let out = dir.path().join("out.csv");
    let o = correct(&cal_path, &input, &out, &[]);
    let said = String::from_utf8_lossy(&o.stdout);
    assert!(said.contains("within the chain of 2 field elements"), "{said}");
    let text = std::fs::read_to_string(&out).unwrap();
    let mut lines = text.lines();
    let head: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |n: &str| head.iter().position(|h| *h == n).unwrap();
    for (line, &(_, _, p0, chi0)) in lines.zip(&stars) {
        let v: Vec<f64> = line.split(',').map(|t| t.parse().unwrap()).collect();
        let (q0, u0) = (v[col("q0")], v[col("u0")]);
        assert!((q0 - p0 * (2.0 * chi0).cos()).abs() < 1e-12 && (u0 - p0 * (2.0 * chi0).sin()).abs() < 1e-12, "{line}");
    }
}
