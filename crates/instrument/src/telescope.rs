//! The `[telescope]` section: the telescope in front of the instrument, as far as polarization
//! goes (the chain's first element, `docs/architecture.md`).
//!
//! - `focus`: `"cassegrain"` (M1, M2 near normal incidence: no first-order instrumental
//!   polarization from the telescope, and the instrument turns with the sky) or `"nasmyth"`
//!   (a 45 deg tertiary mirror whose plane of incidence turns with the parallactic angle as seen
//!   from the sky: a few percent of polarization, the largest instrumental term such an
//!   instrument has).
//! - `[[telescope.mirrors]]`: name, metal (a built-in table `aluminium` / `silver` of
//!   [`mueller::mirror::MetalTable::builtin`], or a `lambda,n,k` table file), angle of
//!   incidence (deg), and an optional over-layer (`overlayer_thickness_nm` of
//!   `overlayer = "alumina"` or a real index).
//! - Header keywords of the parallactic angle at the start and end of an exposure and of the
//!   rotator / adapter angle, with the sense of each against the convention of
//!   [`mueller::mirror`] (position angle of the zenith, north through east): `+1` the header
//!   angle is that angle, `-1` it counts the other way.
//! - `site_latitude_deg`: for simulated nights (parallactic-angle tracks from hour angles).
//!
//! Data only: the mirror Mueller matrices are `mueller::mirror`'s, the fitted models
//! `fit::telescope`'s.

use serde::{Deserialize, Serialize};
use std::path::Path;

/// Where the instrument sits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Focus {
    Cassegrain,
    Nasmyth,
}

impl Focus {
    pub fn name(self) -> &'static str {
        match self {
            Focus::Cassegrain => "cassegrain",
            Focus::Nasmyth => "nasmyth",
        }
    }
}

/// One mirror of the train, in the order light meets them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Mirror {
    pub name: String,
    /// `aluminium` / `silver` (built-in tables) or the path of a `lambda,n,k` table (micron).
    pub metal: String,
    /// Angle of incidence (deg): 0 for M1, M2; 45 for a Nasmyth M3.
    pub aoi_deg: f64,
    /// Over-layer material: `"alumina"` (the native oxide of aluminium,
    /// [`mueller::mirror::alumina_index`]) or a real refractive index as a string ("1.38").
    #[serde(default)]
    pub overlayer: Option<String>,
    /// Over-layer thickness (nm); 0 or absent: bare metal.
    #[serde(default)]
    pub overlayer_thickness_nm: f64,
}

/// The `[telescope]` section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Telescope {
    pub focus: Focus,
    /// Geographic latitude of the site (deg, north positive), for simulated nights.
    #[serde(default)]
    pub site_latitude_deg: Option<f64>,
    #[serde(default)]
    pub mirrors: Vec<Mirror>,
    /// Header keyword of the parallactic angle (deg) at the start of an exposure.
    #[serde(default)]
    pub parang_start_keyword: String,
    /// Header keyword of the parallactic angle (deg) at the end of an exposure (empty: the
    /// start value is used for the whole exposure).
    #[serde(default)]
    pub parang_end_keyword: String,
    /// `+1`: the header's parallactic angle is the position angle of the zenith, north through
    /// east (the convention of `mueller::mirror`); `-1`: it counts the other way.
    #[serde(default = "plus_one")]
    pub parang_sense: i32,
    /// Header keyword of the rotator / adapter angle (deg); empty: none.
    #[serde(default)]
    pub rotator_keyword: String,
    /// `+1` / `-1`: the sense of the rotator angle against `mueller::rotation`.
    #[serde(default = "plus_one")]
    pub rotator_sense: i32,
}

fn plus_one() -> i32 {
    1
}

impl Telescope {
    /// The mirror at oblique incidence (the Nasmyth M3), if any.
    pub fn oblique_mirror(&self) -> Option<&Mirror> {
        self.mirrors.iter().find(|m| m.aoi_deg > 1.0)
    }

    /// The parallactic angles (rad, in the convention of `mueller::mirror`) at the start and
    /// end of an exposure from its header values (deg), the sense applied; the end is `None`
    /// when the header gives only the start. (`fit::telescope::Track::new` makes the track,
    /// going the short way round across +-180 deg.)
    pub fn parallactic_rad(&self, start_deg: f64, end_deg: Option<f64>) -> (f64, Option<f64>) {
        let s = self.parang_sense as f64;
        (start_deg.to_radians() * s, end_deg.map(|e| e.to_radians() * s))
    }

    /// Validate; errors are `(key, value, why)` relative to `telescope`.
    pub(crate) fn check(&self, dir: Option<&Path>) -> Result<(), (String, String, String)> {
        let bad = |k: &str, v: String, why: &str| Err((format!("telescope.{k}"), v, why.to_string()));
        if let Some(l) = self.site_latitude_deg {
            if !(l.is_finite() && (-90.0..=90.0).contains(&l)) {
                return bad("site_latitude_deg", l.to_string(), "must be a latitude in degrees (-90 to 90)");
            }
        }
        for (k, v) in [("parang_sense", self.parang_sense), ("rotator_sense", self.rotator_sense)] {
            if v != 1 && v != -1 {
                return bad(k, v.to_string(), "must be 1 or -1");
            }
        }
        for m in &self.mirrors {
            let key = |f: &str| format!("mirrors.{}.{f}", m.name);
            if !(m.aoi_deg.is_finite() && (0.0..90.0).contains(&m.aoi_deg)) {
                return bad(&key("aoi_deg"), m.aoi_deg.to_string(), "must be an angle of incidence in [0, 90) deg");
            }
            let t = m.overlayer_thickness_nm;
            if !(t.is_finite() && (0.0..=10_000.0).contains(&t)) {
                return bad(&key("overlayer_thickness_nm"), t.to_string(), "must be 0 to 10000 nm");
            }
            if let Some(o) = &m.overlayer {
                let ok = o.eq_ignore_ascii_case("alumina") || o.parse::<f64>().is_ok_and(|n| n.is_finite() && n >= 1.0);
                if !ok {
                    return bad(&key("overlayer"), o.clone(), "must be \"alumina\" or a real refractive index >= 1");
                }
            } else if t > 0.0 {
                return bad(&key("overlayer_thickness_nm"), t.to_string(), "a thickness needs an overlayer material");
            }
            let builtin = mueller::mirror::MetalTable::builtin(&m.metal).is_ok();
            let file = dir.map(|d| d.join(&m.metal)).unwrap_or_else(|| Path::new(&m.metal).to_path_buf());
            if !builtin && !file.is_file() {
                return bad(
                    &key("metal"),
                    m.metal.clone(),
                    "is neither a built-in table (aluminium, silver) nor a table file",
                );
            }
        }
        match self.focus {
            Focus::Nasmyth => {
                if self.oblique_mirror().is_none() {
                    return bad(
                        "mirrors",
                        format!("{} mirrors", self.mirrors.len()),
                        "a Nasmyth focus needs its oblique (45 deg) tertiary mirror listed",
                    );
                }
            }
            Focus::Cassegrain => {
                if let Some(m) = self.oblique_mirror() {
                    return bad(
                        &format!("mirrors.{}.aoi_deg", m.name),
                        m.aoi_deg.to_string(),
                        "a Cassegrain focus has no oblique mirror (use focus = \"nasmyth\")",
                    );
                }
            }
        }
        if !self.parang_end_keyword.is_empty() && self.parang_start_keyword.is_empty() {
            return bad("parang_end_keyword", self.parang_end_keyword.clone(), "needs parang_start_keyword too");
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn t() -> Telescope {
        Telescope {
            focus: Focus::Nasmyth,
            site_latitude_deg: None,
            mirrors: vec![],
            parang_start_keyword: String::new(),
            parang_end_keyword: String::new(),
            parang_sense: 1,
            rotator_keyword: String::new(),
            rotator_sense: 1,
        }
    }

    #[test]
    fn the_sense_turns_the_header_angle() {
        let d = |x: f64| x.to_radians();
        assert_eq!(t().parallactic_rad(10.0, Some(20.0)), (d(10.0), Some(d(20.0))));
        let m = Telescope { parang_sense: -1, ..t() };
        assert_eq!(m.parallactic_rad(10.0, None), (-d(10.0), None));
    }
}
