//! Print the paraxial check and the polarization field of the FORS1-like collimator
//! (a design aid: `cargo run -p instpol-mueller --example collimator [file.toml]`).

use mueller::raytrace::{Prescription, Sampling};

#[derive(serde::Deserialize)]
struct Wrap {
    optics: Prescription,
}

fn main() {
    let path = std::env::args().nth(1).unwrap_or_else(|| "instruments/fors1.toml".into());
    let text = std::fs::read_to_string(&path).expect("read toml");
    let w: Wrap = toml::from_str(&text).expect("parse");
    let c = w.optics.compile(554.0).expect("compile");
    // Focal length from the chief ray at a small field.
    let s = Sampling::default();
    for r in [0.0f64, 0.5, 1.0, 2.0, 3.0, 4.0, 4.5, 4.8] {
        let f = c.field_point(r, 0.0, &s, None).expect("trace");
        let ch = c.chief_ray(r, 0.0, None).expect("chief");
        println!(
            "r {r:4.1}  p {:8.4}%  chief {:8.4}%  phi {:7.2}  lost {}",
            100.0 * f.p,
            100.0 * ch.p,
            f.phi.to_degrees(),
            f.rays_lost
        );
    }
    let per = c.per_surface(4.5, 0.0, &s).unwrap();
    for (i, f) in per.iter().enumerate() {
        println!("{:12} {:8.4}%", c.surface_name(i), 100.0 * f.p);
    }
    // Convergence with the pupil sampling (absolute change of p against 4x the rays).
    for r in [1.0, 3.0, 4.8] {
        let reference = c.field_point(r, 0.0, &Sampling::from_rays(16384), None).unwrap().p;
        for m in [16usize, 64, 256, 512, 1024, 4096] {
            let s = Sampling::from_rays(m);
            let t = std::time::Instant::now();
            let f = c.field_point(r, 0.0, &s, None).unwrap();
            println!(
                "conv r {r:3.1} rays {:5} p {:.8} |p - p(16384)| {:.1e}  {:.2} ms",
                s.rays(),
                f.p,
                (f.p - reference).abs(),
                1e3 * t.elapsed().as_secs_f64()
            );
        }
    }
    let law = w.optics.wavelength_law(4.5, &s, &[400.0, 450.0, 500.0, 600.0, 700.0, 800.0, 900.0]).unwrap();
    println!("law a {:.4} b {:.3e}  {:?}", law.a, law.b, law.samples);
}
