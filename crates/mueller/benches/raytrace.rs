//! Ray-tracing throughput: field points x pupil rays per second on the FORS1-like collimator.
//! `cargo bench -p instpol-mueller --features bench --bench raytrace`

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use mueller::raytrace::{Prescription, Sampling};
use std::hint::black_box;

#[derive(serde::Deserialize)]
struct Wrap {
    optics: Prescription,
}

fn bench(c: &mut Criterion) {
    let w: Wrap = toml::from_str(include_str!("../../../instruments/fors1.toml")).unwrap();
    let comp = w.optics.compile(554.0).unwrap();
    let radii: Vec<f64> = (0..13).map(|i| 4.8 * i as f64 / 12.0).collect();
    let mut g = c.benchmark_group("raytrace");
    for rays in [64usize, 256, 1024] {
        let s = Sampling::from_rays(rays);
        // One field point, single thread: rays per second.
        g.throughput(Throughput::Elements(s.rays() as u64));
        g.bench_with_input(BenchmarkId::new("field_point", s.rays()), &s, |b, s| {
            b.iter(|| comp.field_point(black_box(3.0), 1.0, s, None).unwrap())
        });
        // A 13-point profile, parallel over field points: field points x rays per second.
        g.throughput(Throughput::Elements((s.rays() * radii.len()) as u64));
        g.bench_with_input(BenchmarkId::new("profile_13", s.rays()), &s, |b, s| {
            b.iter(|| comp.profile(black_box(&radii), 0.3, s, None).unwrap())
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
