//! `instpol photometry`'s output: the JSON records of a source (linear, or V/I through a
//! quarter-wave plate) and the text printed without --json.

#[derive(serde::Serialize)]
pub struct Out {
    pub x_px: f64,
    pub y_px: f64,
    pub hwp_deg: Vec<f64>,
    pub f_o: Vec<f64>,
    pub f_e: Vec<f64>,
    pub q: f64,
    pub u: f64,
    pub sigma_q: f64,
    pub sigma_u: f64,
    pub p: f64,
    pub sigma_p: f64,
    pub chi_deg: f64,
    /// null when chi is undetermined (the rule of `instpol stokes`).
    pub sigma_chi_deg: Option<f64>,
    /// The filter's HWP zero angle added to chi (deg).
    pub hwp_chi_offset_deg: f64,
    pub n_aperture: usize,
    pub aperture_area_px: f64,
    pub n_annulus: usize,
    /// Aperture centres per HWP angle `[x_o, y_o, x_e, y_e]` (px).
    pub centres_px: Vec<[f64; 4]>,
    /// The o/e offset used (px) at the source.
    pub oe_offset_px: Option<(f64, f64)>,
    /// The Wollaston kappa applied to the fluxes before the reduction (null: none).
    pub kappa_applied: Option<f64>,
    /// The aperture radius used (px).
    pub aperture_px: f64,
    /// With repeated HWP positions (frames summed per position): every exposure measured on
    /// its own and checked against the others (null when no position repeats).
    pub exposures: Option<Vec<skyfield::photometry::ExposureCheck>>,
    pub n_outlier_exposures: usize,
    /// The standard and the frames' filter, wavelength and telescope angles (--star).
    #[serde(flatten)]
    pub record: fit::telescope::StandardRecord,
    /// What the measurement is (`skyfield::provenance::Product`): q, u in the sky frame of
    /// `hwp_chi_offset_deg`.
    pub product: skyfield::provenance::Product,
}

/// The JSON of a source measured through a quarter-wave plate.
#[derive(serde::Serialize)]
pub struct CircularOut {
    pub x_px: f64,
    pub y_px: f64,
    pub hwp_deg: Vec<f64>,
    /// The filter's quarter-wave zero angle added to the plate angles (deg).
    pub qwp_zero_angle_deg: f64,
    pub f_o: Vec<f64>,
    pub f_e: Vec<f64>,
    pub sigma_o: Vec<f64>,
    pub sigma_e: Vec<f64>,
    /// V/I (fraction, IAU sign) and its error.
    pub v: f64,
    pub sigma_v: f64,
    pub centres_px: Vec<[f64; 4]>,
    pub oe_offset_px: Option<(f64, f64)>,
    pub aperture_px: f64,
    pub filter: String,
    /// What the source was measured in: the instrument file, filter, plate and detector, the
    /// run's inputs.
    pub product: skyfield::provenance::Product,
}

/// The text report of a source measured at `(x, y)` px: the apertures (`recentred`: followed in
/// every frame), the kappa applied (`kappa_from_data`: estimated from these frames), the
/// exposures checked one by one, and Q/I, U/I, P, chi with their errors.
pub fn print(o: &Out, (x, y): (f64, f64), recentred: bool, kappa_from_data: bool) {
    outln!("source at ({x:.2}, {y:.2}) px, aperture {:.2} px, {} HWP angles", o.aperture_px, o.hwp_deg.len());
    let moved = o.centres_px.iter().map(|c| (c[0] - x).hypot(c[1] - y)).fold(0.0, f64::max);
    if recentred {
        outln!("  apertures re-centred in every frame (largest move {moved:.2} px)");
    }
    if let Some(k) = o.kappa_applied {
        let how = if kappa_from_data { ", estimated from these data (eq:kappa2)" } else { "" };
        outln!("  fluxes corrected for kappa = {k:.6e}{how}");
    }
    if let Some(ex) = &o.exposures {
        outln!(
            "  {} exposures measured one by one at repeated HWP positions: {} flagged",
            ex.len(),
            o.n_outlier_exposures
        );
    }
    outln!("  Q/I = {:+.5} +- {:.5}", o.q, o.sigma_q);
    outln!("  U/I = {:+.5} +- {:.5}", o.u, o.sigma_u);
    outln!("  P   = {:.4}% +- {:.4}%", 100.0 * o.p, 100.0 * o.sigma_p);
    match o.sigma_chi_deg {
        Some(s) => outln!("  chi = {:.2} +- {:.2} deg", o.chi_deg, s),
        None => outln!("  chi = {:.2} deg (undetermined: P is not above its error)", o.chi_deg),
    }
}

impl CircularOut {
    /// The record of a source measured at `(x, y)` px through a quarter-wave plate of zero
    /// angle `zero` (deg), with the o/e offset there and the aperture radius used.
    pub fn of(
        ph: &skyfield::photometry::CircularPhotometry,
        (x, y): (f64, f64),
        zero: f64,
        oe_offset_px: Option<(f64, f64)>,
        aperture_px: f64,
        filter: &str,
        product: skyfield::provenance::Product,
    ) -> Self {
        CircularOut {
            x_px: x,
            y_px: y,
            hwp_deg: ph.hwp_deg.clone(),
            qwp_zero_angle_deg: zero,
            f_o: ph.f_o.clone(),
            f_e: ph.f_e.clone(),
            sigma_o: ph.sigma_o.clone(),
            sigma_e: ph.sigma_e.clone(),
            v: ph.circular.v,
            sigma_v: ph.circular.sigma_v(),
            centres_px: ph.centres.clone(),
            oe_offset_px,
            aperture_px,
            filter: filter.to_string(),
            product,
        }
    }
}

/// The text report of a source's V/I through a quarter-wave plate.
pub fn print_circular(o: &CircularOut) {
    outln!(
        "source at ({:.2}, {:.2}) px, aperture {:.2} px, {} quarter-wave plate angles",
        o.x_px,
        o.y_px,
        o.aperture_px,
        o.hwp_deg.len()
    );
    outln!("  V/I = {:+.5} +- {:.5}", o.v, o.sigma_v);
}
