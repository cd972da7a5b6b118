//! `instpol fit-standards`: the console's words for a fit (bands as astronomers write them,
//! `V (550 nm)`, through `fit::correction::setup::band_label`).

use fit::telescope::report::FitReport;

/// One fit's parameters, chi^2 and flagged points, under a line naming its bands and model.
pub fn print_fit(o: &FitReport, inst: Option<&instrument::Instrument>) {
    let bands: Vec<String> = o.bands.iter().map(|b| fit::correction::setup::band_label(b, inst)).collect();
    let head = if o.joint { format!("joint ({})", bands.join(", ")) } else { bands.join(", ") };
    outln!("{head}: model {}", o.model);
    for p in &o.params {
        if p.unit == "fraction" {
            outln!("  {:<22} {:>10.4} +- {:.4} %", p.name, 100.0 * p.value, 100.0 * p.sigma_value);
        } else {
            outln!("  {:<22} {:>10.4} +- {:.4} {}", p.name, p.value, p.sigma_value, p.unit);
        }
    }
    outln!(
        "  chi2/dof = {:.2} / {} = {:.2}; errors x sqrt({:.2}) ({}); RMS q = {:.3} %, u = {:.3} %; {} of {} points used",
        o.chi2,
        o.n_dof,
        o.chi2_dof,
        o.error_factor,
        o.error_scaling,
        100.0 * o.rms_q,
        100.0 * o.rms_u,
        o.n_used,
        o.n_total
    );
    if o.minima.len() > 1 {
        outln!(
            "  {} minima in the thickness within delta chi2 < 4 (the data do not choose between them):",
            o.minima.len()
        );
        for m in &o.minima {
            outln!("    {:>8.2} nm   chi2 = {:.2}   delta chi2 = {:.2}", m.thickness_nm, m.chi2, m.delta_chi2);
        }
    }
    for f in &o.flagged {
        outln!("  flagged: {f}");
    }
}
