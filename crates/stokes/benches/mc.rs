//! Monte Carlo engine against the cost of its random numbers alone, one thread, N = 4,
//! SNR = 100 (5000 counts per beam), the numpy peer's work (`bench/mc.sh` runs the side-by-side
//! comparison with `shared/peers/numpy_mc.py`).
//!
//! `cargo bench -p instpol-stokes --features bench --bench mc`

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use rand::SeedableRng;
use rand_distr::Distribution;
use rand_xoshiro::Xoshiro256PlusPlus;
use std::hint::black_box;
use stokes::mc::poisson::PoissonSampler;
use stokes::mc::{Engine, McConfig, Noise};

const TRIALS: u64 = 200_000;

fn engine_vs_draws(c: &mut Criterion) {
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    let mut g = c.benchmark_group("mc_one_thread");
    g.throughput(Throughput::Elements(TRIALS));
    g.sample_size(20);
    for noise in Noise::ALL {
        let mut cfg = McConfig::new(4, 100.0, 0.01, 30f64.to_radians(), TRIALS, noise);
        cfg.seed = 1;
        let eng = Engine::new(&cfg).unwrap();
        g.bench_function(format!("engine/{noise}"), |b| b.iter(|| pool.install(|| black_box(eng.run(None)))));
        g.bench_function(format!("draws_only/{noise}"), |b| b.iter(|| pool.install(|| black_box(eng.draw_only()))));
    }
    g.finish();
}

/// One Poisson draw of mean 5000: the alias table against rand_distr's PTRS.
fn poisson_draw(c: &mut Criterion) {
    let mut g = c.benchmark_group("poisson_5000");
    const N: u64 = 100_000;
    g.throughput(Throughput::Elements(N));
    let alias = PoissonSampler::new(5000.0).unwrap();
    let ptrs = rand_distr::Poisson::new(5000.0).unwrap();
    g.bench_function("alias", |b| {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(1);
        b.iter(|| {
            let mut s = 0.0;
            for _ in 0..N {
                s += alias.sample(&mut rng);
            }
            black_box(s)
        })
    });
    g.bench_function("rand_distr_ptrs", |b| {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(1);
        b.iter(|| {
            let mut s = 0.0f64;
            for _ in 0..N {
                s += ptrs.sample(&mut rng);
            }
            black_box(s)
        })
    });
    g.finish();
}

criterion_group!(benches, engine_vs_draws, poisson_draw);
criterion_main!(benches);
