//! `instpol raytrace`: polarization ray tracing of the instrument's collimator prescription.
//! All numbers come from `mueller::raytrace`; this file prints, plots and writes them.

use anyhow::{anyhow, bail, Result};
use mueller::raytrace::{fit_radial, FieldFile, Sampling, PAPER_LAW_A, PAPER_LAW_B};
use plotters::prelude::*;
use serde::Serialize;
use std::path::{Path, PathBuf};

/// Trace real rays through the collimator prescription of an instrument file ([optics]) and
/// predict the instrumental polarization field it makes (the paper's section "cause"):
/// p(r) along the field diagonal, its angle (radial: phi = polar angle), the fitted radial
/// polynomial p = c1 r + c2 r^2 + c3 r^3, each surface's share at the field edge, and the
/// wavelength law p(lambda)/p(550) = a + b lambda over 400-900 nm.
///
/// Each field point averages the Mueller matrices of the rays over the telescope pupil
/// (Gauss-Legendre rings x spokes). Polarization is a fraction in JSON, percent in tables.
///
/// Example: instpol raytrace --instrument fors1 --filter V --plot p_r.png --field-out v.json
#[derive(clap::Args)]
pub struct Args {
    /// Instrument name (built-in: fors1) or path to an instrument TOML with an [optics] section.
    #[arg(long, default_value = "fors1")]
    pub instrument: String,
    /// Filter whose effective wavelength to trace (default V).
    #[arg(long, conflicts_with = "wavelength_nm")]
    pub filter: Option<String>,
    /// Trace at this vacuum wavelength (nm) instead of a filter's.
    #[arg(long)]
    pub wavelength_nm: Option<f64>,
    /// Number of field points from the axis to the field radius (>= 4).
    #[arg(long, default_value_t = 13)]
    pub field_points: usize,
    /// Approximate number of rays per field point (pupil sampling; >= 4). The default
    /// changes p by < 1e-5 when doubled.
    #[arg(long, default_value_t = Sampling::DEFAULT_RAYS)]
    pub pupil_rays: usize,
    /// Print JSON instead of tables.
    #[arg(long)]
    pub json: bool,
    /// Draw p(r) against the paper's V and I fits into this image (.png or .svg, by its extension).
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Write the field (format instpol-field-v1, JSON) for the simulator to this file.
    #[arg(long)]
    pub field_out: Option<PathBuf>,
}

#[derive(Serialize)]
struct PerSurface {
    surface: String,
    p_at_edge: f64,
}

#[derive(Serialize)]
struct Law {
    a: f64,
    b: f64,
    radius_arcmin: f64,
    samples: Vec<LawSample>,
    paper_a: f64,
    paper_b: f64,
}

#[derive(Serialize)]
struct LawSample {
    wavelength_nm: f64,
    ratio: f64,
    paper: f64,
}

#[derive(Serialize)]
struct PhiAlpha {
    alpha_deg: f64,
    phi_deg: f64,
    p: f64,
}

#[derive(Serialize)]
struct Out {
    instrument: String,
    prescription: String,
    wavelength_nm: f64,
    #[serde(rename = "n_pupil_rays")]
    pupil_rays: usize,
    profile_alpha_deg: f64,
    radius_arcmin: Vec<f64>,
    p: Vec<f64>,
    phi_deg: Vec<f64>,
    polynomial_powers: Vec<i32>,
    polynomial: Vec<f64>,
    phi_vs_alpha: Vec<PhiAlpha>,
    per_surface: Vec<PerSurface>,
    wavelength_law: Law,
}

pub fn run(a: Args) -> Result<()> {
    crate::util::inputs(crate::util::file_arg(&a.instrument))?;
    for o in a.plot.iter().chain(&a.field_out) {
        crate::util::check_output(o)?;
    }
    if let Some(p) = &a.plot {
        crate::plot::ImageFormat::of(p)?;
    }
    let inst = instrument::Instrument::load(&a.instrument)?;
    let presc = inst
        .optics
        .as_ref()
        .ok_or_else(|| anyhow!("instrument {} has no [optics] prescription to trace", inst.name))?;
    let lam = match (a.wavelength_nm, &a.filter) {
        (Some(l), _) => {
            if !(l.is_finite() && l > 100.0 && l < 30000.0) {
                bail!("--wavelength-nm {l} must be a wavelength in nm (100-30000)");
            }
            l
        }
        (None, f) => inst.filter(f.as_deref().unwrap_or("V"))?.lambda_eff_nm,
    };
    if a.field_points < 4 {
        bail!("--field-points {} must be >= 4 (the radial fit has 3 terms)", a.field_points);
    }
    if a.pupil_rays < 4 {
        bail!("--pupil-rays {} must be >= 4", a.pupil_rays);
    }
    // Bounded before allocating: the trace is field_points x pupil_rays ray paths, and each
    // limit is far beyond where p(r) stops changing (the defaults change p by < 1e-5).
    const MAX_FIELD_POINTS: usize = 10_000;
    const MAX_PUPIL_RAYS: usize = 1_000_000;
    if a.field_points > MAX_FIELD_POINTS {
        bail!("--field-points {} is above the limit of {MAX_FIELD_POINTS}", a.field_points);
    }
    if a.pupil_rays > MAX_PUPIL_RAYS {
        bail!("--pupil-rays {} is above the limit of {MAX_PUPIL_RAYS}", a.pupil_rays);
    }
    if (a.field_points as f64) * (a.pupil_rays as f64) > 2e7 {
        bail!(
            "--field-points {} x --pupil-rays {} = {:.2e} rays: above the limit of 2e7 (minutes of tracing); lower one",
            a.field_points,
            a.pupil_rays,
            a.field_points as f64 * a.pupil_rays as f64
        );
    }
    let sampling = Sampling::from_rays(a.pupil_rays);
    let c = presc.compile(lam)?;
    let edge = presc.field_radius_arcmin;
    // Along the diagonal: the direction in which a square field reaches its corners.
    let alpha = 45f64.to_radians();
    let radii: Vec<f64> = (0..a.field_points).map(|i| edge * i as f64 / (a.field_points - 1) as f64).collect();
    let lambdas: Vec<f64> = (0..=10).map(|i| 400.0 + 50.0 * i as f64).collect();

    let bar = indicatif::ProgressBar::new(4).with_message("tracing");
    if a.json {
        bar.set_draw_target(indicatif::ProgressDrawTarget::hidden());
    }
    let pts = c.profile(&radii, alpha, &sampling, None)?;
    bar.inc(1);
    let alphas: Vec<f64> = (0..12).map(|k| (15.0 + 30.0 * k as f64).to_radians()).collect();
    let ring: Vec<_> = alphas
        .iter()
        .map(|&al| c.field_point(0.5 * edge * al.cos(), 0.5 * edge * al.sin(), &sampling, None))
        .collect::<Result<_, _>>()?;
    bar.inc(1);
    let (ex, ey) = (edge * alpha.cos(), edge * alpha.sin());
    let per = c.per_surface(ex, ey, &sampling)?;
    bar.inc(1);
    let law = presc.wavelength_law(edge, &sampling, &lambdas)?;
    bar.finish_and_clear();

    let p: Vec<f64> = pts.iter().map(|f| f.p).collect();
    let poly = fit_radial(&radii, &p, &[1, 2, 3])?;
    let out = Out {
        instrument: inst.name.clone(),
        prescription: presc.description.clone(),
        wavelength_nm: lam,
        pupil_rays: sampling.rays(),
        profile_alpha_deg: alpha.to_degrees(),
        radius_arcmin: radii.clone(),
        p: p.clone(),
        // phi is undefined where p = 0 (the axis): reported as 0 there.
        phi_deg: pts.iter().map(|f| if f.p > 1e-12 { f.phi.to_degrees() } else { 0.0 }).collect(),
        polynomial_powers: poly.powers.clone(),
        polynomial: poly.coefficients.clone(),
        phi_vs_alpha: ring
            .iter()
            .map(|f| PhiAlpha {
                alpha_deg: f.alpha.to_degrees().rem_euclid(360.0),
                phi_deg: f.phi.to_degrees(),
                p: f.p,
            })
            .collect(),
        per_surface: per
            .iter()
            .enumerate()
            .map(|(i, f)| PerSurface { surface: c.surface_name(i).to_string(), p_at_edge: f.p })
            .collect(),
        wavelength_law: Law {
            a: law.a,
            b: law.b,
            radius_arcmin: law.radius_arcmin,
            samples: law
                .samples
                .iter()
                .map(|&(l, r)| LawSample { wavelength_nm: l, ratio: r, paper: PAPER_LAW_A + PAPER_LAW_B * l })
                .collect(),
            paper_a: PAPER_LAW_A,
            paper_b: PAPER_LAW_B,
        },
    };
    if let Some(path) = &a.field_out {
        let ff = FieldFile::new(&format!("ray trace of {}", presc.description), lam, &pts, poly.clone());
        crate::util::write_atomic(path, serde_json::to_string_pretty(&ff)?.as_bytes())?;
    }
    if let Some(path) = &a.plot {
        plot(path, &radii, &p, lam, &inst.name)?;
    }
    if a.json {
        return crate::util::print_json(&out);
    }
    outln!("{} at {lam} nm, {} rays per field point", out.prescription, out.pupil_rays);
    outln!("{:>10} {:>10} {:>10}", "r arcmin", "p %", "phi deg");
    for ((r, p), phi) in radii.iter().zip(&out.p).zip(&out.phi_deg) {
        outln!("{r:>10.3} {:>10.4} {phi:>10.2}", 100.0 * p);
    }
    let c = &out.polynomial;
    outln!("fit: p(r) % = {:.4} r + {:.4} r^2 + {:.5} r^3", 100.0 * c[0], 100.0 * c[1], 100.0 * c[2]);
    outln!("phi - alpha at r = {:.2}': max {:.4} deg", 0.5 * edge, {
        ring.iter().map(|f| f.phi_rel().to_degrees().abs()).fold(0.0, f64::max)
    });
    outln!("per surface at the edge (r = {edge}'):");
    for s in &out.per_surface {
        outln!("  {:<14} {:>8.4} %", s.surface, 100.0 * s.p_at_edge);
    }
    outln!(
        "wavelength law at r = {edge}': p/p(550) = {:.4} + {:.4e} lambda  (paper: {PAPER_LAW_A} + {PAPER_LAW_B:e} lambda)",
        law.a, law.b
    );
    for s in &out.wavelength_law.samples {
        outln!("  {:>5} nm  {:>7.4}  paper {:>7.4}", s.wavelength_nm, s.ratio, s.paper);
    }
    Ok(())
}

/// p(r) in percent against the paper's V and I polynomials (section fors1).
fn plot(path: &Path, r: &[f64], p: &[f64], lam: f64, name: &str) -> Result<()> {
    crate::plot::save_image(path, (900, 600), |root| draw(root, r, p, lam, name), |root| draw(root, r, p, lam, name))
}

/// The p(r) figure on either backend (PNG or SVG).
fn draw<DB: DrawingBackend>(
    root: &DrawingArea<DB, plotters::coord::Shift>,
    r: &[f64],
    p: &[f64],
    lam: f64,
    name: &str,
) -> Result<()> {
    let pe = |e: &dyn std::fmt::Debug| anyhow!("plot: {e:?}");
    let rmax = r.last().copied().unwrap_or(5.0).max(1.0);
    let v = |x: f64| 0.012 * x + 0.046 * x * x + 0.002 * x * x * x;
    let i = |x: f64| -0.017 * x + 0.105 * x * x - 0.006 * x * x * x;
    let grid: Vec<f64> = (0..=100).map(|k| rmax * k as f64 / 100.0).collect();
    let marks: Vec<Vec<(f64, f64)>> = vec![
        grid.iter().map(|&x| (x, v(x))).collect(),
        grid.iter().map(|&x| (x, i(x))).collect(),
        r.iter().zip(p).map(|(&x, &y)| (x, 100.0 * y)).collect(),
    ];
    // The shared frame (fonts sized for a journal column, crate::plot).
    let ax = crate::plot::Axes::new(format!("{name}: ray trace at {lam} nm"), "r (arcmin)", "p (%)");
    let y = || crate::plot::marks_y_range(&marks);
    use crate::plot::{key, Mark};
    let keys = [
        key("paper V fit", Mark::Line(crate::plot::BLUE_OI.stroke_width(2))),
        key("paper I fit", Mark::Line(crate::plot::VERMILLION.stroke_width(2))),
        key("ray trace", Mark::Line(BLACK.stroke_width(2))),
    ];
    let (mut ch, place) = crate::plot::chart_with_legend(root, &ax, || 0.0..rmax, y, &marks, &keys)?;
    for (m, k) in marks.iter().zip(&keys) {
        let Mark::Line(style) = k.mark else { continue };
        ch.draw_series(LineSeries::new(m.iter().copied(), style)).map_err(|e| pe(&e))?;
    }
    ch.draw_series(r.iter().zip(p).map(|(&x, &y)| Circle::new((x, 100.0 * y), 3, BLACK.filled())))
        .map_err(|e| pe(&e))?;
    crate::plot::draw_legend(&ch, place, &keys)
}
