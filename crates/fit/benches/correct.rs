//! Throughput of the correction (the target: >= 1e7 corrections per second per core with the
//! polynomial model, so that a pipeline never waits for it). Run: `cargo bench -p instpol-fit
//! --features bench --bench correct`; criterion reports elements per second for batches of 100 000 catalog rows
//! on one thread, for the exact inversion with full error propagation and for `eq:approx`.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use fit::correction::correct::{CorrectOptions, Corrected, Corrector, Measurement, Method};
use fit::models::model::{FieldModel, InstPol};
use std::hint::black_box;

/// The FORS1 V radial polynomial of section `sec:fors1` (fractions, r in arcmin), radial
/// pattern, constant model covariance: the cost of a cubic polynomial field model.
struct RadialCubic {
    c: [f64; 4],
    half: f64,
}

impl FieldModel for RadialCubic {
    #[inline]
    fn eval(&self, x: f64, y: f64) -> InstPol {
        let r2 = x * x + y * y;
        let r = r2.sqrt();
        let p = ((self.c[3] * r + self.c[2]) * r + self.c[1]) * r + self.c[0];
        let k = if r2 > 0.0 { p / r2 } else { 0.0 };
        InstPol { q: k * (x * x - y * y), u: k * 2.0 * x * y, var_q: 2.5e-7, var_u: 2.5e-7, cov_qu: 0.0 }
    }
    #[inline]
    fn contains(&self, x: f64, y: f64) -> bool {
        x.abs() <= self.half && y.abs() <= self.half
    }
}

fn catalog(n: usize) -> Vec<Measurement> {
    // A deterministic spread of positions and polarizations over the field.
    (0..n)
        .map(|i| {
            let t = i as f64;
            Measurement::at_plate(
                3.4 * (0.618_033_988_7 * t).fract() * 2.0 - 3.4,
                3.4 * (0.754_877_666_2 * t).fract() * 2.0 - 3.4,
                0.01 * (0.1 * t).cos(),
                0.01 * (0.1 * t).sin(),
                5e-4,
                5e-4,
                0.0,
            )
        })
        .collect()
}

/// A radial3 calibration fitted to a simulated FORS1 V sky field (30 px bins, 0.01% noise).
fn calibration(free_centre: bool) -> fit::Calibration {
    use fit::models::pipeline::{calibrate_bins, CalibrateOptions, CalibrationMeta};
    let truth = fit::RadialModel::new(1, vec![0.012e-2, 0.046e-2, 0.002e-2], [0.1, -0.05]);
    let centres = fit::models::synth::bin_centres(2048, 2048, 0.2, 30);
    let bins: Vec<fit::Bin> = fit::models::synth::sky_field(&centres, &truth, 0.0, 0.0, 1e-4, 7)
        .iter()
        .map(|m| fit::Bin::new(m.x, m.y, m.qu.q, m.qu.u, m.qu.sigma_q(), m.qu.sigma_u()))
        .collect();
    let meta = CalibrationMeta {
        instrument: "FORS1".into(),
        filter: "V".into(),
        lambda_nm: 554.0,
        hwp_chi_offset_deg: 0.0,
        pixel: None,
        provenance: fit::files::calfile::Provenance::now("bench", vec![]),
    };
    let mut opts = CalibrateOptions::default();
    opts.fit.free_centre = free_centre;
    // The bins cover 2040 of 2048 px; the catalogue reaches +-3.4': widen the valid region.
    opts.region_margin = 0.1;
    calibrate_bins(bins, meta, &opts).unwrap().calibration
}

fn bench(c: &mut Criterion) {
    let model = RadialCubic { c: [0.0, 0.012e-2, 0.046e-2, 0.002e-2], half: 3.42 };
    let input = catalog(100_000);
    let mut out = vec![Corrected::default(); input.len()];
    let mut g = c.benchmark_group("correct");
    g.throughput(Throughput::Elements(input.len() as u64));
    for (name, method) in [("exact", Method::Exact), ("first_order", Method::FirstOrder)] {
        let cor = Corrector::new(
            &model,
            CorrectOptions { method, zero_angle_deg: 0.01f64.to_degrees(), ..Default::default() },
        );
        g.bench_function(name, |b| {
            b.iter(|| cor.correct_batch(black_box(&input), black_box(&mut out)).unwrap());
        });
    }
    // The calibration file's radial model (fit::models::radial), with a coefficient covariance.
    let mut rm = fit::RadialModel::new(1, vec![0.012e-2, 0.046e-2, 0.002e-2], [0.0, 0.0]);
    let np = rm.n_params();
    for i in 0..3 {
        rm.cov[i * np + i] = (1e-5f64).powi(2);
    }
    let cor = Corrector::new(&rm, CorrectOptions::default());
    g.bench_function("exact_fit_radial_model", |b| {
        b.iter(|| cor.correct_batch(black_box(&input), black_box(&mut out)).unwrap());
    });
    // A calibration as `instpol correct` holds it: the radial fit of a simulated V sky field
    // (fixed and free centre, with the fit's covariance), through `Calibration`'s FieldModel.
    for (name, free_centre) in [("exact_calibration_radial_fixed", false), ("exact_calibration_radial_free", true)] {
        let cal = calibration(free_centre);
        let cor = Corrector::new(&cal, CorrectOptions::for_calibration(&cal));
        g.bench_function(name, |b| {
            b.iter(|| cor.correct_batch(black_box(&input), black_box(&mut out)).unwrap());
        });
    }
    // The same through a trait object, as the CLI holds a loaded calibration.
    let dynm: &dyn FieldModel = &model;
    let cor = Corrector::new(dynm, CorrectOptions::default());
    g.bench_function("exact_dyn", |b| {
        b.iter(|| cor.correct_batch(black_box(&input), black_box(&mut out)).unwrap());
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
