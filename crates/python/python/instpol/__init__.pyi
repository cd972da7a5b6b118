# Type stubs of the Python package `instpol` (see __init__.py for the docstrings, which cite
# Patat & Romaniello 2006 by equation label).
import os
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import numpy.typing as npt

__version__: str
ArrayLike = npt.ArrayLike
PathLike = Union[str, os.PathLike[str]]

class InputError(ValueError):
    """Bad input: a value, an array or a file's content."""

class FileError(OSError):
    """A file that cannot be opened, read or written."""

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
    """Q/I, U/I, P, chi with errors from dual-beam fluxes (eq:F, eq:Q, eq:U, eq:sigp, eq:sigchi)."""

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
    """Bias-corrected P0 and an interval on it (section sec:bias), vectorized."""

class Calibration:
    """A calibration file: the instrumental polarization field of one instrument and filter
    (a partial polarizer p, phi, or a Mueller field from calibrate-mueller)."""

    @classmethod
    def load(cls, path: PathLike) -> Calibration: ...
    @property
    def path(self) -> os.PathLike[str]: ...
    @property
    def instrument(self) -> str: ...
    @property
    def filter(self) -> str: ...
    @property
    def lambda_nm(self) -> float: ...
    @property
    def hwp_chi_offset_deg(self) -> float: ...
    @property
    def model(self) -> str: ...
    @property
    def mueller_model(self) -> Optional[str]: ...
    @property
    def mueller_free(self) -> List[str]: ...
    @property
    def rms_residual(self) -> float: ...
    @property
    def centre_arcmin(self) -> Tuple[float, float]: ...
    @property
    def has_pixel_grid(self) -> bool: ...
    @property
    def telescope_bands(self) -> List[str]: ...
    def evaluate(self, x: ArrayLike, y: ArrayLike, units: str = ...) -> Dict[str, Any]:
        """Instrumental (q, u) = p (cos 2phi, sin 2phi) (eq:instpol) with errors at (x, y)."""
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
    ) -> Dict[str, Any]:
        """Exact inversion of eq:instpol (or eq:approx), as `instpol correct`, bit for bit."""
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

def reduce(
    frames: Union[PathLike, Sequence[PathLike]],
    instrument: str = ...,
    *,
    bin: int = ...,
    nsigma: float = ...,
    allow_incomplete: bool = ...,
    bias: Optional[PathLike] = ...,
    flat: Optional[PathLike] = ...,
    hwp_angles: Optional[Sequence[float]] = ...,
    assembled: bool = ...,
    output: Optional[PathLike] = ...,
) -> StokesMap:
    """Frames to a binned Stokes map (eq:F, eq:Q, eq:U per pixel, clipped bin means)."""

def catalog(
    frames: Union[PathLike, Sequence[PathLike]],
    instrument: str = ...,
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
) -> Dict[str, Any]:
    """Every paired star measured: Q/I, U/I, P, chi with errors and flags."""

def demo(out_dir: PathLike, *, frames: bool = ..., keep_frames: bool = ..., seed: int = ...) -> Dict[str, Any]:
    """The paper's three empty fields simulated, calibrated and validated: instpol demo's report."""

def scan(
    dirs: Union[PathLike, Sequence[PathLike]],
    instrument: str,
    products: PathLike,
    *,
    sky: Optional[Dict[str, Tuple[float, float]]] = ...,
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
