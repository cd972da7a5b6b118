//! The calibration file of an instrument's constant response from standards
//! ([`crate::response`], [`field::ConstantResponse`]): `HIERARCH IP MODEL = 'RESPONSE'`, a
//! primary HDU of keywords (`docs/calibration-file.md`), and its correction of one
//! measurement, the exact inverse with the covariance of the measurement and of the four
//! parameters propagated.
//!
//! Keywords (besides `FORMAT VERSION`, `INSTRUMENT`, `FILTER`, `MODEL` and the provenance):
//! `PLATE` (`half_wave`), `FRAME` (`sky`: the instrument's sky frame of the zero angle
//! `HWP CHI OFFSET DEG`, where the response lives), `RE Q0`, `RE U0`, `RE EFFICIENCY`,
//! `RE OFFSET DEG` (the angle to add to a measured `chi`), `RE COV<i><j>` for `i <= j` in
//! 1..4 (the covariance of `q0, u0, efficiency, offset`, the offset in rad), `RE NUNPOL`,
//! `RE NPOL` (the standards used).

use crate::correction::correct::{Corrected, Measurement};
use crate::files::keys::{fits_err, open_versioned, save_fits_atomically, KeyReader, KeyWriter, FORMAT_VERSION};
use crate::{Error, Result};
use field::ConstantResponse;
use std::path::Path;

/// `HIERARCH IP MODEL` of a constant response's calibration file.
pub const RESPONSE_MODEL: &str = "RESPONSE";

/// A constant response as a calibration: what it was measured with and the response with
/// its covariance.
#[derive(Debug, Clone, PartialEq)]
pub struct ResponseCal {
    pub instrument: String,
    pub filter: String,
    /// The plate the standards were measured through (`half_wave`).
    pub plate: String,
    /// The HWP zero angle (deg) of the sky frame the response lives in.
    pub hwp_chi_offset_deg: f64,
    pub response: ConstantResponse,
    /// Covariance of `(q0, u0, efficiency, offset)`, the offset in rad.
    pub covariance: [[f64; 4]; 4],
    pub n_unpolarized: usize,
    pub n_polarized: usize,
    /// What the calibration is (the product keywords: the instrument file's BLAKE3, the
    /// detector, the inputs' BLAKE3), `None` for a file that does not say.
    pub product: Option<skyfield::provenance::Product>,
}

impl ResponseCal {
    /// The calibration of a fit ([`crate::response::fit`]) of standards measured with
    /// `setup` ([`crate::response::one_setup`]: its instrument, filter and what the catalogs
    /// record of their instrument file and detector).
    pub fn of_fit(fit: &crate::response::ResponseFit, setup: &crate::correction::setup::Setup) -> Self {
        ResponseCal {
            instrument: setup.instrument.clone(),
            filter: setup.filter.clone(),
            plate: "half_wave".into(),
            hwp_chi_offset_deg: fit.hwp_chi_offset_deg,
            response: fit.response,
            covariance: fit.covariance,
            n_unpolarized: fit.unpolarized.len(),
            n_polarized: fit.polarized.standards.len(),
            product: Some(setup.product()),
        }
    }

    /// Write the file atomically.
    pub fn save(&self, path: &Path) -> Result<()> {
        save_fits_atomically(path, |f| {
            let hdu = f.primary_hdu().map_err(fits_err(path, "opening the primary HDU"))?;
            let mut w = KeyWriter { f, hdu: &hdu, path };
            w.int("FORMAT VERSION", FORMAT_VERSION)?;
            w.str("INSTRUMENT", &self.instrument)?;
            w.str("FILTER", &self.filter)?;
            w.str("MODEL", RESPONSE_MODEL)?;
            w.str("PLATE", &self.plate)?;
            w.str("FRAME", "sky")?;
            w.real("HWP CHI OFFSET DEG", self.hwp_chi_offset_deg)?;
            let r = &self.response;
            w.real("RE Q0", r.q0)?;
            w.real("RE U0", r.u0)?;
            w.real("RE EFFICIENCY", r.efficiency)?;
            w.real("RE OFFSET DEG", r.offset_deg)?;
            for i in 0..4 {
                for j in i..4 {
                    w.real(&format!("RE COV{}{}", i + 1, j + 1), self.covariance[i][j])?;
                }
            }
            w.int("RE NUNPOL", self.n_unpolarized as i64)?;
            w.int("RE NPOL", self.n_polarized as i64)?;
            w.str("CREATED", &crate::files::keys::utc_now_iso())?;
            crate::files::keys::write_product(&mut w, self.product.as_ref())
        })
    }

    /// Read the file, checking the response is an instrument's
    /// ([`ConstantResponse::unphysical`]) and its covariance has non-negative variances.
    pub fn load(path: &Path) -> Result<Self> {
        let mut f = open_versioned(path)?;
        let hdu = f.primary_hdu().map_err(fits_err(path, "reading the primary HDU"))?;
        let mut r = KeyReader { f: &mut f, hdu: &hdu, path };
        let bad = |what: String| Error::BadFile { path: path.into(), what };
        let model = r.str("MODEL")?;
        if model != RESPONSE_MODEL {
            return Err(bad(format!(
                "MODEL = '{model}', not '{RESPONSE_MODEL}': read it with fit::files::calibration::load"
            )));
        }
        let frame = r.str("FRAME")?;
        if !frame.trim().eq_ignore_ascii_case("sky") {
            return Err(bad(format!(
                "FRAME = '{frame}': this build reads a response in the instrument's sky frame only"
            )));
        }
        let response = ConstantResponse {
            q0: r.real("RE Q0")?,
            u0: r.real("RE U0")?,
            efficiency: r.real("RE EFFICIENCY")?,
            offset_deg: r.real("RE OFFSET DEG")?,
        };
        if let Some(why) = response.unphysical() {
            return Err(bad(format!("the response: {why}")));
        }
        let mut covariance = [[0.0; 4]; 4];
        for i in 0..4 {
            for j in i..4 {
                let v = r.real(&format!("RE COV{}{}", i + 1, j + 1))?;
                covariance[i][j] = v;
                covariance[j][i] = v;
            }
            if !(covariance[i][i] >= 0.0) {
                return Err(bad(format!("RE COV{0}{0} = {1} is not a variance", i + 1, covariance[i][i])));
            }
        }
        Ok(ResponseCal {
            instrument: r.str("INSTRUMENT")?,
            filter: r.str("FILTER")?,
            plate: r.opt_str("PLATE").unwrap_or_else(|| "half_wave".into()),
            hwp_chi_offset_deg: r.real("HWP CHI OFFSET DEG")?,
            response,
            covariance,
            n_unpolarized: r.opt_int("RE NUNPOL").unwrap_or(0).max(0) as usize,
            n_polarized: r.opt_int("RE NPOL").unwrap_or(0).max(0) as usize,
            product: crate::files::keys::read_product(&mut r)?,
        })
    }

    /// The star's polarization from its measurement in its frame: turned into the response's
    /// sky frame ([`mueller::Frame::to_sky`]: a celestial row back by its position angle too),
    /// then `R(k) ((q, u) - (q0, u0)) / eta`, with the measurement's covariance carried by
    /// `A = R(k) / eta` and the parameters' by the Jacobian `B` (`-A` for `q0, u0`,
    /// `-t / eta` for the efficiency, `2 J t` for the offset with `J` the quarter turn):
    /// `A C A^T + B P B^T`. The instrumental polarization removed is `(q0, u0)`.
    pub fn correct(&self, m: &Measurement) -> std::result::Result<Corrected, crate::correction::correct::Error> {
        crate::correction::correct::check_measurement(m)?;
        let qu = m.frame.to_sky(&m.qu, self.hwp_chi_offset_deg);
        let r = &self.response;
        let (tq, tu) = r.invert(qu.q, qu.u).ok_or(crate::correction::correct::Error::NonFinite {
            what: "the response's efficiency",
            value: r.efficiency,
        })?;
        let (s, c) = (2.0 * r.offset_deg.to_radians()).sin_cos();
        let e = r.efficiency;
        let a = [[c / e, -s / e], [s / e, c / e]];
        let (aq, au, ac) = qu.covariance_through(&a);
        let b = [[-a[0][0], -a[0][1], -tq / e, -2.0 * tu], [-a[1][0], -a[1][1], -tu / e, 2.0 * tq]];
        let p = &self.covariance;
        let mut bpb = [[0.0; 2]; 2];
        for (i, bi) in b.iter().enumerate() {
            for (j, bj) in b.iter().enumerate() {
                bpb[i][j] =
                    (0..4).flat_map(|k| (0..4).map(move |l| (k, l))).map(|(k, l)| bi[k] * p[k][l] * bj[l]).sum();
            }
        }
        let (vq, vu, cv) = (aq + bpb[0][0], au + bpb[1][1], ac + bpb[0][1]);
        let inst = mueller::Qu::new(r.q0, r.u0, p[0][0], p[1][1], p[0][1]);
        Ok(Corrected::of(mueller::Qu::new(tq, tu, vq, vu, cv), inst, false))
    }
}
