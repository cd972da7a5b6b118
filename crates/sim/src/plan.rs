//! The simulation plan: the steps a scene needs, built once, and the frames they make.

use crate::scene::{Coords, Extended, InstPolSpec, Profile, Psf, Scene, Star};
use crate::Error;
use field::{Analyser, ExposureForward, FieldBlock, PlateMotion};
use field::{FieldModel, GridMap, InstPol, NearestCell, RadialPattern};
use instrument::Instrument;
use mueller::{DualBeam, Harmonic, Hwp, Stokes, Wollaston};
use rand::{RngExt, SeedableRng};
use rand_distr::{Distribution, Normal, Poisson};
use rand_xoshiro::Xoshiro256PlusPlus;
use rayon::prelude::*;
use skyfield::beams::{BeamGeometry, PixelKind};
use skyfield::fits::{write_frame, Bitpix, KeyValue};
use std::f64::consts::PI;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Normalized Stokes `(I, Q, U)` of one sky pixel at the plate (V = 0 throughout).
type Iqu = [f64; 3];

/// The telescope of a scene: its band model (the chain's) and each exposure's
/// parallactic-angle track.
struct TelescopeTerm {
    model: mueller::telescope::BandModel,
    tracks: Vec<mueller::telescope::Track>,
    /// Each exposure's hour angles at start and end (deg), for `--explain`.
    hour_angles: Vec<(f64, f64)>,
}

/// The sky at the HWP: one vector for a uniform sky with no field-dependent effect, else one
/// per sky pixel (in the order of `Plan::sky_pixels`).
#[derive(Debug, Clone)]
enum SkyAtPlate {
    Constant(Iqu),
    Image(Vec<Iqu>),
}

/// The sky's circular polarization at the plate (e-/px per exposure: `sky.v` times the sky's
/// brightness): one value for a uniform sky, else one per sky pixel (in the order of
/// `Plan::sky_pixels`).
#[derive(Debug, Clone)]
enum SkyV {
    Constant(f64),
    Image(Vec<f64>),
}

/// A per-pixel detector step, applied in this order to the electrons of each pixel.
#[derive(Debug, Clone, Copy, PartialEq)]
enum DetStep {
    /// Multiply by the (flat-field error) gain map.
    Flat,
    /// Replace the expected electrons by a Poisson draw.
    Photon,
    /// Add this frame's cosmic-ray charge.
    Cosmic,
    /// Add Gaussian read noise (e- rms).
    ReadNoise(f64),
    /// Electrons to ADU.
    Gain(f64),
    /// Add a bias level (ADU).
    Bias(f64),
    /// Clip at the saturation level (ADU).
    Saturate(f64),
}

impl DetStep {
    fn random(&self) -> bool {
        matches!(self, DetStep::Photon | DetStep::ReadNoise(_))
    }
}

/// Everything a scene needs, computed once; frames are rendered from it.
/// Most bytes of frames a simulation writes unless told it may ([`Plan::check_output_size`]):
/// 16 GB, a thousand full-size FORS frames, more than any test or tutorial scene needs.
pub const MAX_OUTPUT_BYTES: u64 = 16_000_000_000;

pub struct Plan {
    pub scene: Scene,
    pub inst: Instrument,
    geom: BeamGeometry,
    /// (o, e) detector indices of every sky pixel the mask lets through.
    sky_pixels: Vec<(u32, u32)>,
    sky: SkyAtPlate,
    /// Behind a telescope: the field's elements at every sky pixel (in the order of
    /// `sky_pixels`), applied after each exposure's telescope matrix
    /// ([`field::InstrumentChain::field_block_at`]).
    behind: Option<Vec<FieldBlock>>,
    /// Per exposure: the chain's forward model compiled ([`field::InstrumentChain::exposure_forward`]).
    forwards: Vec<ExposureForward>,
    /// The sky's `V` at the plate (scene `sky.v`), which the sky's `(I, Q, U)` does not hold.
    sky_v: Option<SkyV>,
    flat: Option<Vec<f64>>,
    steps: Vec<DetStep>,
    cosmic: Option<crate::scene::CosmicSpec>,
    bitpix: Bitpix,
    explain: Vec<String>,
    /// Stars drawn frame by frame (maskless layouts, or frames that move): each beam's image
    /// placed by the layout at the star's position in that frame.
    moving: Vec<StarDraw>,
    /// Pointing offset of each frame (px).
    shifts: Vec<(f64, f64)>,
    /// The telescope's parallactic-angle track of each exposure (scene `[telescope]`).
    tracks: Option<Vec<mueller::telescope::Track>>,
    /// The optical chain every frame is rendered through: the telescope, the field's elements,
    /// the plate and the analyser (`forwards`, `behind`, `sky` and `moving` are its pieces).
    chain: field::InstrumentChain,
}

/// A star drawn frame by frame: its position (px, o image, before the frame's shift), its
/// Stokes vector as it enters the exposures' part of the chain
/// ([`field::InstrumentChain::before_exposures`]) and its PSF.
struct StarDraw {
    x: f64,
    y: f64,
    st: Iqu,
    psf: PsfShape,
    /// `V` at the plate (e-, with `st`'s normalization; 0 for the sky's stars without circular
    /// polarization).
    v: f64,
    /// With a telescope: `st` is the light before it, and this the field's block at the star
    /// (applied after the telescope's matrix of each frame).
    field: Option<FieldBlock>,
}

/// A circular PSF profile of `r^2` (px^2) and the radius it is drawn to.
#[derive(Clone, Copy)]
enum PsfShape {
    Gaussian { sigma: f64 },
    Moffat { alpha: f64, beta: f64 },
}

impl PsfShape {
    fn of(s: &Star, inst: &Instrument) -> Self {
        let fwhm = s.fwhm_arcsec / inst.detector.pixel_scale_arcsec;
        match s.psf {
            Psf::Gaussian => PsfShape::Gaussian { sigma: fwhm / (8.0 * 2f64.ln()).sqrt() },
            Psf::Moffat => {
                let b = s.moffat_beta;
                PsfShape::Moffat { alpha: fwhm / (2.0 * (2f64.powf(1.0 / b) - 1.0).sqrt()), beta: b }
            }
        }
    }

    #[inline]
    fn at(&self, r2: f64) -> f64 {
        match *self {
            PsfShape::Gaussian { sigma } => (-0.5 * r2 / (sigma * sigma)).exp(),
            PsfShape::Moffat { alpha, beta } => (1.0 + r2 / (alpha * alpha)).powf(-beta),
        }
    }

    /// Radius (px) the profile is drawn to: 8 sigma, or where a Moffat falls to 1e-6 of its
    /// peak (at most 300 px).
    fn radius(&self) -> f64 {
        match *self {
            PsfShape::Gaussian { sigma } => 8.0 * sigma,
            PsfShape::Moffat { alpha, beta } => (alpha * (1e-6f64.powf(-1.0 / beta) - 1.0).sqrt()).min(300.0),
        }
    }
}

/// What [`simulate`] wrote.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Simulated {
    #[serde(rename = "outputs")]
    pub frames: Vec<PathBuf>,
    #[serde(rename = "truth_output")]
    pub truth: PathBuf,
    /// Bias frames' chip files (chip instruments whose bias no overscan removes), for
    /// `instpol master-bias`; in the output's `bias/` folder, apart from the science frames.
    #[serde(rename = "bias_outputs", skip_serializing_if = "Vec::is_empty")]
    pub bias: Vec<PathBuf>,
}

/// A random stream for (seed, purpose, frame, row): independent of thread scheduling.
fn stream(seed: u64, purpose: u64, frame: u64, row: u64) -> Xoshiro256PlusPlus {
    fn mix(mut z: u64) -> u64 {
        z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    Xoshiro256PlusPlus::seed_from_u64(mix(seed ^ mix(purpose ^ mix(frame ^ mix(row)))))
}

const STREAM_FLAT: u64 = 1;
const STREAM_PIXELS: u64 = 2;
const STREAM_COSMIC: u64 = 3;
const STREAM_TRANSPARENCY: u64 = 4;
/// The read noise of raw files' pre/overscan regions and of bias frames.
const STREAM_READOUT: u64 = 5;

fn file_err(path: &Path, m: impl std::fmt::Display) -> Error {
    Error::File { path: path.into(), message: m.to_string() }
}

/// Read a 2-D map (or the first plane of a cube) with its size `(nx, ny)`.
fn read_map(path: &Path) -> Result<(Vec<f64>, usize, usize), Error> {
    let mut f = fitsio::FitsFile::open(path).map_err(|e| file_err(path, format!("cannot open as FITS: {e}")))?;
    let hdu = f.primary_hdu().map_err(|e| file_err(path, e))?;
    let shape = match &hdu.info {
        fitsio::hdu::HduInfo::ImageInfo { shape, .. } => shape.clone(),
        _ => return Err(file_err(path, "primary HDU is not an image")),
    };
    let (ny, nx) = match shape.as_slice() {
        [ny, nx] => (*ny, *nx),
        [_, ny, nx] => (*ny, *nx),
        _ => return Err(file_err(path, format!("expected a 2-D image or a cube, shape {shape:?}"))),
    };
    // The header's sizes are checked before CFITSIO allocates for them: an empty axis (no
    // first plane to take) and a claimed size larger than the file (a corrupt NAXISn would
    // otherwise abort on allocation) are errors.
    if shape.contains(&0) {
        return Err(file_err(path, format!("the image has no pixels: shape {shape:?} (header NAXISn)")));
    }
    let len = std::fs::metadata(path).map(|m| m.len() as u128).unwrap_or(u128::MAX);
    let claimed = shape.iter().try_fold(1u128, |a, &n| a.checked_mul(n as u128)).unwrap_or(u128::MAX);
    if claimed > len {
        return Err(file_err(
            path,
            format!("the header claims {shape:?} values (NAXISn) but the file holds only {len} bytes"),
        ));
    }
    let v: Vec<f64> = hdu.read_image(&mut f).map_err(|e| file_err(path, format!("cannot read data: {e}")))?;
    if v.len() < nx * ny {
        return Err(file_err(path, format!("read {} values, the header says {nx} x {ny}", v.len())));
    }
    Ok((v[..nx * ny].to_vec(), nx, ny))
}

/// A ray tracer's field profile (`mueller::raytrace::FieldFile`) about `centre` as a field
/// model: `p` interpolated in radius, angle radial plus the tabulated offset.
struct RaytraceField {
    field: mueller::raytrace::FieldFile,
    centre: [f64; 2],
}

impl FieldModel for RaytraceField {
    fn eval(&self, x: f64, y: f64) -> InstPol {
        let (p, phi) = self.p_phi(x, y);
        InstPol { q: p * (2.0 * phi).cos(), u: p * (2.0 * phi).sin(), ..Default::default() }
    }

    fn contains(&self, _x: f64, _y: f64) -> bool {
        true
    }

    /// A negative `p` is the same partial polarizer turned by 90 deg.
    fn p_phi(&self, x: f64, y: f64) -> (f64, f64) {
        let (p, phi) = self.field.eval(x - self.centre[0], y - self.centre[1]);
        if p >= 0.0 {
            (p, phi)
        } else {
            (-p, phi + 0.5 * PI)
        }
    }
}

/// The field model a scene's `[effects.instpol]` names: a radial pattern, Q/U maps on the
/// detector (each map pixel a block of `bin_px x bin_px` detector pixels, nearest cell), or a
/// ray tracer's profile.
fn load_field(spec: &InstPolSpec, inst: &Instrument) -> Result<Arc<dyn FieldModel>, Error> {
    Ok(match spec {
        InstPolSpec::Radial { coeffs_percent, centre_arcmin, phi_offset_deg } => Arc::new(RadialPattern {
            coeffs: coeffs_percent.iter().map(|c| c / 100.0).collect(),
            centre: *centre_arcmin,
            phi_offset: phi_offset_deg.to_radians(),
        }),
        InstPolSpec::Map { q_file, u_file, bin_px } => {
            let (q, nx, ny) = read_map(q_file)?;
            let (u, ux, uy) = read_map(u_file)?;
            if (ux, uy) != (nx, ny) {
                return Err(file_err(u_file, format!("U map is {ux} x {uy}, Q map is {nx} x {ny}")));
            }
            let cells = inst.field_coords().binned((*bin_px).max(1));
            let zero = vec![0.0; nx * ny];
            Arc::new(NearestCell(GridMap::on_pixels(&cells, nx, ny, q, u, zero.clone(), zero)))
        }
        InstPolSpec::Raytrace { file, centre_arcmin } => {
            let text = std::fs::read_to_string(file).map_err(|e| file_err(file, e))?;
            let f: mueller::raytrace::FieldFile = serde_json::from_str(&text).map_err(|e| file_err(file, e))?;
            if f.format != mueller::raytrace::FieldFile::FORMAT {
                return Err(file_err(
                    file,
                    format!("format '{}' is not {}", f.format, mueller::raytrace::FieldFile::FORMAT),
                ));
            }
            let n = f.radius_arcmin.len();
            if n == 0 || f.p.len() != n || f.phi_rel_deg.len() != n {
                return Err(file_err(file, "radius_arcmin, p and phi_rel_deg must have the same, non-zero length"));
            }
            if f.radius_arcmin.windows(2).any(|w| !(w[1] > w[0])) {
                return Err(file_err(file, "radius_arcmin must increase"));
            }
            if f.p.iter().chain(&f.phi_rel_deg).any(|v| !v.is_finite()) {
                return Err(file_err(file, "p and phi_rel_deg must be finite"));
            }
            Arc::new(RaytraceField { field: f, centre: *centre_arcmin })
        }
    })
}

/// An instrumental field is a partial polarizer of degree `p <= 1` everywhere on the detector
/// (as the sky's p is refused above 1): refused naming the key and the first position where
/// it is not, searched over the field's coordinates of every detector pixel of a grid of at
/// most 257 x 257 points with the corners, and for a radial pattern also along every radius
/// out to the farthest corner (a polynomial's peak between grid points). NaN map cells carry
/// no instrumental polarization and pass.
fn check_field_physical(spec: &InstPolSpec, model: &dyn FieldModel, inst: &Instrument) -> Result<(), Error> {
    let (key, value) = match spec {
        InstPolSpec::Radial { coeffs_percent, .. } => ("effects.instpol.coeffs_percent", format!("{coeffs_percent:?}")),
        InstPolSpec::Map { q_file, u_file, .. } => {
            ("effects.instpol.q_file/u_file", format!("{} / {}", q_file.display(), u_file.display()))
        }
        InstPolSpec::Raytrace { file, .. } => ("effects.instpol.file", file.display().to_string()),
    };
    let coords = inst.field_coords();
    let (nx, ny) = (inst.detector.nx.max(1), inst.detector.ny.max(1));
    let axis = |n: usize| -> Vec<f64> {
        let k = n.min(257);
        (0..k).map(|i| if k == 1 { 0.0 } else { i as f64 * (n - 1) as f64 / (k - 1) as f64 }).collect()
    };
    let mut points: Vec<(f64, f64)> = Vec::new();
    for &py in &axis(ny) {
        for &px in &axis(nx) {
            points.push(coords.pixel_to_arcmin(px, py));
        }
    }
    if let InstPolSpec::Radial { centre_arcmin, .. } = spec {
        let corners = [(0.0, 0.0), ((nx - 1) as f64, 0.0), (0.0, (ny - 1) as f64), ((nx - 1) as f64, (ny - 1) as f64)];
        let r_max = corners
            .iter()
            .map(|&(px, py)| {
                let (x, y) = coords.pixel_to_arcmin(px, py);
                (x - centre_arcmin[0]).hypot(y - centre_arcmin[1])
            })
            .fold(0.0, f64::max);
        points.extend((0..=4096).map(|i| (centre_arcmin[0] + r_max * i as f64 / 4096.0, centre_arcmin[1])));
    }
    for (x, y) in points {
        let (p, _) = model.p_phi(x, y);
        if p > 1.0 {
            let (px, py) = coords.arcmin_to_pixel(x, y);
            return Err(Error::Invalid {
                path: PathBuf::from("<scene>"),
                key: key.into(),
                value,
                why: format!(
                    "the instrumental field's polarization degree is {p:.4} at ({x:.3}, {y:.3}) arcmin (detector pixel \
                     ({px:.0}, {py:.0})): a fraction above 1, more than fully polarized (coefficients are in percent)"
                ),
            });
        }
    }
    Ok(())
}

/// Sersic `b_n` (asymptotic expansion, good to < 1e-4 for n > 0.36).
fn sersic_b(n: f64) -> f64 {
    2.0 * n - 1.0 / 3.0 + 4.0 / (405.0 * n) + 46.0 / (25515.0 * n * n)
}

impl Plan {
    /// Build the plan of a validated scene.
    pub fn build(scene: &Scene) -> Result<Self, Error> {
        Self::build_with_field(scene, None)
    }

    /// Build the plan of a validated scene whose instrumental field is the model `field`
    /// (any [`FieldModel`]: a calibration's model, a fitted radial polynomial, a map, a
    /// closure), evaluated at every sky pixel's field position (arcmin from the detector
    /// centre). The scene must then not name an `[effects.instpol]` of its own. Where the model
    /// gives no finite polarization (outside a map, NaN pixels) there is none.
    /// A scene whose instrument stands at a position angle on the sky (`sky_pa_deg`) is
    /// rendered as the instrument sees it ([`Scene::seen_by_instrument`]).
    pub fn build_with_field(scene: &Scene, field: Option<Arc<dyn FieldModel>>) -> Result<Self, Error> {
        let mut plan = Self::build_seen(&scene.seen_by_instrument(), field)?;
        if let Some(pa) = scene.sky_pa_deg {
            plan.explain.insert(
                1,
                format!(
                    "instrument at position angle {pa} deg on the sky: every chi below as it sees it (chi - {pa} deg)"
                ),
            );
        }
        Ok(plan)
    }

    /// [`Plan::build_with_field`] of a scene already as the instrument sees it: the scene's
    /// optical chain ([`field::InstrumentChain`] with its plate and analyser, the effects the
    /// scene names and no others) built once, the sky and the stars as they enter it, each
    /// exposure's forward model compiled from it, and the detector's steps.
    fn build_seen(scene: &Scene, field: Option<Arc<dyn FieldModel>>) -> Result<Self, Error> {
        let inst = Instrument::load(&scene.instrument)?;
        let filter = inst.filter(&scene.filter)?.clone();
        // The beam layout of the scene's filter (its own throw, when the instrument gives one).
        let geom = BeamGeometry::new(&inst.for_filter(&scene.filter));
        let mut explain = vec![describe_setup(scene, &inst, &filter, &geom)];
        let tel = match &scene.telescope {
            Some(t) => Some(telescope_term(scene, t, &inst, &filter, &mut explain)?),
            None => None,
        };
        // Each exposure's telescope line goes here, once the chain has its matrix.
        let telescope_lines_at = explain.len();
        let sky_pixels: Vec<(u32, u32)> = geom
            .sky_pixels()
            .map(|(x, y)| {
                let (o, e) = geom.beams_of_sky(x, y).expect("sky pixel");
                (o as u32, e as u32)
            })
            .collect();

        explain.push("sky at the plate (once per scene):".into());
        let fx = &scene.effects;
        let field = resolve_field(field, fx, &inst)?;
        // Half-wave-plate causes (tilted, wedged plate): equivalent blocks at the scene's angles.
        let hwp_causes = scene.hwp_causes()?;
        let (analyser, optics) = analyser_of(scene, &inst, &filter);
        // The chain: the telescope, the field-dependent elements in the order light meets them
        // (the instrumental field, the stressed lens, the plate's causes), the plate and the
        // analyser. Every frame is rendered through it.
        let chain = field::InstrumentChain {
            telescope: tel.as_ref().map(|t| t.model),
            elements: field_elements(&field, fx, hwp_causes),
            ..Default::default()
        }
        .with_analyser(analyser);
        // Stars go frame by frame when the two beams overlap (maskless) or the frames move;
        // otherwise they are folded into the sky image once.
        // A star with circular polarization is drawn frame by frame too: the sky image holds
        // (I, Q, U) only.
        let per_frame = geom.layout != instrument::Layout::Strips
            || !scene.frame_shifts_px.is_empty()
            || scene.stars.iter().any(|s| s.v != 0.0);
        let shifts: Vec<(f64, f64)> = if scene.frame_shifts_px.is_empty() {
            vec![(0.0, 0.0); scene.hwp_angles_deg.len()]
        } else {
            scene.frame_shifts_px.iter().map(|s| (s[0], s[1])).collect()
        };
        let moving = if per_frame { stars_frame_by_frame(scene, &inst, &chain, &mut explain) } else { Vec::new() };
        let (sky, behind) = sky_at_plate(scene, &inst, &geom, &sky_pixels, &chain, per_frame, &mut explain)?;
        let sky_v = sky_v_of(scene, &inst, &geom, &sky_pixels, &sky, &chain, &mut explain)?;
        explain.extend(optics);

        // --- the chain's forward model of each exposure, compiled once ---
        let tracks = tel.as_ref().map(|t| t.tracks.clone());
        let forwards = exposures_of(scene, tracks.as_deref())
            .iter()
            .map(|e| chain.exposure_forward(e))
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| Error::Scene { path: PathBuf::from("<scene>"), message: format!("telescope: {e}") })?;
        if let Some(t) = &tel {
            let lines = t.tracks.iter().zip(&t.hour_angles).zip(&forwards).enumerate().map(|(k, ((track, (a, b)), f))| {
                let [q, u] = f.telescope_qu().unwrap_or_default();
                format!(
                    "  frame {k}: hour angle {a:.3} to {b:.3} deg, parallactic angle {:.3} to {:.3} deg: unpolarized light -> q = {q:.5}, u = {u:.5}",
                    track.start.to_degrees(),
                    track.end.to_degrees(),
                )
            });
            explain.splice(telescope_lines_at..telescope_lines_at, lines.collect::<Vec<_>>());
        }

        let (steps, flat, bitpix, det) = detector_steps(scene, &inst, &geom);
        explain.push(det);
        Ok(Self {
            scene: scene.clone(),
            inst,
            geom,
            sky_pixels,
            sky,
            behind,
            forwards,
            sky_v,
            flat,
            steps,
            cosmic: fx.cosmic_rays.clone(),
            bitpix,
            explain,
            moving,
            shifts,
            chain,
            tracks,
        })
    }

    /// The optical chain the frames are rendered through: the scene's telescope (its band
    /// model), the field-dependent elements in the order light meets them (instrumental field,
    /// stressed lens, plate defects) and the HWP zero angle. A correction holding the same
    /// chain undoes what the frames show ([`field::InstrumentChain::invert_exposures`]).
    pub fn chain(&self) -> &field::InstrumentChain {
        &self.chain
    }

    /// The exposures as the chain sees them: each frame's HWP angle as commanded (rad) and its
    /// parallactic-angle track (a fixed angle 0 without a telescope), in frame order.
    pub fn exposures(&self) -> Vec<mueller::telescope::Exposure> {
        exposures_of(&self.scene, self.tracks.as_deref())
    }

    /// The train and noise steps, one per line, for `--explain`.
    pub fn explain(&self) -> String {
        self.explain.join("\n")
    }

    /// Number of frames (HWP angles).
    pub fn n_frames(&self) -> usize {
        self.forwards.len()
    }

    /// Detector size `(nx, ny)`.
    pub fn size(&self) -> (usize, usize) {
        (self.geom.nx, self.geom.ny)
    }

    /// Render frame `k` (ADU, row-major, before the file's rounding).
    pub fn render(&self, k: usize) -> Vec<f64> {
        let (nx, ny) = (self.geom.nx, self.geom.ny);
        let mut img = vec![0.0; nx * ny];
        // Every pixel through the chain's forward model of this exposure.
        let fwd = &self.forwards[k];
        let v_at = |i: usize| match &self.sky_v {
            None => 0.0,
            Some(SkyV::Constant(v)) => *v,
            Some(SkyV::Image(w)) => w[i],
        };
        match &self.sky {
            SkyAtPlate::Constant(s) => {
                let (fo, fe) = fwd.fluxes(s, v_at(0), None);
                match self.geom.layout {
                    // Every pixel takes the o light of one sky point and the e light of another.
                    instrument::Layout::Maskless => img.fill(fo + fe),
                    // Each camera sees the whole uniform sky in its beam.
                    instrument::Layout::TwoCameras => self.fill_cameras(&mut img, fo, fe),
                    instrument::Layout::Strips => {
                        for &(o, e) in &self.sky_pixels {
                            img[o as usize] = fo;
                            img[e as usize] = fe;
                        }
                    }
                }
            }
            SkyAtPlate::Image(v) => {
                for (i, (s, &(o, e))) in v.iter().zip(&self.sky_pixels).enumerate() {
                    let (fo, fe) = fwd.fluxes(s, v_at(i), self.behind.as_ref().map(|b| &b[i]));
                    img[o as usize] = fo;
                    img[e as usize] = fe;
                }
            }
        }
        for st in &self.moving {
            self.draw_star(&mut img, st, k, fwd);
        }
        if let Some(t) = self.scene.effects.transparency_rms.filter(|&t| t > 0.0) {
            let mut rng = stream(self.scene.seed, STREAM_TRANSPARENCY, k as u64, 0);
            let n: f64 = rand_distr::StandardNormal.sample(&mut rng);
            let f = (1.0 + t * n).max(0.0);
            img.iter_mut().for_each(|v| *v *= f);
        }
        // Cosmic-ray hits of this frame, by row (drawn only when the scene has them).
        let mut hits: Vec<Vec<(usize, f64)>> = Vec::new();
        if let Some(c) = &self.cosmic {
            hits = vec![Vec::new(); ny];
            let mut rng = stream(self.scene.seed, STREAM_COSMIC, k as u64, 0);
            let n = if c.rate_per_frame > 0.0 {
                Poisson::new(c.rate_per_frame).map(|p| p.sample(&mut rng) as usize).unwrap_or(0)
            } else {
                0
            };
            let per = c.energy_e / (c.size_px * c.size_px) as f64;
            for _ in 0..n {
                let x0 = rng.random_range(0..nx);
                let y0 = rng.random_range(0..ny);
                for y in y0..(y0 + c.size_px).min(ny) {
                    for x in x0..(x0 + c.size_px).min(nx) {
                        hits[y].push((x, per));
                    }
                }
            }
        }
        let random = self.steps.iter().any(|s| s.random());
        let seed = self.scene.seed;
        img.par_chunks_mut(nx).enumerate().for_each(|(y, row)| {
            let mut rng = random.then(|| stream(seed, STREAM_PIXELS, k as u64, y as u64));
            let flat_row = self.flat.as_ref().map(|f| &f[y * nx..(y + 1) * nx]);
            for step in &self.steps {
                match *step {
                    DetStep::Flat => {
                        for (v, g) in row.iter_mut().zip(flat_row.expect("flat map")) {
                            *v *= g;
                        }
                    }
                    DetStep::Photon => {
                        let r = rng.as_mut().expect("rng");
                        for v in row.iter_mut() {
                            if *v > 0.0 {
                                *v = Poisson::new(*v).map(|p| p.sample(r)).unwrap_or(*v);
                            }
                        }
                    }
                    DetStep::Cosmic => {
                        for &(x, q) in &hits[y] {
                            row[x] += q;
                        }
                    }
                    DetStep::ReadNoise(s) => {
                        let r = rng.as_mut().expect("rng");
                        let nd = Normal::new(0.0, s).expect("read noise >= 0");
                        for v in row.iter_mut() {
                            *v += nd.sample(r);
                        }
                    }
                    DetStep::Gain(g) => {
                        for v in row.iter_mut() {
                            *v /= g;
                        }
                    }
                    DetStep::Bias(b) => {
                        for v in row.iter_mut() {
                            *v += b;
                        }
                    }
                    DetStep::Saturate(s) => {
                        for v in row.iter_mut() {
                            *v = v.min(s);
                        }
                    }
                }
            }
        });
        img
    }

    /// Add star `s` of frame `k` to `img` (e- at the plate): in each beam the light of that
    /// beam (the chain's forward model of the exposure, `fwd`), spread by the PSF about where
    /// the layout puts the beam's image of the star, on the detector pixels that beam reaches
    /// (strips: its image of the mask strips; maskless: every pixel). The PSF is normalized over
    /// its window, as for the stars of the sky image, so that the mask hides light instead of
    /// moving it.
    fn draw_star(&self, img: &mut [f64], s: &StarDraw, k: usize, fwd: &ExposureForward) {
        let (nx, ny) = (self.geom.nx, self.geom.ny);
        let (x, y) = (s.x + self.shifts[k].0, s.y + self.shifts[k].1);
        // The star's V reaches the beams through the analyser's V column (a quarter-wave
        // plate's modulation of V); a star without V adds nothing.
        let (fo, fe) = fwd.fluxes(&s.st, s.v, s.field.as_ref());
        let Some((dx, dy)) = self.geom.e_offset(x, y) else { return };
        let radius = s.psf.radius();
        for (beam, (cx, cy), flux) in [(0, (x, y), fo), (1, (x + dx, y + dy), fe)] {
            if cx + radius < 0.0 || cy + radius < 0.0 || cx - radius > nx as f64 || cy - radius > ny as f64 {
                continue;
            }
            let x0 = (cx - radius).floor().max(0.0) as usize;
            let x1 = ((cx + radius).ceil().max(0.0) as usize).min(nx - 1);
            let y0 = (cy - radius).floor().max(0.0) as usize;
            let y1 = ((cy + radius).ceil().max(0.0) as usize).min(ny - 1);
            let w = |px: usize, py: usize| s.psf.at((px as f64 - cx).powi(2) + (py as f64 - cy).powi(2));
            let norm: f64 = (y0..=y1).flat_map(|py| (x0..=x1).map(move |px| (px, py))).map(|(px, py)| w(px, py)).sum();
            if !(norm > 0.0) {
                continue;
            }
            for py in y0..=y1 {
                for px in x0..=x1 {
                    let reaches = match self.geom.kind(px, py) {
                        PixelKind::Both => true,
                        PixelKind::Ordinary(_) => beam == 0,
                        PixelKind::Extraordinary(_) => beam == 1,
                        PixelKind::Masked => false,
                    };
                    if reaches {
                        img[py * nx + px] += flux * w(px, py) / norm;
                    }
                }
            }
        }
    }

    /// A uniform sky on two cameras: `fo` on every o camera pixel, `fe` on every e camera pixel.
    fn fill_cameras(&self, img: &mut [f64], fo: f64, fe: f64) {
        let nx = self.geom.nx;
        for (p, v) in img.iter_mut().enumerate() {
            match self.geom.kind(p % nx, p / nx) {
                PixelKind::Ordinary(_) => *v = fo,
                PixelKind::Extraordinary(_) => *v = fe,
                _ => {}
            }
        }
    }

    /// The header keywords of frame `k`.
    fn keys(&self, k: usize) -> Vec<(String, KeyValue, String)> {
        let mut tel_keys = Vec::new();
        if let (Some(t), Some(it)) = (&self.tracks, &self.inst.telescope) {
            let sense = it.parang_sense as f64;
            let tr = t[k];
            // Header angles in (-180, 180] as a telescope writes them, in the header's sense.
            let deg = |a: f64| 2.0 * mueller::wrap_half_pi(0.5 * a).to_degrees();
            for (key, v, what) in [
                (&it.parang_start_keyword, sense * deg(tr.start), "parallactic angle at start [deg]"),
                (&it.parang_end_keyword, sense * deg(tr.end), "parallactic angle at end [deg]"),
                (&it.rotator_keyword, it.rotator_sense as f64 * deg(tr.rotator), "rotator angle [deg]"),
            ] {
                tel_keys.push((key.clone(), KeyValue::F64(v), what.to_string()));
            }
        }
        let mut keys =
            self.header_keys("instpol simulation", Some(self.scene.hwp_angles_deg[k]), self.scene.exposure_s);
        keys.extend(tel_keys);
        keys.extend(self.rotation_keys(k));
        keys.extend(self.sky_angle_keys());
        if let Some(m) = self.frame_start_mjd(k) {
            keys.push(("MJD-OBS".into(), KeyValue::F64(m), "start of the exposure [MJD]".into()));
        }
        // An instrument whose headers carry no HWP angle gets none (as its real frames).
        keys.retain(|(k, _, _)| !k.is_empty());
        self.with_scene_keywords(keys)
    }

    /// `keys` with the scene's own keywords ([`crate::scene::Output::keywords`]) in place of
    /// any of the same name.
    fn with_scene_keywords(&self, mut keys: Vec<(String, KeyValue, String)>) -> Vec<(String, KeyValue, String)> {
        let extra = &self.scene.output.keywords;
        if extra.is_empty() {
            return keys;
        }
        let norm = |k: &str| k.trim().trim_start_matches("HIERARCH ").to_ascii_uppercase();
        let names: Vec<String> = extra.keys().map(|k| norm(k)).collect();
        keys.retain(|(k, _, _)| !names.contains(&norm(k)));
        for (k, v) in extra {
            keys.push((
                k.clone(),
                match v {
                    crate::scene::Keyword::Number(x) => KeyValue::F64(*x),
                    crate::scene::Keyword::Text(t) => KeyValue::Str(t.clone()),
                },
                String::new(),
            ));
        }
        keys
    }

    /// The keywords every simulated file carries: instrument, `object`, the HWP angle (when
    /// given), filter (its first alias, as the instrument's headers name it), exposure time and
    /// the simulation's seed.
    fn header_keys(&self, object: &str, hwp_deg: Option<f64>, exptime_s: f64) -> Vec<(String, KeyValue, String)> {
        let pol = &self.inst.polarimetry;
        let filt = self.inst.filter(&self.scene.filter).map(|f| f.aliases.first().cloned().unwrap_or(f.name.clone()));
        let mut keys = vec![
            ("INSTRUME".into(), KeyValue::Str(self.inst.name.clone()), String::new()),
            ("OBJECT".into(), KeyValue::Str(object.into()), String::new()),
        ];
        if let Some(h) = hwp_deg {
            keys.push((pol.hwp_angle_keyword.clone(), KeyValue::F64(h), "HWP angle [deg]".into()));
        }
        keys.extend([
            (pol.filter_keyword.clone(), KeyValue::Str(filt.unwrap_or(self.scene.filter.clone())), String::new()),
            (pol.exptime_keyword.clone(), KeyValue::F64(exptime_s), "exposure time [s]".into()),
            ("SIMSEED".into(), KeyValue::I64(self.scene.seed as i64), "instpol simulation seed".into()),
        ]);
        keys
    }

    /// The keywords of frame `k`'s plate range for an instrument whose plate turns
    /// (`[polarimetry.rotation]`): begin and end angles, or the rotor position. A fixed plate in
    /// the scene writes a range of zero width (begin = end).
    fn rotation_keys(&self, k: usize) -> Vec<(String, KeyValue, String)> {
        let Some(r) = &self.inst.polarimetry.rotation else { return vec![] };
        let a = self.scene.hwp_angles_deg[k];
        let d = self.scene.hwp_motion.as_ref().map_or(0.0, |m| m.sweep_deg);
        if r.by_position() {
            // Checked when the scene was loaded (Scene::checked).
            let pos = crate::scene::rotor_position(r, a, d).unwrap_or(r.first_position);
            return vec![(r.position_keyword.clone(), KeyValue::I64(pos), "rotor position".into())];
        }
        vec![
            (r.begin_keyword.clone(), KeyValue::F64(a - 0.5 * d), "plate angle at the start [deg]".into()),
            (r.end_keyword.clone(), KeyValue::F64(a + 0.5 * d), "plate angle at the end [deg]".into()),
        ]
    }

    /// The keyword of the instrument's position angle on the sky (`[polarimetry.sky_angle]`),
    /// when the scene gives the angle (`sky_pa_deg`): the header's value, the sense and offset
    /// undone. An instrument that reads the angle from a WCS gets none: the simulator writes no
    /// celestial WCS (a scene gives one through `[output] keywords`).
    fn sky_angle_keys(&self) -> Vec<(String, KeyValue, String)> {
        match (&self.inst.polarimetry.sky_angle, self.scene.sky_pa_deg) {
            (Some(a), Some(pa)) if !a.from_wcs => {
                let what = "instrument position angle on the sky [deg]".to_string();
                vec![(a.keyword.clone(), KeyValue::F64(a.header_value_deg(pa)), what)]
            }
            _ => vec![],
        }
    }

    /// File name of frame `k` (for a chip instrument, [`Plan::frame_files`]).
    pub fn frame_name(&self, k: usize) -> String {
        format!("{}.fits", self.frame_stem(k))
    }

    /// Frame `k`'s file name without `.fits` (a chip instrument's chip files add `_<chip>`).
    fn frame_stem(&self, k: usize) -> String {
        match &self.scene.output.archive {
            Some(_) => {
                let ms = self.frame_start_mjd(k).map_or(0, |m| ((m - 40_587.0) * 86_400_000.0).round() as i64);
                let iso = skyfield::provenance::iso_utc(ms.div_euclid(1000));
                format!("{}.{iso}.{:03}", self.inst.name, ms.rem_euclid(1000))
            }
            None => format!("{}_{:02}_hwp{:05.1}", self.scene.output.prefix, k, self.scene.hwp_angles_deg[k]),
        }
    }

    /// Frame `k`'s start (MJD) when the scene writes archive-like files.
    fn frame_start_mjd(&self, k: usize) -> Option<f64> {
        self.scene.output.archive.as_ref().map(|a| a.start_mjd + k as f64 * a.cadence_s / 86_400.0)
    }

    /// True when frames are written as raw chip files (the instrument's `[format]` has chips).
    pub fn writes_chips(&self) -> bool {
        !self.inst.format.chips.is_empty()
    }

    /// The files of frame `k` (relative to the output folder): one, or one per chip named as
    /// `sim::raw` names them (`STEM_<chip>.fits`).
    pub fn frame_files(&self, k: usize) -> Vec<String> {
        self.chip_names(&self.frame_stem(k))
    }

    fn chip_names(&self, stem: &str) -> Vec<String> {
        if !self.writes_chips() {
            return vec![format!("{stem}.fits")];
        }
        self.inst.format.chips.iter().map(|c| format!("{stem}_{}.fits", c.name)).collect()
    }

    /// Number of bias frames written: a chip instrument with a chip whose bias level no
    /// overscan removes (subtraction off, or no pre/overscan region) cannot be reduced without
    /// a master bias, so its simulation writes the frames to make one; none otherwise, and none
    /// for frames the instrument declares bias corrected already (`[format] already_corrected`).
    pub fn n_bias_frames(&self) -> usize {
        let needs = self.writes_chips()
            && !self.inst.format.already(instrument::Correction::Bias)
            && self.inst.format.chips.iter().any(|c| {
                !c.subtract_overscan
                    || (c.prescan_x.is_none()
                        && c.overscan_x.is_none()
                        && c.prescan_y.is_none()
                        && c.overscan_y.is_none())
            });
        if needs {
            self.scene.output.bias_frames.unwrap_or(crate::scene::DEFAULT_BIAS_FRAMES)
        } else {
            0
        }
    }

    /// The chip files of bias frame `i` (relative to the output folder, in `bias/`).
    pub fn bias_files(&self, i: usize) -> Vec<String> {
        self.chip_names(&format!("bias/{}", self.bias_stem(i)))
    }

    fn bias_stem(&self, i: usize) -> String {
        format!("{}_bias_{:02}", self.scene.output.prefix, i)
    }

    /// About how many bytes the frames [`Plan::write`] writes take: every frame and bias frame
    /// at the detector's size and the output's BITPIX (raw chip files add their scan regions
    /// and headers, a few per cent).
    pub fn output_bytes(&self) -> u64 {
        let per_value = match self.bitpix {
            Bitpix::U16 => 2,
            Bitpix::F32 => 4,
            Bitpix::F64 => 8,
        };
        let frames = (self.n_frames() + self.n_bias_frames()) as u64;
        frames.saturating_mul(self.geom.nx as u64 * self.geom.ny as u64).saturating_mul(per_value)
    }

    /// Refuse a simulation whose frames would take more than [`MAX_OUTPUT_BYTES`] unless
    /// `force`: a scene of thousands of HWP angles on a full-size detector fills a disk, one
    /// frame at a time, with no end in sight. `path`: the scene, for the message.
    pub fn check_output_size(&self, path: &Path, force: bool) -> Result<(), Error> {
        let bytes = self.output_bytes();
        if bytes > MAX_OUTPUT_BYTES && !force {
            return Err(Error::Scene {
                path: path.into(),
                message: format!(
                    "{} frames of {} x {} px would write about {:.1} GB (limit {} GB without --force): fewer hwp_angles_deg, a smaller detector or BITPIX, or --force to write them",
                    self.n_frames() + self.n_bias_frames(),
                    self.geom.nx,
                    self.geom.ny,
                    bytes as f64 / 1e9,
                    MAX_OUTPUT_BYTES / 1_000_000_000
                ),
            });
        }
        Ok(())
    }

    /// Every file [`Plan::write`] writes (relative to the output folder), `truth.json` last.
    pub fn output_files(&self) -> Vec<String> {
        (0..self.n_frames())
            .flat_map(|k| self.frame_files(k))
            .chain((0..self.n_bias_frames()).flat_map(|i| self.bias_files(i)))
            .chain(["truth.json".to_string()])
            .collect()
    }

    /// Each chip's read-out in the raw files: the scene's (or format's) bias level, the gain
    /// and read noise the frames were rendered with, the scene's keyword-declared scan sizes.
    fn readouts(&self) -> Vec<crate::raw::RawChip> {
        let out = &self.scene.output;
        // Frames the instrument declares bias corrected already (an archive's level-1 frames)
        // carry no bias level unless the scene gives one.
        let default_bias = if self.inst.format.already(instrument::Correction::Bias) {
            0.0
        } else {
            crate::scene::DEFAULT_RAW_BIAS_ADU
        };
        let bias = out.raw_bias_adu.or(self.inst.format.raw_bias_adu).unwrap_or(default_bias);
        let gain = self.steps.iter().find_map(|s| if let DetStep::Gain(g) = s { Some(*g) } else { None });
        let rn = self.steps.iter().find_map(|s| if let DetStep::ReadNoise(r) = s { Some(*r) } else { None });
        let rc = crate::raw::RawChip {
            bias_adu: bias,
            gain_e_per_adu: gain.unwrap_or(self.inst.detector.gain_e_per_adu),
            read_noise_e: rn.unwrap_or(0.0),
            scan: out.raw_scan_px.unwrap_or(crate::scene::DEFAULT_RAW_SCAN_PX),
        };
        // A chip whose gain the instrument file gives as a number reads out with it (two
        // cameras of different gains); a gain from a keyword is the scene's, written there.
        self.inst
            .format
            .chips
            .iter()
            .map(|c| match c.gain_e_per_adu {
                Some(instrument::NumberOrKeyword::Number(g)) => crate::raw::RawChip { gain_e_per_adu: g, ..rc },
                _ => rc,
            })
            .collect()
    }

    /// Write frame `k` (or, `bias`, bias frame `k`) as raw chip files: the rendered ADU (a
    /// bias frame: none) placed in each chip on its bias level, pre/overscan regions of bias
    /// and read noise (a bias frame: read noise everywhere).
    fn write_chips(&self, out: &Path, k: usize, bias: bool, img: &[f64]) -> Result<Vec<PathBuf>, Error> {
        let chips = self.readouts();
        let readout = crate::raw::Readout {
            chips: &chips,
            exposure_no: if bias {
                1001 + k as i64
            } else {
                self.scene.output.first_exposure_no.unwrap_or(1) + k as i64
            },
            binning: None,
            bitpix: self.bitpix,
        };
        // A bias frame: no HWP angle, no exposure time.
        let keys = if bias { self.header_keys("BIAS", None, 0.0) } else { self.keys(k) };
        let mut rng = stream(self.scene.seed, STREAM_READOUT, k as u64, bias as u64);
        let (dir, stem) =
            if bias { (out.join("bias"), self.bias_stem(k)) } else { (out.to_path_buf(), self.frame_stem(k)) };
        crate::raw::write_chip_files(&self.inst, &readout, &keys, bias, &mut rng, &dir, &stem, &mut |_, p, _| {
            // The rendered frame carries its own read noise and photon noise.
            if bias {
                0.0
            } else {
                img[p]
            }
        })
    }
}

/// The telescope of a scene: the mirror of `mueller::telescope::BandModel` at the filter's
/// effective wavelength and each exposure's parallactic-angle track from its hour angles
/// (`mueller::telescope::exposure_track`). The chain averages the matrix over each track and
/// divides it by its `M_00`, so that fluxes stay those of the scene
/// (`field::chain::telescope_matrix`).
fn telescope_term(
    scene: &Scene,
    t: &crate::scene::TelescopeSpec,
    inst: &Instrument,
    filter: &instrument::Filter,
    explain: &mut Vec<String>,
) -> Result<TelescopeTerm, Error> {
    use mueller::mirror::MetalTable;
    use mueller::telescope::{exposure_track, BandModel};
    let bad = |m: String| Error::Scene { path: PathBuf::from("<scene>"), message: format!("telescope: {m}") };
    let table = match MetalTable::builtin(&t.metal) {
        Ok(t) => t,
        Err(_) => MetalTable::read(Path::new(&t.metal)).map_err(|e| bad(format!("metal {}: {e}", t.metal)))?,
    };
    let w = filter.lambda_eff_nm / 1000.0;
    let index = table.index(w).map_err(|e| bad(format!("metal {} at {w} micron: {e}", t.metal)))?;
    let model = BandModel {
        wavelength_um: w,
        index,
        factor: t.factor,
        thickness_nm: t.overlayer_thickness_nm,
        offset: t.offset_deg.to_radians(),
        q0: 0.0,
        u0: 0.0,
    };
    let lat = scene.site_latitude_deg(inst).ok_or_else(|| bad("no site latitude".into()))?.to_radians();
    let dec = t.dec_deg.to_radians();
    let (mut hour_angles, mut tracks) = (Vec::new(), Vec::new());
    explain.push(format!(
        "telescope: M3 of {} (n, k x {}, alumina {} nm) at 45 deg, offset {} deg, rotator {} deg, dec {} deg, latitude {:.3} deg; per exposure the matrix averaged over its parallactic-angle track:",
        t.metal, t.factor, t.overlayer_thickness_nm, t.offset_deg, t.rotator_deg, t.dec_deg, lat.to_degrees()
    ));
    for k in 0..scene.hwp_angles_deg.len() {
        let (a, b) = t.hour_angles(k, scene.exposure_s);
        tracks.push(exposure_track(lat, dec, a.to_radians(), b.to_radians()).with_rotator(t.rotator_deg.to_radians()));
        hour_angles.push((a, b));
    }
    Ok(TelescopeTerm { model, tracks, hour_angles })
}

fn describe_star(s: &Star) -> String {
    let unit = if s.coords == Coords::Pixel { "px" } else { "arcmin" };
    let v = if s.v != 0.0 { format!(", V/I = {}", s.v) } else { String::new() };
    format!(
        "at ({}, {}) {unit}, {} e-, p = {}, chi = {} deg{v}, {:?} PSF FWHM {}\"",
        s.x, s.y, s.flux_e, s.p, s.chi_deg, s.psf, s.fwhm_arcsec
    )
}

fn describe_instpol(s: &InstPolSpec) -> String {
    match s {
        InstPolSpec::Radial { coeffs_percent, centre_arcmin, phi_offset_deg } => format!(
            "radial polynomial p(r) = sum c_k r^k, c = {coeffs_percent:?} %, centre {centre_arcmin:?} arcmin, phi = polar angle + {phi_offset_deg} deg"
        ),
        InstPolSpec::Map { q_file, u_file, bin_px } => {
            format!("Q/U maps {} and {}, {bin_px} px per map pixel", q_file.display(), u_file.display())
        }
        InstPolSpec::Raytrace { file, centre_arcmin } => {
            format!("ray-trace profile {} (radial pattern), centre {centre_arcmin:?} arcmin", file.display())
        }
    }
}

fn source_pixel(inst: &Instrument, x: f64, y: f64, c: Coords) -> (f64, f64) {
    match c {
        Coords::Pixel => (x, y),
        Coords::Arcmin => inst.arcmin_to_pixel(x, y),
    }
}

/// Add a star's Stokes vector, spread by its PSF (sampled at pixel centres, normalized to the
/// flux over the rendered window), to the sky image.
fn add_star(img: &mut [Iqu], ordinal: &[u32], inst: &Instrument, s: &Star) {
    let (nx, ny) = (inst.detector.nx, inst.detector.ny);
    let (xc, yc) = source_pixel(inst, s.x, s.y, s.coords);
    let fwhm = s.fwhm_arcsec / inst.detector.pixel_scale_arcsec;
    let (profile, radius): (Box<dyn Fn(f64) -> f64>, f64) = match s.psf {
        Psf::Gaussian => {
            let sig = fwhm / (8.0 * 2f64.ln()).sqrt();
            (Box::new(move |r2: f64| (-0.5 * r2 / (sig * sig)).exp()), 8.0 * sig)
        }
        Psf::Moffat => {
            let b = s.moffat_beta;
            let alpha = fwhm / (2.0 * (2f64.powf(1.0 / b) - 1.0).sqrt());
            // Radius where the profile has fallen to 1e-6 of its peak, at most 300 px.
            let r = alpha * (1e-6f64.powf(-1.0 / b) - 1.0).sqrt();
            (Box::new(move |r2: f64| (1.0 + r2 / (alpha * alpha)).powf(-b)), r.min(300.0))
        }
    };
    let x0 = (xc - radius).floor().max(0.0) as usize;
    let x1 = ((xc + radius).ceil() as usize).min(nx.saturating_sub(1));
    let y0 = (yc - radius).floor().max(0.0) as usize;
    let y1 = ((yc + radius).ceil() as usize).min(ny.saturating_sub(1));
    if xc + radius < 0.0 || yc + radius < 0.0 || x0 > x1 || y0 > y1 {
        return;
    }
    // Normalize over the whole window (masked pixels included: the mask hides that light).
    let mut norm = 0.0;
    for y in y0..=y1 {
        for x in x0..=x1 {
            let r2 = (x as f64 - xc).powi(2) + (y as f64 - yc).powi(2);
            norm += profile(r2);
        }
    }
    if norm <= 0.0 {
        return;
    }
    let st = mueller::stokes_p_chi(s.flux_e / norm, s.p, s.chi_deg.to_radians());
    for y in y0..=y1 {
        for x in x0..=x1 {
            let k = ordinal[y * nx + x];
            if k == u32::MAX {
                continue;
            }
            let w = profile((x as f64 - xc).powi(2) + (y as f64 - yc).powi(2));
            let t = &mut img[k as usize];
            t[0] += w * st[0];
            t[1] += w * st[1];
            t[2] += w * st[2];
        }
    }
}

fn add_extended(img: &mut [Iqu], sky_pixels: &[(u32, u32)], inst: &Instrument, e: &Extended) -> Result<(), Error> {
    let nx = inst.detector.nx;
    let (q, u) = (e.p * (2.0 * e.chi_deg.to_radians()).cos(), e.p * (2.0 * e.chi_deg.to_radians()).sin());
    match e.profile {
        Profile::Image => {
            let path = e.image.as_ref().expect("validated");
            let (v, ix, iy) = read_map(path)?;
            if (ix, iy) != (inst.detector.nx, inst.detector.ny) {
                return Err(file_err(
                    path,
                    format!("image is {ix} x {iy}, the detector is {} x {}", nx, inst.detector.ny),
                ));
            }
            for (t, &(o, _)) in img.iter_mut().zip(sky_pixels) {
                let i = v[o as usize];
                if i.is_finite() && i > 0.0 {
                    t[0] += i;
                    t[1] += i * q;
                    t[2] += i * u;
                }
            }
        }
        Profile::Sersic | Profile::Exponential => {
            let n = if e.profile == Profile::Exponential { 1.0 } else { e.sersic_n };
            let b = sersic_b(n);
            let (xc, yc) = source_pixel(inst, e.x, e.y, e.coords);
            let re = e.r_e_arcsec / inst.detector.pixel_scale_arcsec;
            let (sp, cp) = e.pa_deg.to_radians().sin_cos();
            img.par_iter_mut().zip(sky_pixels.par_iter()).for_each(|(t, &(o, _))| {
                let (x, y) = ((o as usize % nx) as f64 - xc, (o as usize / nx) as f64 - yc);
                let (a, bb) = (x * cp + y * sp, -x * sp + y * cp);
                let r = a.hypot(bb / e.axis_ratio);
                let i = e.i_e * (-b * ((r / re).powf(1.0 / n) - 1.0)).exp();
                t[0] += i;
                t[1] += i * q;
                t[2] += i * u;
            });
        }
    }
    Ok(())
}

/// The flat-field error gains: 1 on masked pixels; on o (e) pixels `1 + rms n + A L(x, y)`
/// with `n` standard normal and `L` a smooth unit-amplitude pattern, different for the two
/// beams: `L_o = sin(2 pi x/nx + 0.3) cos(2 pi y/ny)`, `L_e = cos(2 pi x/nx - 0.7) sin(2 pi
/// y/ny + 0.4)`.
fn flat_map(geom: &BeamGeometry, f: &crate::scene::FlatSpec, seed: u64) -> Vec<f64> {
    let (nx, ny) = (geom.nx, geom.ny);
    let mut out = vec![1.0; nx * ny];
    out.par_chunks_mut(nx).enumerate().for_each(|(y, row)| {
        let mut rng = stream(seed, STREAM_FLAT, 0, y as u64);
        let yy = 2.0 * PI * y as f64 / ny as f64;
        for (x, g) in row.iter_mut().enumerate() {
            let xx = 2.0 * PI * x as f64 / nx as f64;
            let n: f64 = rand_distr::StandardNormal.sample(&mut rng);
            *g = match geom.kind(x, y) {
                PixelKind::Ordinary(_) | PixelKind::Both => {
                    1.0 + f.pixel_rms_o * n + f.large_scale_o * (xx + 0.3).sin() * yy.cos()
                }
                PixelKind::Extraordinary(_) => {
                    1.0 + f.pixel_rms_e * n + f.large_scale_e * (xx - 0.7).cos() * (yy + 0.4).sin()
                }
                PixelKind::Masked => 1.0,
            };
        }
    });
    out
}

/// The truth file: every input of the scene, resolved.
#[derive(serde::Serialize)]
struct Truth<'a> {
    format: &'static str,
    scene: &'a Scene,
    instrument: &'a Instrument,
    frames: Vec<TruthFrame>,
    /// Bias frames' chip files (chip instruments that need a master bias).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    bias_frames: Vec<String>,
    explain: &'a [String],
    /// Sky normalized Stokes parameters (fractions) as given.
    sky_q: Option<f64>,
    sky_u: Option<f64>,
}

#[derive(serde::Serialize)]
struct TruthFrame {
    /// The frame's file (a chip instrument's: its first chip file).
    file: String,
    /// A chip instrument's files of this frame, in chip order.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    chip_files: Vec<String>,
    hwp_deg: f64,
    /// The exposure's parallactic-angle track (deg, the convention of `mueller::mirror`),
    /// with a telescope.
    #[serde(skip_serializing_if = "Option::is_none")]
    parallactic_start_deg: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    parallactic_end_deg: Option<f64>,
    /// The `(q, u)` the telescope gives an unpolarized source over this exposure.
    #[serde(skip_serializing_if = "Option::is_none")]
    telescope_qu: Option<[f64; 2]>,
}

/// Simulate a scene into `out` (created if needed): one FITS file per HWP angle and
/// `truth.json`. Frames are rendered and written in parallel; `on_frame` ticks once per file.
pub fn simulate(scene: &Scene, out: &Path, on_frame: &(dyn Fn() + Sync)) -> Result<Simulated, Error> {
    let plan = Plan::build(scene)?;
    plan.write(out, on_frame)
}

/// [`simulate`] with the instrumental field given as a model value instead of the scene's
/// `[effects.instpol]` (see [`Plan::build_with_field`]).
pub fn simulate_with_field(
    scene: &Scene,
    field: Arc<dyn FieldModel>,
    out: &Path,
    on_frame: &(dyn Fn() + Sync),
) -> Result<Simulated, Error> {
    Plan::build_with_field(scene, Some(field))?.write(out, on_frame)
}

impl Plan {
    /// Render and write every frame and the truth file into `out`.
    pub fn write(&self, out: &Path, on_frame: &(dyn Fn() + Sync)) -> Result<Simulated, Error> {
        std::fs::create_dir_all(out).map_err(|e| file_err(out, format!("cannot create output folder: {e}")))?;
        let (nx, ny) = self.size();
        let files: Vec<Vec<PathBuf>> = (0..self.n_frames())
            .into_par_iter()
            .map(|k| {
                let img = self.render(k);
                let written = if self.writes_chips() {
                    self.write_chips(out, k, false, &img)?
                } else {
                    let path = out.join(self.frame_name(k));
                    write_frame(&path, nx, ny, &img, self.bitpix, &self.keys(k))?;
                    vec![path]
                };
                on_frame();
                Ok(written)
            })
            .collect::<Result<_, Error>>()?;
        let nb = self.n_bias_frames();
        if nb > 0 {
            let d = out.join("bias");
            std::fs::create_dir_all(&d).map_err(|e| file_err(&d, format!("cannot create output folder: {e}")))?;
        }
        let bias: Vec<PathBuf> = (0..nb)
            .into_par_iter()
            .map(|i| self.write_chips(out, i, true, &[]))
            .collect::<Result<Vec<_>, Error>>()?
            .into_iter()
            .flatten()
            .collect();
        let rel = |p: &PathBuf| p.strip_prefix(out).unwrap_or(p).to_string_lossy().into_owned();
        // The truth on the sky, as the scene gave it (the plan holds it as the instrument saw it).
        let on_sky = self.scene.on_sky();
        let (sky_q, sky_u) = match &on_sky.sky {
            Some(s) => {
                (Some(s.p * (2.0 * s.chi_deg.to_radians()).cos()), Some(s.p * (2.0 * s.chi_deg.to_radians()).sin()))
            }
            None => (None, None),
        };
        let truth = Truth {
            format: "instpol-sim-truth-1",
            scene: &on_sky,
            instrument: &self.inst,
            frames: files
                .iter()
                .zip(&self.scene.hwp_angles_deg)
                .enumerate()
                .map(|(k, (p, &a))| TruthFrame {
                    file: rel(&p[0]),
                    chip_files: if self.writes_chips() { p.iter().map(rel).collect() } else { vec![] },
                    hwp_deg: a,
                    parallactic_start_deg: self.tracks.as_ref().map(|t| t[k].start.to_degrees()),
                    parallactic_end_deg: self.tracks.as_ref().map(|t| t[k].end.to_degrees()),
                    telescope_qu: self.forwards[k].telescope_qu(),
                })
                .collect(),
            bias_frames: bias.iter().map(rel).collect(),
            explain: &self.explain,
            sky_q,
            sky_u,
        };
        let tpath = out.join("truth.json");
        let text = serde_json::to_string_pretty(&truth).map_err(|e| file_err(&tpath, e))?;
        let mut tmp = skyfield::fits::temp_beside(&tpath, ".json").map_err(|e| file_err(&tpath, e))?;
        std::io::Write::write_all(&mut tmp, text.as_bytes()).map_err(|e| file_err(&tpath, e))?;
        // Through the durable writer, as every output: fsynced before its rename, so a full
        // disk is reported here rather than lost.
        skyfield::durable::finish(tmp.into_temp_path(), &tpath).map_err(|e| file_err(&tpath, e))?;
        Ok(Simulated { frames: files.into_iter().flatten().collect(), truth: tpath, bias })
    }
}

/// The field-dependent elements of a scene in the order light meets them: the instrumental
/// field, the constant response, the stressed lens (first of all when the scene puts it
/// before the field, `before_instpol`), the plate's causes (the telescope acts
/// before all of them, per exposure).
fn field_elements(
    field: &Option<(Arc<dyn FieldModel>, String)>,
    fx: &crate::scene::Effects,
    hwp_causes: Option<crate::hwp_causes::HwpCauses>,
) -> field::FieldChain {
    let mut chain = field::FieldChain::new();
    let lens = fx.stressed_lens.as_ref().map(|sl| (sl, format!("stressed lens (mueller::linear block): {sl:?}")));
    if let Some((sl, what)) = lens.as_ref().filter(|(sl, _)| sl.before_instpol) {
        chain = chain.then(Arc::new(sl.element()), what.clone());
    }
    if let Some((f, what)) = &field {
        chain =
            chain.then(f.clone(), format!("instrumental field Element::PartialPolarizer{{p(x,y), phi(x,y)}}: {what}"));
    }
    if let Some(r) = &fx.constant_response {
        chain = chain.then(Arc::new(*r), format!("constant response from standards: {}", r.describe()));
    }
    if let Some((sl, what)) = lens.filter(|(sl, _)| !sl.before_instpol) {
        chain = chain.then(Arc::new(sl.element()), what);
    }
    if let Some(hc) = hwp_causes {
        let what = format!("half-wave-plate causes (equivalent block): {}", hc.describe());
        chain = chain.then(hc.into_element(), what);
    }
    chain
}

/// The first line of a scene's `--explain`: the instrument, its beam layout, the filter and
/// the plate's angles.
fn describe_setup(scene: &Scene, inst: &Instrument, filter: &instrument::Filter, geom: &BeamGeometry) -> String {
    let layout = match geom.layout {
        instrument::Layout::Strips => format!("{} strips, throw {} px", geom.strips.len(), inst.throw_px_exact()),
        instrument::Layout::Maskless => format!("maskless, o/e offset {:?} px", geom.oe_offset.unwrap_or_default()),
        instrument::Layout::TwoCameras => {
            let c = geom.cameras.as_ref();
            format!(
                "two cameras, e camera turned {:?}, transform {:?}",
                c.map(|c| c.e_orientation),
                c.and_then(|c| c.transform)
            )
        }
    };
    format!(
        "instrument {} ({} x {} px, {layout}), filter {}, {} HWP angles {:?} deg",
        inst.name,
        geom.nx,
        geom.ny,
        filter.name,
        scene.hwp_angles_deg.len(),
        scene.hwp_angles_deg
    )
}

/// The instrumental field of a scene with the line that says what it is: the model given
/// (`field`) or the scene's `[effects.instpol]` (one of them, not both), checked physical.
fn resolve_field(
    field: Option<Arc<dyn FieldModel>>,
    fx: &crate::scene::Effects,
    inst: &Instrument,
) -> Result<Option<(Arc<dyn FieldModel>, String)>, Error> {
    Ok(match (field, &fx.instpol) {
        (Some(_), Some(_)) => {
            return Err(Error::Scene {
                path: PathBuf::from("<scene>"),
                message: "the scene names [effects.instpol] and a field model was given too: give one".into(),
            })
        }
        (Some(m), None) => {
            let d = m.describe();
            Some((m, d))
        }
        (None, Some(spec)) => {
            let model = load_field(spec, inst)?;
            check_field_physical(spec, model.as_ref(), inst)?;
            Some((model, describe_instpol(spec)))
        }
        (None, None) => None,
    })
}

/// The exposures as the chain sees them: each frame's HWP angle as commanded (rad) and its
/// parallactic-angle track (`tracks`, a telescope's; a fixed angle 0 without one).
fn exposures_of(scene: &Scene, tracks: Option<&[mueller::telescope::Track]>) -> Vec<mueller::telescope::Exposure> {
    scene
        .hwp_angles_deg
        .iter()
        .enumerate()
        .map(|(k, a)| mueller::telescope::Exposure {
            hwp: a.to_radians(),
            track: tracks.map_or(mueller::telescope::Track::at(0.0), |t| t[k]),
        })
        .collect()
}

/// The stars drawn frame by frame, each as it enters the exposures' part of the chain
/// ([`field::InstrumentChain::before_exposures`]; behind a telescope the field's elements at
/// the star kept as one block).
fn stars_frame_by_frame(
    scene: &Scene,
    inst: &Instrument,
    chain: &field::InstrumentChain,
    explain: &mut Vec<String>,
) -> Vec<StarDraw> {
    let mut moving = Vec::new();
    for st in &scene.stars {
        explain.push(format!("  + star {} (drawn frame by frame in both beams)", describe_star(st)));
        let (x, y) = source_pixel(inst, st.x, st.y, st.coords);
        let v = mueller::stokes_p_chi(st.flux_e, st.p, st.chi_deg.to_radians());
        let (xa, ya) = inst.pixel_to_arcmin(x, y);
        // (I, Q, U, V): a star's V goes through the field's elements' Mueller matrices (a
        // telescope is refused with V by the scene's checks).
        let s = chain.before_exposures(xa, ya, Stokes::new(v[0], v[1], v[2], st.flux_e * st.v));
        let field = chain.elements_per_exposure().then(|| chain.field_block_at(xa, ya));
        moving.push(StarDraw { x, y, st: [s[0], s[1], s[2]], psf: PsfShape::of(st, inst), v: s[3], field });
    }
    if !scene.frame_shifts_px.is_empty() {
        explain.push(format!("  frames moved by {:?} px", scene.frame_shifts_px));
    }
    moving
}

/// The sky as it enters the exposures' part of the chain: one vector for a uniform sky with
/// no field-dependent effect, else an image (gradient, stars folded in, extended sources)
/// with the field's elements applied once per pixel, or, behind a telescope, kept per pixel
/// (the second value).
#[allow(clippy::too_many_arguments)]
fn sky_at_plate(
    scene: &Scene,
    inst: &Instrument,
    geom: &BeamGeometry,
    sky_pixels: &[(u32, u32)],
    chain: &field::InstrumentChain,
    per_frame: bool,
    explain: &mut Vec<String>,
) -> Result<(SkyAtPlate, Option<Vec<FieldBlock>>), Error> {
    let base = scene.sky.as_ref().map(|s| {
        let st = mueller::stokes_p_chi(s.brightness_e, s.p, s.chi_deg.to_radians());
        [st[0], st[1], st[2]]
    });
    let elements = !chain.elements.is_empty() && geom.layout == instrument::Layout::Strips;
    let needs_image = scene.sky.as_ref().is_some_and(|s| s.gradient_e_per_arcmin.is_some())
        || (!scene.stars.is_empty() && !per_frame)
        || !scene.extended.is_empty()
        || elements;
    if !needs_image {
        match &scene.sky {
            Some(s) => explain.push(format!(
                "  uniform sky I = {} e-/px, p = {} ({:.3}%), chi = {} deg: one Stokes vector, nothing per pixel",
                s.brightness_e,
                s.p,
                100.0 * s.p,
                s.chi_deg
            )),
            None => explain.push("  empty sky: no light".into()),
        }
        return Ok((SkyAtPlate::Constant(base.unwrap_or([0.0; 3])), None));
    }
    let mut img = sky_image(scene, inst, geom, sky_pixels, base, per_frame, explain)?;
    let mut behind = None;
    if elements {
        let coords = inst.field_coords();
        let arcmin = |o: u32| coords.pixel_to_arcmin((o as usize % geom.nx) as f64, (o as usize / geom.nx) as f64);
        for what in chain.elements.describe() {
            explain.push(format!("  x {what}, per pixel"));
        }
        if chain.elements_per_exposure() {
            // After the telescope, which changes frame by frame: the elements kept per pixel.
            explain.push("    (kept per pixel as one block: it acts after each frame's telescope matrix)".into());
            behind = Some(
                sky_pixels
                    .par_iter()
                    .map(|&(o, _)| {
                        let (xa, ya) = arcmin(o);
                        chain.field_block_at(xa, ya)
                    })
                    .collect(),
            );
        } else {
            img.par_iter_mut().zip(sky_pixels.par_iter()).for_each(|(s, &(o, _))| {
                let (xa, ya) = arcmin(o);
                let t = chain.before_exposures(xa, ya, Stokes::new(s[0], s[1], s[2], 0.0));
                *s = [t[0], t[1], t[2]];
            });
        }
    }
    Ok((SkyAtPlate::Image(img), behind))
}

/// The sky image before the chain: the sky (with its gradient), the stars folded in (when
/// not drawn frame by frame) and the extended sources, one `(I, Q, U)` per sky pixel.
#[allow(clippy::too_many_arguments)]
fn sky_image(
    scene: &Scene,
    inst: &Instrument,
    geom: &BeamGeometry,
    sky_pixels: &[(u32, u32)],
    base: Option<Iqu>,
    per_frame: bool,
    explain: &mut Vec<String>,
) -> Result<Vec<Iqu>, Error> {
    let mut img = vec![base.unwrap_or([0.0; 3]); sky_pixels.len()];
    let nx = geom.nx;
    let pos = |o: u32| ((o as usize) % nx, (o as usize) / nx);
    if let Some(s) = &scene.sky {
        explain.push(format!(
            "  sky I = {} e-/px, p = {} ({:.3}%), chi = {} deg",
            s.brightness_e,
            s.p,
            100.0 * s.p,
            s.chi_deg
        ));
        if let Some([gx, gy]) = s.gradient_e_per_arcmin {
            explain.push(format!("  + linear gradient ({gx}, {gy}) e-/px per arcmin"));
            let (q0, u0) = (s.p * (2.0 * s.chi_deg.to_radians()).cos(), s.p * (2.0 * s.chi_deg.to_radians()).sin());
            for (k, &(o, _)) in sky_pixels.iter().enumerate() {
                let (x, y) = pos(o);
                let (xa, ya) = inst.pixel_to_arcmin(x as f64, y as f64);
                let i = (s.brightness_e + gx * xa + gy * ya).max(0.0);
                img[k] = [i, i * q0, i * u0];
            }
        }
    }
    if (!scene.stars.is_empty() && !per_frame) || !scene.extended.is_empty() {
        // Sky-pixel ordinal of each detector pixel, for sources that touch a window.
        let mut ordinal = vec![u32::MAX; geom.nx * geom.ny];
        for (k, &(o, _)) in sky_pixels.iter().enumerate() {
            ordinal[o as usize] = k as u32;
        }
        for st in scene.stars.iter().filter(|_| !per_frame) {
            explain.push(format!("  + star {}", describe_star(st)));
            add_star(&mut img, &ordinal, inst, st);
        }
        for ex in &scene.extended {
            explain
                .push(format!("  + extended source: {:?} profile, p = {}, chi = {} deg", ex.profile, ex.p, ex.chi_deg));
            add_extended(&mut img, sky_pixels, inst, ex)?;
        }
    }
    Ok(img)
}

/// The sky's `V` at the plate (scene `sky.v`), which the sky's `(I, Q, U)` does not hold: it
/// reaches the beams through the analyser's `V` column. The field's elements (an
/// instrumental field, a stressed lens, plate defects) would mix it with `I, Q, U` pixel by
/// pixel, which the sky image of `(I, Q, U)` does not carry: refused (a telescope is refused
/// by the scene's checks).
fn sky_v_of(
    scene: &Scene,
    inst: &Instrument,
    geom: &BeamGeometry,
    sky_pixels: &[(u32, u32)],
    sky: &SkyAtPlate,
    chain: &field::InstrumentChain,
    explain: &mut Vec<String>,
) -> Result<Option<SkyV>, Error> {
    let Some(s) = scene.sky.as_ref().filter(|s| s.v != 0.0) else { return Ok(None) };
    if !chain.elements.is_empty() {
        return Err(Error::Scene {
            path: PathBuf::from("<scene>"),
            message: "sky.v: the sky's circular polarization is not carried through the instrumental field's \
                      elements ([effects.instpol], a stressed lens, plate defects): the sky image holds \
                      (I, Q, U)"
                .into(),
        });
    }
    explain.push(format!("  sky V/I = {} (through the plate's V column)", s.v));
    Ok(Some(match (sky, s.gradient_e_per_arcmin) {
        (SkyAtPlate::Constant(_), _) | (_, None) => SkyV::Constant(s.brightness_e * s.v),
        (SkyAtPlate::Image(_), Some([gx, gy])) => SkyV::Image(
            sky_pixels
                .iter()
                .map(|&(o, _)| {
                    let (x, y) = ((o as usize) % geom.nx, (o as usize) / geom.nx);
                    let (xa, ya) = inst.pixel_to_arcmin(x as f64, y as f64);
                    s.v * (s.brightness_e + gx * xa + gy * ya).max(0.0)
                })
                .collect(),
        ),
    }))
}

/// The plate and the analyser a scene names (`field::Analyser`): the instrument's plate
/// (half- or quarter-wave) with the scene's retardance error, zero angle, dust and
/// pleochroism, its motion during an exposure, the Wollaston and the post-analyser optics;
/// with the lines that say so.
fn analyser_of(scene: &Scene, inst: &Instrument, filter: &instrument::Filter) -> (Analyser, Vec<String>) {
    let fx = &scene.effects;
    let mut hwp = Hwp { nominal_retardance: inst.polarimetry.plate.retardance(), ..Hwp::ideal() };
    let mut optics: Vec<String> = Vec::new();
    let qwp = inst.polarimetry.plate == instrument::Plate::QuarterWave;
    if qwp {
        optics.push("quarter-wave plate (retardance pi/2)".into());
    }
    if let Some(d) = fx.hwp_retardance_error_deg {
        hwp.retardance_error = d.to_radians();
        optics.push(format!("HWP retardance error {d} deg"));
    }
    let chi_off = if fx.hwp_chi_offset_from_filter { Some(filter.chi_offset_deg()) } else { fx.hwp_chi_offset_deg };
    // A quarter-wave plate's zero angle is its axis's offset: twice it is the plate's
    // chi_offset (mueller::Hwp: the axis at theta + chi_offset / 2).
    let qwp_zero =
        if fx.hwp_chi_offset_from_filter { Some(filter.qwp_zero_angle_deg()) } else { fx.qwp_zero_angle_deg };
    if let Some(z) = qwp_zero.filter(|_| qwp) {
        hwp.chi_offset = 2.0 * z.to_radians();
        optics.push(format!("QWP zero angle {z} deg (fast axis at the plate angle + {z} deg)"));
    } else if let Some(c) = chi_off.filter(|_| !qwp) {
        hwp.chi_offset = c.to_radians();
        optics.push(format!("HWP chromatic zero angle {c} deg"));
    }
    if let Some(h) = &fx.dust {
        hwp.dust = Some(Harmonic { amplitude: h.amplitude, phase: h.phase_deg.to_radians() });
        optics.push(format!("HWP dust (k = 1) amplitude {} phase {} deg", h.amplitude, h.phase_deg));
    }
    if let Some(h) = &fx.pleochroism {
        hwp.pleochroism = Some(Harmonic { amplitude: h.amplitude, phase: h.phase_deg.to_radians() });
        optics.push(format!("HWP pleochroism (k = 2) amplitude {} phase {} deg", h.amplitude, h.phase_deg));
    }
    let wollaston = match &fx.wollaston {
        Some(w) => {
            let s = w.s.unwrap_or(1.0 - w.t);
            optics.push(format!("Wollaston t = {}, s = {s}, delta_alpha = {} deg", w.t, w.delta_alpha_deg));
            Wollaston { t: w.t, s, delta_alpha: w.delta_alpha_deg.to_radians() }
        }
        None => Wollaston::ideal(),
    };
    let post = fx.post_analyzer.as_ref().map(|p| {
        optics.push(format!("post-analyzer M_PA(A = {}, B = {}, C = {}, phi = {} deg)", p.a, p.b, p.c, p.phi_deg));
        mueller::post_analyzer(p.a, p.b, p.c, p.phi_deg.to_radians())
    });
    let mut lines = vec![if optics.is_empty() {
        "optics: ideal HWP + ideal Wollaston (eq:ord)".to_string()
    } else {
        format!("optics (mueller::DualBeam, compiled once): {}", optics.join("; "))
    }];
    lines.push("  per HWP angle: f_O, f_E = two rows . (I, Q, U) at the plate (the model is linear)".into());
    let motion = match &scene.hwp_motion {
        None => PlateMotion::Fixed,
        Some(m) => {
            lines.push(format!(
                "  the plate turns {} deg during each exposure, centred on its angle ({})",
                m.sweep_deg,
                if m.substeps > 0 {
                    format!("the fixed plate's fluxes averaged over {} sub-steps", m.substeps)
                } else {
                    "the plate's matrix averaged over the motion, mueller::Hwp::matrix_swept".into()
                }
            ));
            match m.substeps {
                0 => PlateMotion::Swept { sweep: m.sweep_deg.to_radians() },
                n => PlateMotion::Substeps { sweep: m.sweep_deg.to_radians(), n },
            }
        }
    };
    (Analyser::new(&DualBeam { pre: vec![], hwp, wollaston, post }, motion), lines)
}

/// The detector's steps per pixel a scene names, in order, with the flat-field error map,
/// the output's BITPIX and the line that says so.
fn detector_steps(
    scene: &Scene,
    inst: &Instrument,
    geom: &BeamGeometry,
) -> (Vec<DetStep>, Option<Vec<f64>>, Bitpix, String) {
    let fx = &scene.effects;
    let d = &inst.detector;
    let mut steps = Vec::new();
    let mut det = Vec::new();
    let flat = match &fx.flat {
        Some(f) => {
            steps.push(DetStep::Flat);
            det.push(format!(
                "flat-field errors (o: rms {} + large-scale {}; e: rms {} + large-scale {})",
                f.pixel_rms_o, f.large_scale_o, f.pixel_rms_e, f.large_scale_e
            ));
            Some(flat_map(geom, f, scene.seed))
        }
        None => None,
    };
    if let Some(t) = fx.transparency_rms {
        det.push(format!("transparency noise {t} rms per frame (both beams together)"));
    }
    if fx.photon_noise {
        steps.push(DetStep::Photon);
        det.push("photon noise (Poisson)".into());
    }
    if let Some(c) = &fx.cosmic_rays {
        steps.push(DetStep::Cosmic);
        det.push(format!(
            "cosmic rays ({} per frame, {} e- over {} px squares)",
            c.rate_per_frame, c.energy_e, c.size_px
        ));
    }
    let rn = fx.read_noise_e.or(if fx.read_noise { Some(d.read_noise_e) } else { None });
    if let Some(r) = rn.filter(|&r| r > 0.0) {
        steps.push(DetStep::ReadNoise(r));
        det.push(format!("read noise {r} e- rms"));
    }
    let gain = fx.gain_e_per_adu.unwrap_or(d.gain_e_per_adu);
    steps.push(DetStep::Gain(gain));
    det.push(format!("gain {gain} e-/ADU"));
    if d.bias_adu != 0.0 {
        steps.push(DetStep::Bias(d.bias_adu));
        det.push(format!("bias {} ADU", d.bias_adu));
    }
    if fx.saturation {
        steps.push(DetStep::Saturate(d.saturation_adu));
        det.push(format!("saturation at {} ADU", d.saturation_adu));
    }
    let bitpix = Bitpix::from_fits(scene.output.bitpix).unwrap_or(Bitpix::U16);
    det.push(format!(
        "written as BITPIX {}{}",
        scene.output.bitpix,
        if bitpix == Bitpix::U16 { " (rounded)" } else { "" }
    ));
    (steps, flat, bitpix, format!("detector steps per pixel: {}", det.join(" -> ")))
}
