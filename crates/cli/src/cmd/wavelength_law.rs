//! `instpol wavelength-law`: p(lambda)/p(550 nm) = a + b lambda across filters.

use anyhow::{bail, Context, Result};
use fit::models::wavelength::fit_wavelength_law;
use std::path::PathBuf;

/// Fit the wavelength law p(lambda)/p(550 nm) = a + b lambda (lambda in nm; the paper's ray
/// tracing gives 0.02 + 1.73e-3 lambda, section sec:cause) across the radial models of several
/// filters' calibration files: each p(r) is averaged over a radius range and a line in lambda
/// is fitted to the averages. Calibrations holding only a map (imported) are refitted with a
/// free-centre radial model first.
///
/// Example: instpol wavelength-law cal_B.fits cal_V.fits cal_I.fits --json
#[derive(clap::Args)]
pub struct Args {
    /// Calibration files (two or more filters with known wavelengths).
    pub calibrations: Vec<PathBuf>,
    /// Inner radius of the averaging range (arcmin).
    #[arg(long, default_value_t = 1.0)]
    pub r_min: f64,
    /// Outer radius (arcmin); default the largest circle inside every calibration's field.
    #[arg(long)]
    pub r_max: Option<f64>,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: Args) -> Result<()> {
    crate::util::inputs(a.calibrations.iter().map(|p| p.as_path()))?;
    if a.calibrations.len() < 2 {
        bail!("need at least two calibration files (filters) for a wavelength law, got {}", a.calibrations.len());
    }
    let mut models = vec![];
    let mut r_in = f64::INFINITY;
    let mut names = vec![];
    let cals: Vec<fit::Calibration> =
        a.calibrations.iter().map(|p| fit::Calibration::load(p)).collect::<Result<_, _>>()?;
    let paired: Vec<(&std::path::Path, &fit::Calibration)> =
        a.calibrations.iter().map(|p| p.as_path()).zip(&cals).collect();
    fit::models::wavelength::check_one_instrument(&paired)?;
    // What the law is of: the calibrations' one instrument (file, plate, detector), no filter.
    let product = cals.first().map(|c| {
        fit::correction::setup::Setup::named(&c.instrument, "")
            .with_product(c.provenance.product.as_ref())
            .product()
            .with_run_inputs()
    });
    for (p, cal) in a.calibrations.iter().zip(cals) {
        if !cal.lambda_nm.is_finite() {
            bail!(
                "{}: the calibration has no wavelength (HIERARCH IP LAMBDA NM); re-import it with --lambda-nm",
                p.display()
            );
        }
        let model =
            fit::models::pipeline::radial_model_of(&cal).with_context(|| format!("radial fit of {}", p.display()))?;
        let reg = cal.region;
        let c = model.centre;
        r_in = r_in.min((c[0] - reg.x_min).min(reg.x_max - c[0]).min(c[1] - reg.y_min).min(reg.y_max - c[1]));
        if let Some(k) = models.iter().position(|(l, _)| *l == cal.lambda_nm) {
            bail!(
                "{} (filter {}) and {} (filter {}) are both at {} nm: the wavelength law needs different filters",
                a.calibrations[k].display(),
                names[k],
                p.display(),
                cal.filter,
                cal.lambda_nm
            );
        }
        names.push(cal.filter.clone());
        models.push((cal.lambda_nm, model));
    }
    let r_max = a.r_max.unwrap_or(r_in);
    let refs: Vec<(f64, &fit::RadialModel)> = models.iter().map(|(l, m)| (*l, m)).collect();
    let law = fit_wavelength_law(&refs, [a.r_min, r_max])?;
    if a.json {
        #[derive(serde::Serialize)]
        struct Out<'a> {
            filters: &'a [String],
            #[serde(flatten)]
            law: &'a fit::models::wavelength::WavelengthLaw,
            #[serde(skip_serializing_if = "Option::is_none")]
            product: Option<skyfield::provenance::Product>,
        }
        crate::util::print_json(&Out { filters: &names, law: &law, product })
    } else {
        outln!("p(lambda)/p(550) = a + b lambda[nm], p(r) averaged over r = {:.2}..{:.2} arcmin", a.r_min, r_max);
        outln!(
            "a = {:.4} +- {:.4}   b = {:.4e} +- {:.1e}   (paper's ray tracing: 0.02 + 1.73e-3 lambda)",
            law.a,
            law.a_err,
            law.b,
            law.b_err
        );
        outln!("{:>10} {:>8} {:>12} {:>8}", "filter", "nm", "mean p (%)", "ratio");
        for k in 0..names.len() {
            outln!("{:>10} {:>8.1} {:>12.4} {:>8.3}", names[k], law.lambda_nm[k], 100.0 * law.mean_p[k], law.ratio[k]);
        }
        Ok(())
    }
}
