# Type stubs of the Python package `instpol` (see __init__.py for the docstrings, which cite
# Patat & Romaniello 2006 by equation label).
from __future__ import annotations

import os
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import numpy.typing as npt
from astropy.table import Table

__version__: str
#: How to cite instpol and Patat & Romaniello 2006 (PASP 118, 146), with BibTeX entries.
__citation__: str
ArrayLike = npt.ArrayLike
PathLike = Union[str, os.PathLike[str]]

class InputError(ValueError):
    """Bad input: a value, an array or a file's content (a ValueError), with the CLI's message."""

class FileError(OSError):
    """A file that cannot be opened, read or written (an OSError), with the CLI's message."""

def stokes(
    hwp_deg: ArrayLike,
    f_o: ArrayLike,
    f_e: ArrayLike,
    sigma_o: Optional[ArrayLike] = ...,
    sigma_e: Optional[ArrayLike] = ...,
    kappa: Optional[float] = ...,
    *,
    angles_in_radians: bool = ...,
) -> Dict[str, Any]:
    """Q/I, U/I, P, chi with errors from dual-beam fluxes (Eq. 5 [eq:F], Eq. 7 [eq:Q], Eq. 8 [eq:U], Eq. 10 [eq:sigp], Eq. 11 [eq:sigchi]).

    hwp_deg: HWP angles (deg); f_o, f_e: fluxes of the two beams, (N,) or (M, N) for M stars
    (electrons with Poisson errors unless sigma_o, sigma_e are given); kappa: a known Wollaston
    imbalance. Returns fractions (q, u, p, sigma_*), degrees (chi_deg in [0, 180)), harmonics
    and kappa. Raises InputError on bad shapes or angles.
    """

def bias(
    p: ArrayLike,
    sigma: ArrayLike,
    estimator: str = ...,
    interval: str = ...,
    *,
    cl: float = ...,
    sigma_q: Optional[ArrayLike] = ...,
    sigma_u: Optional[ArrayLike] = ...,
    chi_deg: ArrayLike = ...,
) -> Dict[str, Any]:
    """Bias-corrected P0 and an interval on it (section 4.1 [sec:bias]), vectorized.

    p, sigma: measured P and the error of each of Q and U, in the same units (fraction or
    percent); estimator: naive, as, wk, ml, mp2, mas, mb, pr06; interval: neyman or hpd at
    confidence cl. Returns estimate, lo, hi (NaN where a limit does not exist) in the
    broadcast shape. Raises InputError on negative or non-finite input.
    """

class Calibration:
    """A calibration file: the instrumental polarization field of one instrument and filter
    (a partial polarizer p, phi, or a Mueller field from calibrate-mueller)."""

    @classmethod
    def load(cls, path: PathLike) -> Calibration:
        """Read a calibration FITS file; FileError if unreadable, InputError if not valid."""
    @property
    def path(self) -> os.PathLike[str]:
        """The file it was loaded from."""
    @property
    def instrument(self) -> str:
        """Instrument name."""
    @property
    def filter(self) -> str:
        """Filter name."""
    @property
    def lambda_nm(self) -> float:
        """Effective wavelength (nm), NaN if unknown."""
    @property
    def hwp_chi_offset_deg(self) -> float:
        """HWP chromatic zero angle added to a measured chi (deg)."""
    @property
    def model(self) -> str:
        """RADIAL, RADIAL+RESIDUAL, MAP, MUELLER or TELESCOPE."""
    @property
    def mueller_model(self) -> Optional[str]:
        """A Mueller field's model (physical, general); None for a p, phi calibration."""
    @property
    def mueller_free(self) -> List[str]:
        """A Mueller field's free effects; empty for a p, phi calibration."""
    @property
    def rms_residual(self) -> float:
        """RMS fit residual per component (fraction); NaN for a Mueller field."""
    @property
    def centre_arcmin(self) -> Tuple[float, float]:
        """Optical-axis centre (arcmin from the detector centre); NaN for a Mueller field."""
    @property
    def has_pixel_grid(self) -> bool:
        """True when positions may be given in px."""
    @property
    def telescope_bands(self) -> List[str]:
        """Bands of the telescope model in the file (empty without one)."""
    def evaluate(self, x: ArrayLike, y: ArrayLike, units: str = ...) -> Dict[str, Any]:
        """Instrumental (q, u) = p (cos 2phi, sin 2phi) (Eq. 17 [eq:instpol]) with errors at (x, y)
        (arcmin from the detector centre, or px with units="px"); fractions."""
    def correct(
        self,
        x: ArrayLike,
        y: ArrayLike,
        q: ArrayLike,
        u: ArrayLike,
        sigma_q: ArrayLike,
        sigma_u: ArrayLike,
        cov_qu: Optional[ArrayLike] = ...,
        *,
        units: str = ...,
        method: str = ...,
        allow_extrapolation: bool = ...,
        extrapolation_error: float = ...,
        estimator: Optional[str] = ...,
        parang_deg: Optional[ArrayLike] = ...,
        parang_end_deg: Optional[ArrayLike] = ...,
        band: Optional[str] = ...,
        recorded: Optional[Dict[str, Any]] = ...,
        hwp_chi_offset_deg: Optional[float] = ...,
        instrument: Optional[str] = ...,
        filter: Optional[str] = ...,
        plate: Optional[str] = ...,
        allow_mismatch: bool = ...,
        sky_pa_deg: Optional[float] = ...,
        product: Optional[Dict[str, Any]] = ...,
    ) -> Dict[str, Any]:
        """Exact inversion of Eq. 17 [eq:instpol] (or Eq. 18 [eq:approx]), as `instpol correct`, bit for bit.

        x, y: arcmin (or px with units="px"); q, u and their errors: fractions; parang_deg:
        each row's parallactic angle (deg) for a telescope model. Returns q0, u0, p0 (fractions),
        chi0_deg and their errors. Raises InputError outside the field (unless
        allow_extrapolation) and on bad input.
        """
    def correct_map(
        self,
        input: PathLike,
        output: Optional[PathLike] = ...,
        *,
        method: str = ...,
        allow_extrapolation: bool = ...,
        extrapolation_error: float = ...,
        parang_deg: Optional[Union[float, Sequence[float]]] = ...,
        rotator_deg: Optional[float] = ...,
        band: Optional[str] = ...,
        allow_mismatch: bool = ...,
    ) -> StokesMap:
        """A whole Stokes map file corrected, as `instpol correct --in MAP.fits`, bit for bit."""

class StokesMap:
    """A binned Stokes map: (ny, nx) arrays of fractions (q, u, p and errors), chi_deg in
    [0, 180), bin centres in arcmin, and the header's values."""

    header: Dict[str, Any]
    warnings: List[str]
    correction: Optional[Dict[str, Any]]
    q: npt.NDArray[np.float64]
    u: npt.NDArray[np.float64]
    sigma_q: npt.NDArray[np.float64]
    sigma_u: npt.NDArray[np.float64]
    cov_qu: npt.NDArray[np.float64]
    sigma_q_phot: npt.NDArray[np.float64]
    sigma_u_phot: npt.NDArray[np.float64]
    p: npt.NDArray[np.float64]
    chi_deg: npt.NDArray[np.float64]
    n_pixels: npt.NDArray[np.uint32]
    intensity: npt.NDArray[np.float64]
    intensity_snr: npt.NDArray[np.float64]
    valid: npt.NDArray[np.bool_]
    x_arcmin: npt.NDArray[np.float64]
    y_arcmin: npt.NDArray[np.float64]

class CircularMap:
    """A binned V/I map from frames through a quarter-wave plate: (ny, nx) arrays of V/I
    (fraction, IAU sign) and its errors, bin centres in arcmin, and the header's values."""

    header: Dict[str, Any]
    warnings: List[str]
    v: npt.NDArray[np.float64]
    sigma_v: npt.NDArray[np.float64]
    sigma_v_phot: npt.NDArray[np.float64]
    n_pixels: npt.NDArray[np.uint32]
    intensity: npt.NDArray[np.float64]
    intensity_snr: npt.NDArray[np.float64]
    valid: npt.NDArray[np.bool_]
    x_arcmin: npt.NDArray[np.float64]
    y_arcmin: npt.NDArray[np.float64]

def reduce(
    frames: Union[PathLike, Sequence[Any]],
    instrument: Optional[str] = ...,
    *,
    bin: int = ...,
    nsigma: float = ...,
    allow_incomplete: bool = ...,
    bias: Optional[PathLike] = ...,
    flat: Optional[PathLike] = ...,
    hwp_angles: Optional[Sequence[float]] = ...,
    assembled: bool = ...,
    output: Optional[PathLike] = ...,
) -> Union[StokesMap, CircularMap]:
    """Frames to a binned Stokes map (Eq. 5 [eq:F], Eq. 7 [eq:Q], Eq. 8 [eq:U] per pixel, clipped bin means); through
    a quarter-wave plate, a CircularMap of V/I.

    bin: bin side (px); nsigma: clipping threshold (robust sigmas); hwp_angles: deg per frame
    when the headers carry none. Raises FileError or InputError with the CLI's messages.
    """

class CatalogTable(Table):
    """The stars of catalog() as an astropy Table with units; catalog-wide values in meta and by key."""
    def __getitem__(self, item: Any) -> Any: ...

def catalog(
    frames: Union[PathLike, Sequence[Any]],
    instrument: Optional[str] = ...,
    *,
    fwhm: float = ...,
    threshold: float = ...,
    aperture: Union[float, str] = ...,
    annulus: Tuple[float, float] = ...,
    bias: Optional[PathLike] = ...,
    flat: Optional[PathLike] = ...,
    hwp_angles: Optional[Sequence[float]] = ...,
    assembled: bool = ...,
    kappa: Optional[float] = ...,
    kappa_from_data: bool = ...,
    pair_tol: float = ...,
    cal: Optional[PathLike] = ...,
    allow_extrapolation: bool = ...,
    force: bool = ...,
    as_table: Optional[bool] = ...,
) -> Any:
    """Every paired star measured: Q/I, U/I, P, chi with errors and flags.

    fwhm (px), threshold (detection sigmas), aperture (px, "2.5fwhm" or "best"), annulus
    (inner, outer px), pair_tol (px); cal: correct in the same run. frames: paths, HDUList,
    CCDData or (array, header). Returns a dict of columns (fractions, deg, px, arcmin as their
    names say) as an astropy Table with units where astropy is installed (CatalogTable: the
    catalog-wide values in meta and by key), as_table=False the dict.
    Raises FileError or InputError.
    """

def calibrate(
    map: PathLike,
    sky_p_percent: float,
    sky_chi_deg: float,
    instrument: Optional[str] = ...,
    *,
    out: Optional[PathLike] = ...,
    model: str = ...,
    include_c0: bool = ...,
    free_centre: bool = ...,
    exclude: Sequence[str] = ...,
    residual_map: bool = ...,
) -> Dict[str, Any]:
    """The instrumental field from a Stokes map of an empty field of known sky polarization
    (sky_p_percent in PERCENT, sky_chi_deg in deg): Eq. 17 [eq:instpol] solved per bin, the
    radial model fitted (coefficients: fractions per arcmin^k); out: the calibration file.
    instpol calibrate --map."""

def calibrate_stars(
    catalogs: Union[PathLike, Sequence[PathLike]],
    instrument: Optional[str] = ...,
    *,
    filter: str,
    out: Optional[PathLike] = ...,
    interstellar: Union[str, Tuple[float, float]] = ...,
    offsets: Optional[Sequence[Tuple[float, float]]] = ...,
    model: str = ...,
    free_centre: bool = ...,
    reject_alpha: float = ...,
    match_radius_arcsec: float = ...,
    allow_mismatch: bool = ...,
) -> Dict[str, Any]:
    """The instrumental field from field-star catalogs of dithered pointings (calibrate-stars).

    interstellar: "free", "zero" or (P_percent, chi_deg); offsets: (dx, dy) arcmin per catalog
    or None to measure them; model: radialN, polyN or plane; out: the calibration file.
    """
    ...

def demo(out_dir: PathLike, *, frames: bool = ..., keep_frames: bool = ..., seed: int = ...) -> Dict[str, Any]:
    """The paper's three empty fields simulated, calibrated and validated: instpol demo's report."""

def simulate(
    scene: Union[PathLike, Dict[str, Any]],
    out: PathLike,
    *,
    field: Optional[PathLike] = ...,
    force: bool = ...,
) -> Dict[str, Any]:
    """Raw-like dual-beam FITS frames of a scene (a TOML file or the same table as a dict), one
    per HWP angle, and truth.json, in out: instpol simulate. Fluxes in e- per exposure,
    polarization as fractions, angles in deg; field: a calibration whose model replaces the
    scene's effects.instpol. Returns the files written (outputs, truth_output)."""

def scan(
    dirs: Union[PathLike, Sequence[PathLike]],
    instrument: str,
    products: PathLike,
    *,
    sky: Optional[Union[Dict[str, Tuple[float, float]], PathLike]] = ...,
    standards: Optional[PathLike] = ...,
    pointing_tol_arcsec: float = ...,
    max_gap_min: float = ...,
    bin: int = ...,
    fwhm: float = ...,
    aperture: float = ...,
    out: Optional[PathLike] = ...,
) -> Dict[str, Any]:
    """A folder of raw files sorted by their headers into a plan: instpol scan's plan."""

def run(
    plan: Union[Dict[str, Any], PathLike],
    *,
    jobs: int = ...,
    units: Optional[Sequence[str]] = ...,
    dry_run: bool = ...,
    instpol_bin: Optional[PathLike] = ...,
) -> Dict[str, Any]:
    """A plan run by the instpol binary, finished units skipped: instpol run's report."""
