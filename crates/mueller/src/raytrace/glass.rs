//! Refractive-index dispersion of optical glasses and coating materials.

use serde::{Deserialize, Serialize};

/// A dispersion law, wavelength in micrometres.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Dispersion {
    /// Constant index.
    Constant(f64),
    /// Sellmeier: `n^2 = 1 + sum B_k l^2 / (l^2 - C_k)`, `C_k` in um^2.
    Sellmeier { b: [f64; 3], c: [f64; 3] },
    /// Cauchy: `n = A + B / l^2 + C / l^4`, `l` in um.
    Cauchy { a: f64, b: f64, c: f64 },
}

impl Dispersion {
    /// Index at vacuum wavelength `wavelength_nm`.
    pub fn index(&self, wavelength_nm: f64) -> f64 {
        let l2 = (wavelength_nm * 1e-3).powi(2);
        match *self {
            Dispersion::Constant(n) => n,
            Dispersion::Sellmeier { b, c } => (1.0 + (0..3).map(|k| b[k] * l2 / (l2 - c[k])).sum::<f64>()).sqrt(),
            Dispersion::Cauchy { a, b, c } => a + b / l2 + c / (l2 * l2),
        }
    }
}

/// The built-in catalog: the makers' published Sellmeier constants.
/// - N-BK7, F2, N-SF6: Schott optical glass data sheets;
/// - fused silica: Malitson 1965 (JOSA 55, 1205);
/// - CaF2: Malitson 1963 (Appl. Opt. 2, 1103);
/// - MgF2 (ordinary ray, for coatings): Dodge 1984 (Appl. Opt. 23, 1980).
pub fn catalog(name: &str) -> Option<Dispersion> {
    let key: String = name.chars().filter(|c| c.is_ascii_alphanumeric()).collect::<String>().to_ascii_uppercase();
    let s = |b: [f64; 3], c: [f64; 3]| Some(Dispersion::Sellmeier { b, c });
    match key.as_str() {
        "AIR" | "VACUUM" => Some(Dispersion::Constant(1.0)),
        "NBK7" | "BK7" => s([1.03961212, 0.231792344, 1.01046945], [0.00600069867, 0.0200179144, 103.560653]),
        "F2" => s([1.34533359, 0.209073176, 0.937357162], [0.00997743871, 0.0470450767, 111.886764]),
        "NSF6" => s([1.77931763, 0.338149866, 2.08734474], [0.0133714182, 0.0617533621, 174.01759]),
        "FUSEDSILICA" | "SIO2" | "FSILICA" => {
            s([0.6961663, 0.4079426, 0.8974794], [0.0684043f64.powi(2), 0.1162414f64.powi(2), 9.896161f64.powi(2)])
        }
        "CAF2" => {
            s([0.5675888, 0.4710914, 3.8484723], [0.050263605f64.powi(2), 0.1003909f64.powi(2), 34.649040f64.powi(2)])
        }
        "MGF2" => {
            s([0.48755108, 0.39875031, 2.3120353], [0.04338408f64.powi(2), 0.09461442f64.powi(2), 23.793604f64.powi(2)])
        }
        _ => None,
    }
}

/// Names accepted by [`catalog`] (for error messages).
pub const CATALOG_NAMES: &str = "air, N-BK7, F2, N-SF6, fused silica, CaF2, MgF2";

#[cfg(test)]
mod tests {
    use super::*;

    /// Catalog nd (587.6 nm) values from the same data sheets.
    #[test]
    fn catalog_matches_published_nd() {
        for (name, nd) in [
            ("N-BK7", 1.5168),
            ("F2", 1.6200),
            ("N-SF6", 1.8052),
            ("fused silica", 1.4585),
            ("CaF2", 1.4338),
            ("MgF2", 1.3777),
        ] {
            let n = catalog(name).unwrap().index(587.56);
            assert!((n - nd).abs() < 3e-4, "{name}: {n} vs {nd}");
        }
        assert!(catalog("unobtainium").is_none());
    }
}
