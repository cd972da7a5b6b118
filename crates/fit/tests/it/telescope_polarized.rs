//! Polarized standards in the telescope fit: measurements of stars of known
//! P, chi (columns `p_true`, `chi_true_deg`) enter `fit-standards` beside unpolarized ones, the
//! star's own polarization passed through the telescope model. The data are made here from the
//! track-averaged chain (`BandModel::sky_through`, another function than the fit's residuals),
//! and the fit must give the mirror back; the same data declared unpolarized must not fit.

use fit::telescope::{fit_band, parse_observations, BandModel, FitOptions, ModelKind, Track};
use mueller::mirror::MetalTable;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use std::path::Path;

/// A V-band aluminium M3 of Wiersema factor `factor` and angle offset `offset_deg`.
fn mirror(table: &MetalTable, factor: f64, offset_deg: f64) -> BandModel {
    BandModel {
        wavelength_um: 0.55,
        index: table.index(0.55).unwrap(),
        factor,
        thickness_nm: 0.0,
        offset: offset_deg.to_radians(),
        q0: 0.0,
        u0: 0.0,
    }
}

/// The measurement file: unpolarized rows have empty p_true, chi_true_deg.
fn night(truth: &BandModel) -> String {
    let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(77);
    let g = Normal::new(0.0, 3e-4).unwrap();
    let mut text = String::from("star,parallactic_deg,q,sigma_q,u,sigma_u,wavelength_um,filter,p_true,chi_true_deg\n");
    // Two unpolarized and two polarized standards (P 5 % at 30 deg, 4 % at 120 deg), each at
    // twelve parallactic angles.
    for (star, p, chi) in [("WD a", 0.0, 0.0), ("WD b", 0.0, 0.0), ("Pol a", 0.05, 30.0), ("Pol b", 0.04, 120.0)] {
        for k in 0..12 {
            let pa = -170.0 + 29.0 * k as f64 + 3.0 * p * 100.0;
            let (qs, us) = (p * f64::cos(2.0 * f64::to_radians(chi)), p * f64::sin(2.0 * f64::to_radians(chi)));
            let (q, u) = truth.sky_through(qs, us, Track::at(pa.to_radians())).unwrap();
            let (pt, ct) = if p > 0.0 { (p.to_string(), chi.to_string()) } else { (String::new(), String::new()) };
            text += &format!(
                "{star},{pa},{},3e-4,{},3e-4,0.55,V,{pt},{ct}\n",
                q + g.sample(&mut rng),
                u + g.sample(&mut rng)
            );
        }
    }
    text
}

#[test]
fn polarized_standards_give_the_mirror_back_and_must_be_declared() {
    let table = MetalTable::builtin("aluminium").unwrap();
    let truth = mirror(&table, 0.86, 40.0);
    let text = night(&truth);
    let obs = parse_observations(&text, Path::new("night.csv")).unwrap();
    assert_eq!(obs.iter().filter(|o| o.sky != (0.0, 0.0)).count(), 24);
    let opts = FitOptions { clip: None, ..Default::default() };
    let f = fit_band(ModelKind::Wiersema, &obs, &table, &opts).unwrap();
    let (fa, off) = (f.param("factor").unwrap(), f.param("offset").unwrap());
    assert!((fa.value - 0.86).abs() < 3.0 * fa.sigma, "factor {} +- {}", fa.value, fa.sigma);
    assert!(mueller::wrap_half_pi(off.value - truth.offset).abs() < 3.0 * off.sigma, "offset {off:?}");
    assert!(f.chi2_reduced < 1.6, "chi2/dof {}", f.chi2_reduced);
    // The same rows without the declared polarization: the stars' 4-5 % is not the mirror's.
    let bare: String = text.lines().map(|l| l.splitn(9, ',').take(8).collect::<Vec<_>>().join(",") + "\n").collect();
    let obs0 = parse_observations(&bare, Path::new("bare.csv")).unwrap();
    assert!(obs0.iter().all(|o| o.sky == (0.0, 0.0)));
    let f0 = fit_band(ModelKind::Wiersema, &obs0, &table, &opts).unwrap();
    assert!(f0.chi2_reduced > 100.0, "declared unpolarized, chi2/dof {}", f0.chi2_reduced);
}

#[test]
fn polarized_standard_columns_are_checked() {
    let head = "star,parallactic_deg,q,sigma_q,u,sigma_u,wavelength_um,p_true";
    let e = parse_observations(&format!("{head}\ns,10,0.01,3e-4,0.02,3e-4,0.55,0.05\n"), Path::new("a.csv"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("chi_true_deg") && e.contains("a.csv"), "{e}");
    let e =
        parse_observations(&format!("{head},chi_true_deg\ns,10,0.01,3e-4,0.02,3e-4,0.55,5.0,30\n"), Path::new("b.csv"))
            .unwrap_err()
            .to_string();
    assert!(e.contains("p_true 5") && e.contains("not percent"), "{e}");
}

/// The measurements as a FITS binary table, ECSV or VOTable (written by the one table module
/// from the CSV) read as the same observations as the CSV text.
#[test]
fn structured_tables_read_as_the_csv() {
    let table = MetalTable::builtin("aluminium").unwrap();
    let truth = mirror(&table, 0.9, 30.0);
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("night.csv");
    std::fs::write(&csv, night(&truth)).unwrap();
    let want = fit::telescope::read_observations(&csv).unwrap();
    let t = skyfield::table::Table::read(&csv, None).unwrap();
    for ext in ["fits", "ecsv", "vot"] {
        let p = dir.path().join(format!("night.{ext}"));
        t.write(&p).unwrap();
        let got = fit::telescope::read_observations(&p).unwrap();
        assert_eq!(got.len(), want.len(), "{ext}");
        for (g, w) in got.iter().zip(&want) {
            assert_eq!(
                (&g.star, g.parallactic, g.qu.q, g.qu.sigma_q(), g.qu.u, g.qu.sigma_u(), &g.band, g.sky),
                (&w.star, w.parallactic, w.qu.q, w.qu.sigma_q(), w.qu.u, w.qu.sigma_u(), &w.band, w.sky),
                "{ext}"
            );
        }
    }
}
