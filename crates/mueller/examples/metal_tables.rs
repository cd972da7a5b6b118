//! Write the shipped metal tables (`instruments/metals/`) from the Lorentz-Drude fits of
//! Rakic et al. 1998 (Applied Optics 37, 5271): `cargo run -p instpol-mueller --example metal_tables`.

use mueller::mirror::{lorentz_drude, LorentzDrude, ALUMINIUM_LD, SILVER_LD};
use std::fmt::Write;

fn table(name: &str, m: &LorentzDrude) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "# {name}: complex refractive index n + i k against vacuum wavelength (micron).");
    let _ = writeln!(s, "# Evaluated from the Lorentz-Drude model of Rakic, Djurisic, Elazar & Majewski 1998,");
    let _ = writeln!(
        s,
        "# Applied Optics 37, 5271, Table 1 (plasma energy {} eV, f0 = {}, Gamma0 = {} eV,",
        m.omega_p, m.f0, m.gamma0
    );
    let _ = writeln!(
        s,
        "# {} Lorentz oscillators), eps(w) = 1 - f0 wp^2/(w(w + i G0)) + sum f_j wp^2/(w_j^2 - w^2 - i w G_j),",
        m.oscillators.len()
    );
    let _ = writeln!(
        s,
        "# n + i k = sqrt(eps), by `cargo run -p instpol-mueller --example metal_tables` (mueller::mirror)."
    );
    let _ = writeln!(s, "lambda,n,k");
    let mut w: f64 = 0.30;
    while w <= 1.2001 {
        let n = lorentz_drude(m, w);
        let _ = writeln!(s, "{w:.3},{:.5},{:.5}", n.re, n.im);
        w += 0.01;
    }
    s
}

fn main() -> std::io::Result<()> {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../instruments/metals");
    std::fs::create_dir_all(&dir)?;
    std::fs::write(dir.join("aluminium.txt"), table("Aluminium", &ALUMINIUM_LD))?;
    std::fs::write(dir.join("silver.txt"), table("Silver", &SILVER_LD))?;
    Ok(())
}
