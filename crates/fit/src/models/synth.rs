//! Synthetic sky-field measurements for tests and the demo: the measured normalized Stokes
//! parameters of an empty field of known sky polarization seen through an instrumental field
//! `M_I(p(x, y), phi(x, y))` (`eq:instpol`, the `mueller` forward model), with Gaussian noise per
//! bin. This is the binned-map shortcut; full frames come from the `sim` crate.

use crate::models::model::FieldModel;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use rand_xoshiro::Xoshiro256PlusPlus;

/// One measured bin: position (arcmin), and the measured `Q1/I1`, `U1/I1` with the noise of
/// each component (independent, equal: `var_q = var_u = sigma^2`, no covariance).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MeasuredBin {
    pub x: f64,
    pub y: f64,
    pub qu: mueller::Qu,
}

/// Bin centres (arcmin from the detector centre) of a regular grid of `bin_px` bins over a
/// `nx x ny` px detector of `scale` arcsec/px (a bin cut by the edge is left out).
pub fn bin_centres(nx: usize, ny: usize, scale_arcsec: f64, bin_px: usize) -> Vec<(f64, f64)> {
    let bins = field::FieldCoords::centred(nx, ny, scale_arcsec).binned(bin_px);
    let mut v = vec![];
    for j in 0..ny / bin_px {
        for i in 0..nx / bin_px {
            v.push(bins.pixel_to_arcmin(i as f64, j as f64));
        }
    }
    v
}

/// Measure the sky `(q0, u0)` through the instrumental field `truth` at each position:
/// `S1 = M_I(p, phi) S0` normalized, plus Gaussian noise `sigma` per component (seeded).
pub fn sky_field(
    centres: &[(f64, f64)],
    truth: &dyn FieldModel,
    sky_q: f64,
    sky_u: f64,
    sigma: f64,
    seed: u64,
) -> Vec<MeasuredBin> {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
    let n = Normal::new(0.0, sigma.max(0.0)).unwrap_or_else(|_| Normal::new(0.0, 0.0).expect("zero sigma"));
    let s0 = mueller::stokes_qu(1.0, sky_q, sky_u);
    centres
        .iter()
        .map(|&(x, y)| {
            let ip = truth.eval(x, y);
            let (p, phi) = ip.p_chi();
            let s1 = mueller::partial_polarizer(p, phi) * s0;
            let q1 = s1[1] / s1[0] + n.sample(&mut rng);
            let u1 = s1[2] / s1[0] + n.sample(&mut rng);
            MeasuredBin { x, y, qu: mueller::Qu::from_sigmas(q1, u1, sigma, sigma, 0.0) }
        })
        .collect()
}

/// A field model given by a closure (for synthetic truths).
pub struct FnField<F: Fn(f64, f64) -> (f64, f64) + Send + Sync>(pub F);

impl<F: Fn(f64, f64) -> (f64, f64) + Send + Sync> FieldModel for FnField<F> {
    fn eval(&self, x: f64, y: f64) -> crate::models::model::InstPol {
        let (q, u) = (self.0)(x, y);
        crate::models::model::InstPol { q, u, ..Default::default() }
    }
    fn contains(&self, _x: f64, _y: f64) -> bool {
        true
    }
}

/// Write a field as a pair of `(2, ny, nx)` FITS cubes (plane 1 `Q/I` or `U/I`, plane 2 a
/// constant error `sigma`), map pixel `(i, j)` covering detector pixels `[bin i, bin (i+1))`
/// of a `det_nx x det_ny` px detector of `scale` arcsec/px: the format of the public FORS2 maps,
/// read by `import_map` and by the simulator's map-shaped instrumental field.
#[allow(clippy::too_many_arguments)]
pub fn write_qu_cubes(
    q_path: &std::path::Path,
    u_path: &std::path::Path,
    field: &dyn FieldModel,
    det_nx: usize,
    det_ny: usize,
    scale_arcsec: f64,
    bin: usize,
    sigma: f64,
) -> crate::Result<()> {
    let (nx, ny) = (det_nx.div_ceil(bin), det_ny.div_ceil(bin));
    let cells = field::FieldCoords::centred(det_nx, det_ny, scale_arcsec).binned(bin);
    let mut q = vec![0.0; 2 * nx * ny];
    let mut u = vec![0.0; 2 * nx * ny];
    for j in 0..ny {
        for i in 0..nx {
            let (x, y) = cells.pixel_to_arcmin(i as f64, j as f64);
            let v = field.eval(x, y);
            let k = j * nx + i;
            q[k] = v.q;
            u[k] = v.u;
            q[nx * ny + k] = sigma;
            u[nx * ny + k] = sigma;
        }
    }
    for (path, data) in [(q_path, &q), (u_path, &u)] {
        let err = |m: String| crate::Error::Fits { path: path.into(), doing: "writing a map cube".into(), message: m };
        let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(std::path::Path::new("."));
        let tmp = skyfield::fits::temp_beside(path, ".fits")
            .map_err(|source| crate::Error::Io { path: dir.into(), err: source })?
            .into_temp_path();
        {
            let mut f = fitsio::FitsFile::create(&tmp)
                .with_custom_primary(&fitsio::images::ImageDescription {
                    data_type: fitsio::images::ImageType::Double,
                    dimensions: &[2, ny, nx],
                })
                .overwrite()
                .open()
                .map_err(|e| err(e.to_string()))?;
            let h = f.primary_hdu().map_err(|e| err(e.to_string()))?;
            h.write_image(&mut f, data).map_err(|e| err(e.to_string()))?;
            skyfield::provenance::stamp(&mut f).map_err(err)?;
            // Status-checked close, fsync, rename (see skyfield::durable).
            skyfield::durable::close_fits(f).map_err(err)?;
        }
        skyfield::durable::finish(tmp, path).map_err(|e| crate::Error::Io { path: path.into(), err: e })?;
    }
    Ok(())
}
