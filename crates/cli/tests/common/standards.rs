//! Standards measured through a telescope's M3, for the telescope-fit tests: made with the
//! track-averaged chain (`BandModel::sky_through`), not the fit's residuals. Shared by the
//! integration tests (`common::standards`) and the fit-standards figure's unit tests (through
//! `#[path]`).

use fit::telescope::{BandModel, Track};

/// Two unpolarized and two polarized standards (5 % at 30 deg, 4 % at 120 deg) seen through an
/// aluminium M3 (factor 0.86, offset 40 deg) at twelve parallactic angles each, at 0.55 µm,
/// with a fixed +-2e-4 pattern for noise and errors of 3e-4: a CSV with a header, and a
/// `filter` column when `filter` is given.
pub fn polarized_standards_csv(filter: Option<&str>) -> String {
    let table = mueller::mirror::MetalTable::builtin("aluminium").unwrap();
    let truth = BandModel {
        wavelength_um: 0.55,
        index: table.index(0.55).unwrap(),
        factor: 0.86,
        thickness_nm: 0.0,
        offset: 40f64.to_radians(),
        q0: 0.0,
        u0: 0.0,
    };
    let filter_col = if filter.is_some() { ",filter" } else { "" };
    let filter_val = filter.map_or(String::new(), |f| format!(",{f}"));
    let mut text = format!("star,parallactic_deg,q,sigma_q,u,sigma_u,wavelength_um{filter_col},p_true,chi_true_deg\n");
    for (s, (star, p, chi)) in
        [("WD a", 0.0, 0.0), ("WD b", 0.0, 0.0), ("Pol a", 0.05f64, 30f64), ("Pol b", 0.04, 120.0)]
            .into_iter()
            .enumerate()
    {
        for k in 0..12 {
            let pa = -170.0 + 29.0 * k as f64 + 7.0 * s as f64;
            let (qs, us) = (p * (2.0 * chi.to_radians()).cos(), p * (2.0 * chi.to_radians()).sin());
            let (q, u) = truth.sky_through(qs, us, Track::at(pa.to_radians())).unwrap();
            let e = if (k + s) % 2 == 0 { 2e-4 } else { -2e-4 };
            let (pt, ct) = if p > 0.0 { (p.to_string(), chi.to_string()) } else { (String::new(), String::new()) };
            text += &format!("{star},{pa},{},3e-4,{},3e-4,0.55{filter_val},{pt},{ct}\n", q + e, u - e);
        }
    }
    text
}
