//! `instpol photometry`: Q, U, P, chi of a point source from a set of frames (V/I through a
//! quarter-wave plate).

use super::photometry_text::{CircularOut, Out};
use anyhow::{bail, Result};
use skyfield::reduce::FrameSet;
use std::path::PathBuf;

/// Aperture photometry of a point source in both beams at every HWP angle, with the local
/// background (annulus, sigma-clipped mean) subtracted beam by beam before F_i, so that a
/// polarized background is removed vectorially (paper, section background). Prints Q/I, U/I,
/// P (%), chi (deg) and their errors.
///
/// With an instrument whose plate is a quarter-wave plate ([polarimetry] plate =
/// "quarter_wave") it prints V/I and its error instead (IAU sign; the plate angles plus the
/// filter's qwp_zero_angle_deg; 2 positions -45,45 or 4 positions -45,45,135,225 deg): Q, U, P
/// and chi are not reported, those sets do not determine them. The JSON is then
/// schemas/photometry-circular.schema.json.
///
/// With --star NAME (a standard of instruments/standards.toml or --standards) the JSON also
/// records the star, its catalogued P (p_true, a fraction) and chi (chi_true_deg) in the
/// frames' band when it is a polarized standard, the filter and its wavelength, and the middle
/// of the frames' parallactic-angle track with their rotator angle (deg, from the keywords of
/// the instrument's [telescope] section; null without them): `instpol fit-standards` reads
/// such a file as one measurement of the telescope.
///
/// Example: instpol photometry star/*.fits --instrument fors1 --x 1900 --y 90 --aperture 8
/// --annulus 12,20
///
/// Example (circular polarization, docs/guide/circular.md):
///   instpol photometry qwp/*.fits --instrument instruments/calcite_qwp.toml --hwp-angles -45,45
///   --x 200 --y 300 --aperture 9 --annulus 14,24
///
/// Example (an EFOSC2 standard, a point of the telescope fit):
///   instpol photometry std/*.fits --instrument efosc2 --x 512 --y 300 --star "HD 64299" --json
///   > hd64299.json && instpol fit-standards hd64299.json other.json --instrument efosc2
#[derive(clap::Args)]
pub struct Args {
    /// Frame files (FITS).
    #[arg(required = true)]
    pub frames: Vec<PathBuf>,
    /// Source x: 0-based pixel of the ordinary image, or arcmin from the detector centre.
    #[arg(long, allow_hyphen_values = true)]
    pub x: f64,
    /// Source y: 0-based pixel or arcmin, as --x.
    #[arg(long, allow_hyphen_values = true)]
    pub y: f64,
    /// Units of --x/--y.
    #[arg(long, value_enum, default_value = "pixel")]
    pub coords: CoordsArg,
    /// Aperture radius: pixels (8), a multiple of the star's FWHM (2.5fwhm; needs --fwhm) or
    /// 'best': the radius of best S/N of the total flux on the curve of growth, 0.5 to 4 FWHM
    /// inside the annulus (needs --fwhm).
    #[arg(long, default_value = "8", value_name = "PX|Kfwhm|best", allow_hyphen_values = true)]
    pub aperture: String,
    /// The star's FWHM (px), for --aperture Kfwhm or best.
    #[arg(long, value_name = "PX")]
    pub fwhm: Option<f64>,
    /// Background annulus inner,outer radius (px).
    #[arg(long, default_value = "12,20")]
    pub annulus: String,
    /// No background subtraction (the combined source + background values).
    #[arg(long)]
    pub no_background: bool,
    /// How the aperture weighs its edge pixels: exact (the fraction of each pixel's area inside
    /// the circle; the same aperture in both beams at any sub-pixel offset) or centre (whole
    /// pixels whose centre is inside).
    #[arg(long, value_enum, default_value = "exact")]
    pub aperture_weights: WeightsArg,
    /// Keep the aperture at --x/--y in every frame instead of re-centring it on the star's
    /// centroid in each (frames usually move by a pixel or two between HWP positions).
    #[arg(long)]
    pub fixed: bool,
    /// Measure the star even when one of its images holds another star's other image (a
    /// maskless layout, stars one o/e offset apart): its P is then wrong, and a warning says so.
    /// Without it such a star is refused, as the catalog flags it `overlap`.
    #[arg(long)]
    pub allow_overlap: bool,
    /// Instrument: built-in name or path to an instrument TOML.
    /// Default: the built-in instrument the first file's INSTRUME keyword names (said on
    /// stderr); a file without one, or of no built-in instrument, is refused.
    #[arg(long)]
    pub instrument: Option<String>,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
    /// The standard star measured (see instruments/standards.toml): recorded in the JSON with
    /// its catalogued polarization, for `instpol fit-standards`.
    #[arg(long)]
    pub star: Option<String>,
    /// A standards file (TOML, the format of instruments/standards.toml) for --star.
    #[arg(long, value_name = "FILE", requires = "star")]
    pub standards: Option<PathBuf>,
    #[command(flatten)]
    pub frame: crate::cmd::frame_opts::FrameOpts,
    #[command(flatten)]
    pub kappa: crate::cmd::frame_opts::KappaOpts,
}

#[derive(Clone, Copy, clap::ValueEnum)]
pub enum WeightsArg {
    Exact,
    Centre,
}

#[derive(Clone, Copy, clap::ValueEnum)]
pub enum CoordsArg {
    Pixel,
    Arcmin,
}

pub fn run(a: Args) -> Result<()> {
    let instrument = crate::util::instrument_of(&a.instrument, a.frames.first().map(|p| p.as_path()))?;
    crate::util::inputs(
        a.frames.iter().map(|p| p.as_path()).chain(crate::util::file_arg(&instrument)).chain(a.standards.as_deref()),
    )?;
    let inst = instrument::Instrument::load(&instrument)?;
    let list = match (&a.star, &a.standards) {
        (None, _) => None,
        (Some(_), Some(p)) => Some(fit::standards::Standards::load(p)?),
        (Some(_), None) => Some(fit::standards::Standards::builtin()?),
    };
    let star = match (&a.star, &list) {
        (Some(n), Some(l)) => Some(l.star(n)?),
        _ => None,
    };
    let (x, y) = match a.coords {
        CoordsArg::Pixel => (a.x, a.y),
        CoordsArg::Arcmin => inst.arcmin_to_pixel(a.x, a.y),
    };
    let annulus = if a.no_background { None } else { Some(crate::util::parse_radii(&a.annulus)?) };
    let bar =
        if a.json { indicatif::ProgressBar::hidden() } else { indicatif::ProgressBar::new(a.frames.len() as u64) };
    bar.set_message("reading");
    let read = a.frame.read_options()?;
    let frames = skyfield::reduce::read_frames_with(&a.frames, &inst, &read, &|| bar.inc(1));
    bar.finish_and_clear();
    let frames = frames?;
    // Repeated plate positions are summed into one frame each; keep the exposures to measure
    // them one by one as well (outlier exposures are flagged by their residual).
    let theta: Vec<f64> = frames.iter().map(|f| f.hwp_deg.to_radians()).collect();
    let singles = stokes::repeats::has_repeats(&theta).then(|| frames.clone());
    let set = FrameSet::from_frames(frames, &inst, true)?;
    for w in &set.warnings {
        eprintln!("warning: {w}");
    }
    let g = skyfield::photometry::layout_for(&set, &inst)?;
    if inst.polarimetry.layout == instrument::Layout::Maskless && inst.polarimetry.oe_offset_px.is_none() {
        let (dx, dy) = g.oe_offset.unwrap_or_default();
        eprintln!(
            "warning: o/e offset measured from the stars: ({dx:.2}, {dy:.2}) px; which image is the ordinary one cannot be measured (taken with dx > 0): if it is the other, Q and U change sign. Set [polarimetry] oe_offset_px in the instrument file."
        );
    }
    if let Some((rms, n)) = g.cameras.as_ref().and_then(|c| c.measured) {
        eprintln!(
            "warning: camera transform measured from {n} star pairs, residual RMS {rms:.3} px: {:?}",
            g.cameras.as_ref().and_then(|c| c.transform).unwrap_or_default()
        );
    }
    let opts = skyfield::photometry::PhotOptions {
        weighting: match a.aperture_weights {
            WeightsArg::Exact => skyfield::aperture::Weighting::Exact,
            WeightsArg::Centre => skyfield::aperture::Weighting::Centre,
        },
        recentre: !a.fixed,
        kappa: a.kappa.correction()?,
    };
    let radius = crate::util::parse_aperture(&a.aperture)?;
    let fwhm = match (radius, a.fwhm) {
        (skyfield::photometry::ApertureRadius::Px(_), f) => f.unwrap_or(f64::NAN),
        (_, Some(f)) if f.is_finite() && f > 0.0 && f < 200.0 => f,
        (_, Some(f)) => bail!("--fwhm {f} px: expected a star width between 0 and 200 px"),
        (_, None) => bail!("--aperture {}: give the star's FWHM with --fwhm PX", a.aperture),
    };
    if let Some(w) = skyfield::photometry::check_overlap(&set, &g, x, y, fwhm, a.allow_overlap)? {
        eprintln!("warning: {w}");
    }
    if inst.polarimetry.plate == instrument::Plate::QuarterWave {
        if a.star.is_some() {
            bail!("--star records a standard's linear polarization for fit-standards: not with a quarter-wave plate");
        }
        let zero = inst.filter(&set.filter).map_or(0.0, |f| f.qwp_zero_angle_deg());
        let (ph, radius_px) = skyfield::photometry::circular_sized(&set, &g, x, y, radius, fwhm, annulus, &opts, zero)?;
        let product = skyfield::provenance::Product::of_instrument(&inst, &set.filter, None).with_run_inputs();
        let o = CircularOut::of(&ph, (x, y), zero, g.e_offset(x, y), radius_px, &set.filter, product);
        if a.json {
            crate::util::print_json(&o)?;
        } else {
            super::photometry_text::print_circular(&o);
        }
        return Ok(());
    }
    let (ph, radius_px) = skyfield::photometry::photometry_sized(&set, &g, x, y, radius, fwhm, annulus, &opts)?;
    let exposures = match &singles {
        Some(fr) => Some(skyfield::photometry::exposure_checks(
            &skyfield::photometry::single_exposures(fr, &set),
            &g,
            x,
            y,
            &skyfield::photometry::Aperture { radius_px, annulus },
            &opts,
            skyfield::photometry::EXPOSURE_OUTLIER_SIGMA,
        )?),
        None => None,
    };
    let n_outlier_exposures = exposures.iter().flatten().filter(|e| e.outlier).count();
    for e in exposures.iter().flatten().filter(|e| e.outlier) {
        eprintln!("warning: exposure {} (HWP {} deg): {} (flagged; kept in the sum)", e.file, e.hwp_deg, e.why);
    }
    let r = &ph.reduction;
    // The HWP zero angle of the filter (the angle to add to a measured chi): Q, U and chi are
    // reported in the sky's frame, as the calibration and validation report them.
    let offset = inst.filter(&set.filter).map(|f| f.chi_offset_deg()).unwrap_or(0.0);
    if let Some(w) = skyfield::catalog::zero_angle_warning(&inst, &set.filter) {
        eprintln!("warning: {w}");
    }
    let (sky, chi_deg) = r.in_sky_frame(offset);
    let record = fit::telescope::cal::standard_record(&a.frames, &inst, &set.filter, star)?;
    let (q, u, var_q, var_u) = (sky.q, sky.u, sky.var_q, sky.var_u);
    let o = Out {
        x_px: x,
        y_px: y,
        hwp_deg: ph.hwp_deg.clone(),
        f_o: ph.f_o.clone(),
        f_e: ph.f_e.clone(),
        q,
        u,
        sigma_q: var_q.max(0.0).sqrt(),
        sigma_u: var_u.max(0.0).sqrt(),
        p: r.p,
        sigma_p: r.sigma_p,
        chi_deg,
        hwp_chi_offset_deg: offset,
        sigma_chi_deg: r.sigma_chi_deg_reported(),
        n_aperture: ph.n_aperture,
        aperture_area_px: ph.aperture_area_px,
        n_annulus: ph.n_annulus,
        oe_offset_px: g.e_offset(x, y),
        centres_px: ph.centres.clone(),
        kappa_applied: ph.kappa_applied,
        aperture_px: radius_px,
        exposures,
        n_outlier_exposures,
        record,
        product: skyfield::provenance::Product::of_instrument(
            &inst,
            &set.filter,
            Some(mueller::Frame::Sky { zero_angle_deg: offset }),
        )
        .with_run_inputs(),
    };
    if a.json {
        crate::util::print_json(&o)?;
    } else {
        super::photometry_text::print(&o, (x, y), !a.fixed, a.kappa.kappa_from_data);
    }
    Ok(())
}
