//! The four nonlinear least-squares fits (the radial model, the telescope model, the Mueller
//! field and the candidate causes of `mueller_explain`) give, on fixed inputs, the results
//! they gave before their loops became the one solver of `fit::lsq`: every number of each
//! result is digested through its JSON text (serde_json writes the shortest decimal that reads
//! back to the same `f64`, so two texts are equal exactly when the bits are), and the digests
//! are the ones recorded with the hand-written loops and argmin's Gauss-Newton.
//!
//! A digest that changes means a fit moved: by the solver (which must not move them) or by a
//! deliberate change of a model, which then records new digests with `INSTPOL_RECORD=1`
//! (printed, to be pasted here).

use crate::common;

use common::mueller_fields::{diat_and_lens, fors1_grid, sky_fields, through};
use common::{fors1_bin_centres, noisy_bins, radial_field, SIGMA_BIN, V_COEFFS};
use fit::mueller_field::explain::{explain, Cause, Context, Target};
use fit::mueller_field::{fit_mueller_field, fit_per_bin, Kind, MuellerFitOptions};
use fit::telescope::{fit_band, fit_joint, read_observations, FitOptions, ModelKind};
use fit::{fit_radial, RadialFitOptions};
use mueller::mirror::MetalTable;

/// FNV-1a, 64 bits, of a text.
fn fnv(s: &str) -> u64 {
    s.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| (h ^ b as u64).wrapping_mul(0x0100_0000_01b3))
}

/// Check (or, with `INSTPOL_RECORD=1`, print) the digest of `what`'s JSON.
fn check<T: serde::Serialize>(name: &str, what: &T, want: u64) {
    check_text(name, &serde_json::to_string(what).unwrap(), want)
}

/// [`check`] of a JSON text (with the places that depend on where the data live made
/// neutral by the caller).
fn check_text(name: &str, text: &str, want: u64) {
    let got = fnv(text);
    if std::env::var("INSTPOL_RECORD").is_ok() {
        eprintln!("{name}: 0x{got:016x}");
        return;
    }
    assert_eq!(got, want, "{name} moved: 0x{got:016x} (text {} chars)", text.len());
}

#[test]
fn radial_fits_are_unchanged() {
    let bins = noisy_bins(&fors1_bin_centres(64), radial_field(&V_COEFFS, (0.3, -0.2)), SIGMA_BIN, 7);
    let free = RadialFitOptions { free_centre: true, centre: [0.1, 0.1], ..Default::default() };
    check("radial free centre, Huber", &fit_radial(&bins, &free).unwrap(), 0xa6c798f1b488712b);
    let plain = RadialFitOptions {
        include_c0: true,
        robust: fit::models::radial::Robust::None,
        degree: 4,
        ..Default::default()
    };
    check("radial c0..c4, no robust weights", &fit_radial(&bins, &plain).unwrap(), 0xfade8b4d5543078d);
    // No pattern: the free centre is refused with the fixed-centre fit's coefficients.
    let flat: Vec<fit::Bin> =
        fors1_bin_centres(64).iter().map(|&(x, y)| fit::Bin::new(x, y, 0.0, 0.0, SIGMA_BIN, SIGMA_BIN)).collect();
    let e = fit_radial(&flat, &free).unwrap_err().to_string();
    check("radial without a pattern (the refusal's text)", &e, 0xcd225d032fbf72f1);
}

/// The JSON of a fit with the data folder's path (which the observations' sources name) made
/// neutral: where the data live is not part of a fit.
fn neutral<T: serde::Serialize>(what: &T, dir: &std::path::Path) -> String {
    serde_json::to_string(what).unwrap().replace(&dir.display().to_string(), "{DATA}")
}

#[test]
fn telescope_fits_are_unchanged() {
    let Some(dir) =
        crate::common::shared_data::shared_data("efosc2-standards", &[], "the telescope fits held to the bit")
    else {
        return;
    };
    let table = MetalTable::read(&dir.join("METALS_Aluminium_Rakic.txt")).unwrap();
    let v = read_observations(&dir.join("pv_standards.txt")).unwrap();
    let opts = FitOptions::default();
    check_text(
        "telescope V wiersema",
        &neutral(&fit_band(ModelKind::Wiersema, &v, &table, &opts).unwrap(), &dir),
        0xbd56b2ba5449c4ae,
    );
    check_text(
        "telescope V oxide",
        &neutral(&fit_band(ModelKind::Oxide, &v, &table, &opts).unwrap(), &dir),
        0x2f7fee7fa35ca0b9,
    );
    let mut all = Vec::new();
    for stem in ["pb", "pv", "pr"] {
        all.extend(read_observations(&dir.join(format!("{stem}_standards.txt"))).unwrap());
    }
    check_text(
        "telescope B V R joint wiersema",
        &neutral(&fit_joint(ModelKind::Wiersema, &all, &table, &opts, true).unwrap(), &dir),
        0x135c66f60d0fbb63,
    );
}

#[test]
fn mueller_field_and_explain_fits_are_unchanged() {
    let lens = |x: f64, y: f64| diat_and_lens(x, y, 18.0, [0.8, -0.4], 10.0);
    let fields = sky_fields(3, &fors1_grid(30, 22), &through(lens), 11);
    let opts =
        MuellerFitOptions { kind: Kind::diattenuation_retardance(), deg: 4, scale_arcmin: 3.4, ..Default::default() };
    let mf = fit_mueller_field(&fields, &opts).unwrap();
    check("mueller field, diattenuation and retardance, degree 4", &mf, 0x6c38494940bce117);
    let few = sky_fields(3, &fors1_grid(6, 5), &through(lens), 12);
    let (bins, skipped) = fit_per_bin(&few, &opts).unwrap();
    check("mueller per-bin fits", &(bins.iter().map(|b| &b.field).collect::<Vec<_>>(), skipped), 0xcfb43649323c8b02);
    let target = Target::smooth(&mf, 16, "test").unwrap();
    let ctx =
        Context::new(&(0..16).map(|k| k as f64 * std::f64::consts::PI / 8.0).collect::<Vec<_>>(), 90.0, 3.4).unwrap();
    check("explain the smooth field", &explain(&target, &ctx, &Cause::ALL).unwrap(), 0x98806ed5d7ef0065);
    let per_bin = Target::per_bin(&bins, "test").unwrap();
    check("explain the per-bin fits", &explain(&per_bin, &ctx, &Cause::ALL).unwrap(), 0xe595cae1909dd19d);
}
