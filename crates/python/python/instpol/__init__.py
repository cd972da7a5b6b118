"""instpol: find, model and remove the instrumental polarization of dual-beam imaging
polarimeters (half-wave plate + Wollaston prism), after Patat & Romaniello 2006, PASP 118, 146
(PR06; equations cited by their number in the published paper and their label in its source,
e.g. Eq. 7 [eq:Q]).

The same library functions as the ``instpol`` command-line tool, with numpy arrays in and out:

- :func:`simulate`: raw-like frames of a scene (``instpol simulate``);
- :func:`reduce`: frames -> binned Stokes map (``instpol reduce``), a :class:`StokesMap` or,
  through a quarter-wave plate, a :class:`CircularMap`;
- :func:`catalog`: frames -> every paired star measured (``instpol catalog``), a
  :class:`CatalogTable`;
- :func:`stokes`: dual-beam fluxes at N half-wave-plate angles -> Q/I, U/I, P, chi and errors
  (``instpol stokes``), for one star or many at once;
- :func:`bias`: bias-corrected polarization degree and an interval on P0 (``instpol bias``);
- :func:`calibrate`, :func:`calibrate_stars`: the instrumental polarization over the field from
  an empty field of known sky polarization or from field stars (``instpol calibrate``,
  ``instpol calibrate-stars``);
- :class:`Calibration`: a calibration file; ``evaluate`` gives the instrumental polarization,
  ``correct`` and ``correct_map`` remove it (``instpol correct``);
- :func:`demo`: the whole chain on the paper's FORS1 fields (``instpol demo``);
- :func:`scan`, :func:`run`: a folder of raw files sorted into a plan, and the plan run
  (``instpol scan``, ``instpol run``).

Units: polarization degrees and Stokes ratios are fractions (not percent) unless a name says
``percent``; angles are degrees (``_deg``); positions are arcmin from the detector centre
(``_arcmin``) or 0-based pixels; fluxes are electrons.

This module only converts arguments; the numbers come from the compiled library
(``instpol._instpol``), which works with the GIL released. Errors raise :class:`InputError`
(a ``ValueError``) or :class:`FileError` (an ``OSError``) with the CLI's messages.

``instpol.__citation__`` says how to cite the tool and PR06 (with BibTeX), as
``instpol --version`` does. The guide's tutorial notebook, docs/guide/tutorial.ipynb, walks
through a night on simulated data; docs/guide/correcting.md has a pipeline from frames to
corrected stars.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import warnings
from typing import Any, Dict, Iterator, Optional, Sequence, Tuple, Union

import numpy as np

from . import _instpol
from ._instpol import FileError, InputError, __citation__, __version__

__all__ = [
    "scan",
    "run",
    "stokes",
    "bias",
    "Calibration",
    "reduce",
    "catalog",
    "calibrate",
    "calibrate_stars",
    "demo",
    "simulate",
    "StokesMap",
    "CircularMap",
    "CatalogTable",
    "InputError",
    "FileError",
    "__version__",
    "__citation__",
]

ArrayLike = Any
PathLike = Union[str, "os.PathLike[str]"]
#: A frame: a FITS file's path, an astropy ``HDUList``, a ``CCDData``, or ``(array, header)``.
Frame = Any


def _f64(a: ArrayLike, name: str) -> np.ndarray:
    """``a`` as a C-contiguous float64 array (no copy when it already is one)."""
    try:
        return np.asarray(a, dtype=np.float64, order="C")
    except (TypeError, ValueError) as e:
        raise InputError(f"{name}: not an array of numbers ({e})") from None


def _broadcast(names: Sequence[str], arrays: Sequence[ArrayLike]) -> Tuple[Tuple[int, ...], list]:
    """Broadcast to one shape; return the shape and the flattened contiguous float64 arrays."""
    conv = [_f64(a, n) for n, a in zip(names, arrays)]
    try:
        b = np.broadcast_arrays(*conv)
    except ValueError:
        shapes = ", ".join(f"{n} {a.shape}" for n, a in zip(names, conv))
        raise InputError(f"arrays of shapes that do not broadcast together: {shapes}") from None
    shape = b[0].shape
    return shape, [np.ascontiguousarray(x).ravel() for x in b]


def _reshape(d: Dict[str, Any], shape: Tuple[int, ...], n: int) -> Dict[str, Any]:
    """Give every length-``n`` array of ``d`` the input ``shape`` (a 0-d shape gives scalars)."""
    out = {}
    for k, v in d.items():
        if isinstance(v, np.ndarray) and v.ndim == 1 and v.shape[0] == n:
            v = v.item() if shape == () else v.reshape(shape)
        elif isinstance(v, dict):
            v = _reshape(v, shape, n)
        out[k] = v
    return out


def _first_star(d: Dict[str, Any]) -> Dict[str, Any]:
    """The batch result of one star as that star's values (floats, lists of its own)."""
    out: Dict[str, Any] = {}
    for k, v in d.items():
        if k == "fourier":
            out[k] = {h: (w if h == "k" else w[0]) for h, w in v.items()}
        elif k == "exposures" and v is not None:
            out[k] = {h: (w if h in ("index", "hwp_deg") else w[0]) for h, w in v.items()}
        elif isinstance(v, np.ndarray):
            out[k] = v[0].item() if v.ndim == 1 else v[0]
        elif isinstance(v, list):
            out[k] = v[0]
        else:
            out[k] = v
    return out


def stokes(
    hwp_deg: ArrayLike,
    f_o: ArrayLike,
    f_e: ArrayLike,
    sigma_o: Optional[ArrayLike] = None,
    sigma_e: Optional[ArrayLike] = None,
    kappa: Optional[float] = None,
    *,
    angles_in_radians: bool = False,
) -> Dict[str, Any]:
    """Reduce dual-beam fluxes at N half-wave-plate angles to Q/I, U/I, P and chi.

    The normalized flux differences ``F_i`` (Eq. 5 [eq:F]) give Q/I and U/I by the Fourier sums
    Eq. 7 [eq:Q], Eq. 8 [eq:U] on the optimal angle set (theta_i = i * 22.5 deg, N a multiple of
    4), else by (weighted) least squares of Eq. 6 [eq:system]; P and chi (Eq. 1 [eq:poldeg],
    Eq. 2 [eq:polang]) with errors propagated from the per-beam errors and the analytic Eq. 10
    [eq:sigp] / Eq. 11 [eq:sigchi]; the harmonics (Eq. 9 [eq:fourcoeff]), a_0 (Eq. 16 [eq:a0])
    and the Wollaston kappa_j (Eq. 14 [eq:g], Eq. 15 [eq:kappa2]). The same reduction as
    ``instpol stokes``.

    Parameters
    ----------
    hwp_deg : (N,) array
        HWP angles in degrees, in observing order (angles that all lie within 0..2pi are
        refused as radians unless ``angles_in_radians=True``).
    f_o, f_e : (N,) or (M, N) arrays
        Ordinary and extraordinary fluxes: one star, or M stars (one per row) at the same
        angles (the batch form).
    sigma_o, sigma_e : arrays of the same shape, optional
        1-sigma errors of the fluxes; without them the fluxes are photon counts (electrons)
        with Poisson errors sqrt(f).
    kappa : float, optional
        Known Wollaston imbalance (t - s)/(t + s) in (-1, 1): fluxes are corrected as
        f_o / (1 + kappa), f_e / (1 - kappa) first.

    Returns
    -------
    dict
        ``q, u, p`` (fractions), ``chi_deg`` in [0, 180), ``sigma_q, sigma_u, cov_qu,
        sigma_p, sigma_chi_deg`` (NaN where chi is undetermined), ``a0, sigma_a0, snr,
        sigma_p_analytic, sigma_chi_analytic_deg, mean_kappa`` (NaN when none),
        ``chi_defined``: floats for one star, (M,) arrays for M stars; ``f, sigma_f`` ((N,) or
        (M, N)), ``kappa`` (the kappa_j), ``fourier`` (dict of ``k, a, b, sigma_a, sigma_b,
        power``), ``estimator`` and ``warnings``; ``exposures`` (see below).

    Exposures repeated at one plate position (angles equal modulo 360 deg) are combined first,
    as ``instpol stokes`` does: the fluxes of each position summed, their variances added
    (photon counts stay counts, checked with their Poisson errors; a negative count is
    refused), so ``n_hwp`` and ``f`` count positions. ``exposures`` is then a dict of every
    input exposure's ``index``, ``hwp_deg``, its own ``f`` (Eq. 5 [eq:F]), its ``pull`` about its
    position's mean and ``outlier`` (pull beyond 4 sigma; kept in the sum), ((N_in,) or
    (M, N_in)); None when no position repeats.

    Raises
    ------
    InputError
        Arrays of different shapes, fewer than 2 angles, angles that repeat a plate position
        or cannot separate Q from U, angles that look like radians, a flux or error that is not
        a finite number.

    Examples
    --------
    An ideal dual beam at the optimal four angles, P = 1 % at chi = 30 deg, 1e6 e- per beam:
    Eq. 5 [eq:F] is F_i = P cos(4 theta_i - 2 chi), and Eq. 10 [eq:sigp] gives sigma_P =
    1/(sqrt(N/2) SNR) with SNR = sqrt(2e6).

    >>> import numpy as np, instpol
    >>> theta = np.arange(4) * 22.5
    >>> f = 0.01 * np.cos(np.radians(4 * theta - 60))
    >>> r = instpol.stokes(theta, 1e6 * (1 + f), 1e6 * (1 - f))
    >>> print(f"P = {100 * r['p']:.3f} %, chi = {r['chi_deg']:.2f} deg, sigma_P = {100 * r['sigma_p']:.3f} %")
    P = 1.000 %, chi = 30.00 deg, sigma_P = 0.050 %
    """
    hwp = _f64(hwp_deg, "hwp_deg").ravel()
    fo, fe = _f64(f_o, "f_o"), _f64(f_e, "f_e")
    if fo.ndim not in (1, 2):
        raise InputError(f"f_o has {fo.ndim} dimensions: expected (N,) for one star or (M, N) for M stars")
    single = fo.ndim == 1
    two = lambda a: np.ascontiguousarray(a.reshape(1, -1) if a.ndim == 1 else a)  # noqa: E731
    so = None if sigma_o is None else two(_f64(sigma_o, "sigma_o"))
    se = None if sigma_e is None else two(_f64(sigma_e, "sigma_e"))
    if fe.ndim != fo.ndim:
        raise InputError(f"f_o has shape {fo.shape} but f_e has shape {fe.shape}")
    kap = None if kappa is None else float(kappa)
    d = _instpol._stokes(hwp, two(fo), two(fe), so, se, kap, bool(angles_in_radians), single)
    if single:
        d = _first_star(d)
    return d


def bias(
    p: ArrayLike,
    sigma: ArrayLike,
    estimator: str = "mas",
    interval: str = "neyman",
    *,
    cl: float = 0.6827,
    sigma_q: Optional[ArrayLike] = None,
    sigma_u: Optional[ArrayLike] = None,
    chi_deg: ArrayLike = 0.0,
) -> Dict[str, Any]:
    """Bias-corrected polarization degree P0 and an interval on it (section 4.1 [sec:bias]).

    P is biased high at low signal-to-noise. Estimators: ``naive``, ``as`` (asymptotic),
    ``wk`` (Wardle & Kronberg 1974), ``ml`` (maximum likelihood), ``mp2`` (2-D most probable),
    ``mas`` (Plaszczynski et al. 2014, takes unequal ``sigma_q``, ``sigma_u``; default),
    ``mb`` (posterior mean), ``pr06`` (the paper's law, valid for P/sigma > 4). Intervals:
    ``neyman`` (classical, from the Rice distribution) or ``hpd`` (Bayesian, flat prior), at
    confidence ``cl``. ``sigma`` is the error of each of Q and U (Eq. 10 [eq:sigp]); P and sigma in the
    same units. Vectorized: the arguments broadcast together; the same numbers as
    ``instpol bias``.

    Returns
    -------
    dict
        ``estimate``, ``lo``, ``hi`` (NaN where a limit does not exist), ``upper_limit_only``,
        ``empty``, ``in_validity_range`` in the broadcast shape (scalars for scalar input),
        ``all_estimators`` (name -> values), ``estimator``, ``interval_kind``, ``cl``.

    Raises
    ------
    InputError
        A negative or non-finite P or sigma, an unknown estimator or interval, ``cl`` outside
        (0, 1), arrays that do not broadcast.

    Examples
    --------
    P = 1 % measured with sigma = 0.2 %: the asymptotic estimator is sqrt(P^2 - sigma^2).

    >>> import instpol
    >>> print(f"{instpol.bias(0.01, 0.002, 'as')['estimate']:.5f}")
    0.00980
    """
    names = ["p", "sigma", "chi_deg"]
    arrs = [p, sigma, chi_deg]
    if sigma_q is not None:
        names.append("sigma_q")
        arrs.append(sigma_q)
    if sigma_u is not None:
        names.append("sigma_u")
        arrs.append(sigma_u)
    shape, flat = _broadcast(names, arrs)
    by = dict(zip(names, flat))
    d = _instpol._bias(
        by["p"], by["sigma"], str(estimator), str(interval), float(cl), by.get("sigma_q"), by.get("sigma_u"),
        by["chi_deg"], shape == (),
    )
    return _reshape(d, shape, flat[0].shape[0])



def _from_product(product, **given):
    """The arguments ``product`` (``catalog()["product"]``) stands for, each given argument kept
    when it agrees with the product's value: (instrument, filter, plate, hwp_chi_offset_deg,
    sky_pa_deg)."""
    if not isinstance(product, dict):
        raise InputError("product: expected catalog()['product'] (a dict)")
    out = []
    for name in ("instrument", "filter", "plate", "hwp_chi_offset_deg", "sky_pa_deg"):
        have, theirs = given[name], product.get(name)
        if have is not None and theirs is not None and have != theirs:
            raise InputError(f"{name}={have!r} but product says {theirs!r}: give one")
        out.append(have if have is not None else theirs)
    return tuple(out)

class Calibration:
    """A calibration file (``instpol calibrate`` or ``instpol import-map``): the instrumental
    polarization field p(x, y), phi(x, y) of one instrument and filter, its covariance, the
    region where it holds and the filter's HWP zero angle. A Mueller-field calibration
    (``instpol calibrate-mueller --out CAL.fits``, ``model == "MUELLER"``) loads too: its field
    (diattenuation, retardance, ...) is inverted exactly for polarized targets, in the maps'
    frame (``hwp_chi_offset_deg`` 0), as ``instpol correct`` does. A telescope-only file
    (``instpol fit-standards --output``, ``model == "TELESCOPE"``) loads too: :meth:`correct`
    then removes the telescope alone, with each row's ``parang_deg``; it has no field to
    :meth:`evaluate`. An instrument's constant response from standards (``instpol efficiency
    --output CAL.fits``, ``model == "RESPONSE"``: ``(q0, u0)``, efficiency and angle offset, the
    same over the field) loads too: :meth:`correct` and :meth:`correct_map` invert it exactly, and
    :meth:`evaluate` gives ``(q0, u0)`` everywhere.

    Load it with :meth:`load`; :meth:`evaluate` gives the instrumental (q, u) at positions,
    :meth:`correct` removes it from measurements (Eq. 17 [eq:instpol] inverted exactly, or
    Eq. 18 [eq:approx]).

    Examples
    --------
    The demo's V calibration at the paper's corner star, (2.53', -3.23'), where the paper's V
    polynomial predicts 0.96 % (section 11 [sec:fors1]); an unpolarized star seen there through the
    instrument corrects to P0 = 0.

    >>> import tempfile, numpy as np, instpol
    >>> tmp = tempfile.TemporaryDirectory()
    >>> _ = instpol.demo(tmp.name, frames=False)
    >>> cal = instpol.Calibration.load(f"{tmp.name}/cal_V.fits")
    >>> e = cal.evaluate(2.53, -3.23)
    >>> print(f"{100 * np.hypot(e['q'], e['u']):.2f} %", e["inside"])
    0.96 % True
    >>> c = cal.correct(2.53, -3.23, e["q"], e["u"], 4e-4, 4e-4)
    >>> abs(c["p0"]) < 1e-12
    True
    >>> tmp.cleanup()
    """

    def __init__(self, inner: Any) -> None:
        self._c = inner

    @classmethod
    def load(cls, path: PathLike) -> "Calibration":
        """Read a calibration FITS file (``path``: any calibration ``instpol`` writes, see
        docs/calibration-file.md).

        Raises
        ------
        FileError
            The file cannot be opened or read.
        InputError
            It is not a valid calibration; the message is that of ``instpol correct --cal``.

        Examples
        --------
        The V calibration the demo writes (the paper's FORS1 V field, a radial model):

        >>> import tempfile, instpol
        >>> tmp = tempfile.TemporaryDirectory()
        >>> _ = instpol.demo(tmp.name, frames=False)
        >>> cal = instpol.Calibration.load(f"{tmp.name}/cal_V.fits")
        >>> print(cal.instrument, cal.filter, cal.model, f"{cal.lambda_nm:.0f} nm")
        FORS1 V RADIAL 554 nm
        >>> tmp.cleanup()
        """
        return cls(_instpol._Calibration.load(os.fspath(path)))

    path = property(lambda self: self._c.path, doc="The file it was loaded from.")
    instrument = property(lambda self: self._c.instrument, doc="Instrument name.")
    filter = property(lambda self: self._c.filter, doc="Filter name.")
    lambda_nm = property(lambda self: self._c.lambda_nm, doc="Effective wavelength (nm), NaN if unknown.")
    hwp_chi_offset_deg = property(
        lambda self: self._c.hwp_chi_offset_deg, doc="HWP chromatic zero angle added to a measured chi (deg)."
    )
    model = property(
        lambda self: self._c.model,
        doc="Model kind: RADIAL, RADIAL+RESIDUAL, MAP, MUELLER, TELESCOPE (a telescope-only file) or RESPONSE.",
    )
    mueller_model = property(
        lambda self: self._c.mueller_model,
        doc="A Mueller field's model in words (physical, general); None for a p, phi calibration.",
    )
    mueller_free = property(
        lambda self: list(self._c.mueller_free),
        doc="A Mueller field's free effects (diattenuation, retardance, ...); empty for a p, phi calibration.",
    )
    rms_residual = property(
        lambda self: self._c.rms_residual, doc="RMS fit residual per component (fraction); NaN for a Mueller field."
    )
    centre_arcmin = property(
        lambda self: self._c.centre_arcmin, doc="Optical-axis centre (arcmin); NaN for a Mueller field."
    )
    has_pixel_grid = property(lambda self: self._c.has_pixel_grid, doc="True when positions may be given in px.")
    telescope_bands = property(
        lambda self: list(self._c.telescope_bands),
        doc="Bands of the telescope model stored in the file (empty without one): correct() then needs parang_deg.",
    )

    def __repr__(self) -> str:
        return f"<instpol.Calibration {self.instrument} {self.filter} ({self.model}) from {self.path!r}>"

    def evaluate(self, x: ArrayLike, y: ArrayLike, units: str = "arcmin") -> Dict[str, Any]:
        """The instrumental polarization at positions ``(x, y)``: ``q, u`` = p (cos 2phi,
        sin 2phi) (Eq. 17 [eq:instpol]), ``sigma_q, sigma_u, cov_qu`` (the calibration's own
        uncertainty), and ``inside`` (the position lies in the calibrated field).

        ``units``: ``"arcmin"`` (from the detector centre; the default, as ``instpol correct
        --coords``) or ``"px"`` (0-based detector pixels of the calibration's grid). Arrays
        broadcast; scalars give scalars. Raises InputError for unknown ``units``, pixels on a
        calibration without a pixel grid, or a Mueller-field or telescope-only calibration.

        Returns
        -------
        dict
            ``q, u, sigma_q, sigma_u, cov_qu`` (fractions; cov_qu a fraction squared) and
            ``inside`` (bool), in the broadcast shape of ``x, y``.

        Examples
        --------
        The demo's V calibration along the x axis at r = 1, 2, 3 arcmin, against the paper's
        V polynomial it was made from, p(r) = 0.012 r + 0.046 r^2 + 0.002 r^3 % (section 11
        [sec:fors1]), with phi the polar angle (0 deg on the x axis):

        >>> import tempfile, numpy as np, instpol
        >>> tmp = tempfile.TemporaryDirectory()
        >>> _ = instpol.demo(tmp.name, frames=False)
        >>> cal = instpol.Calibration.load(f"{tmp.name}/cal_V.fits")
        >>> r = np.array([1.0, 2.0, 3.0])
        >>> e = cal.evaluate(r, 0 * r)
        >>> print(np.round(100 * np.hypot(e["q"], e["u"]), 2), np.round(0.012 * r + 0.046 * r**2 + 0.002 * r**3, 2))
        [0.06 0.22 0.5 ] [0.06 0.22 0.5 ]
        >>> print(np.round(np.degrees(np.arctan2(e["u"], e["q"])) / 2, 1))
        [0. 0. 0.]
        >>> tmp.cleanup()
        """
        shape, (xf, yf) = _broadcast(["x", "y"], [x, y])
        return _reshape(self._c._evaluate(xf, yf, str(units)), shape, xf.shape[0])

    def correct(
        self,
        x: ArrayLike,
        y: ArrayLike,
        q: ArrayLike,
        u: ArrayLike,
        sigma_q: ArrayLike,
        sigma_u: ArrayLike,
        cov_qu: Optional[ArrayLike] = None,
        *,
        units: str = "arcmin",
        method: str = "exact",
        allow_extrapolation: bool = False,
        extrapolation_error: float = 0.5,
        estimator: Optional[str] = None,
        parang_deg: Optional[ArrayLike] = None,
        parang_end_deg: Optional[ArrayLike] = None,
        band: Optional[str] = None,
        recorded: Optional[Dict[str, Any]] = None,
        hwp_chi_offset_deg: Optional[float] = None,
        instrument: Optional[str] = None,
        filter: Optional[str] = None,
        plate: Optional[str] = None,
        allow_mismatch: bool = False,
        sky_pa_deg: Optional[float] = None,
        product: Optional[Dict[str, Any]] = None,
    ) -> Dict[str, Any]:
        """Remove the instrumental polarization from measured ``(q, u)`` at ``(x, y)``.

        Units: ``x, y`` arcmin from the detector centre (or 0-based px with ``units="px"``);
        ``q, u, sigma_q, sigma_u`` fractions (Q/I, U/I) and ``cov_qu`` a fraction squared;
        ``parang_deg``, ``parang_end_deg``, ``hwp_chi_offset_deg`` degrees;
        ``extrapolation_error`` a fraction of the instrumental p. Arrays broadcast together.

        ``instrument``, ``filter`` (and ``plate``): what the rows were measured with, as
        :func:`catalog` returns them (``cat["product"]["instrument"]``, ...). Given, they are
        checked against the calibration as ``instpol correct`` checks a catalog table's
        keywords: another instrument or filter, or a quarter-wave plate's rows, raise InputError
        unless ``allow_mismatch``.

        ``hwp_chi_offset_deg``: the HWP zero angle (deg) that ``q, u`` already carry, as
        ``catalog()``'s do (its ``chi_offset_deg``; ``instpol correct`` reads it from a table's
        column of that name): only the calibration's zero angle less this one is applied, so
        that it is not applied twice. Default: ``recorded["hwp_chi_offset_deg"]`` when given,
        else 0 (``q, u`` as measured at the plate).

        ``sky_pa_deg``: on a rotator, the instrument's position angle on the sky (deg) the rows
        were turned by into the celestial frame, as :func:`catalog` gives it
        (``cat["product"]["sky_pa_deg"]``, not None for an instrument file with a
        ``[polarimetry.sky_angle]``): the rows are turned back before the instrument is undone
        and the result is on the sky again (north through east). It needs
        ``hwp_chi_offset_deg``. With a calibration of a built-in instrument on a rotator
        (MOPTOP), rows given without it (or ``product``) raise InputError: nothing would say
        whether they are on the sky or as the instrument saw them (``sky_pa_deg=0`` says the
        latter).

        ``product``: what the rows are, whole, as :func:`catalog` gives it
        (``cat["product"]``): its ``instrument``, ``filter``, ``plate``, ``hwp_chi_offset_deg``
        and ``sky_pa_deg`` stand for those arguments (one given both ways must agree, or
        InputError). The safe way to correct a catalog's rows.

        The HWP zero angle of the calibration's filter is applied first, then ``M_I`` is
        inverted exactly (``method="exact"``, Eq. 17 [eq:instpol]) or to first order
        (``method="first-order"``, Eq. 18 [eq:approx]); the measurement's and the calibration's
        covariances are propagated. Positions outside the calibrated field raise InputError
        unless ``allow_extrapolation``; then they are flagged and the calibration variance is
        inflated by (F p)^2 (F = ``extrapolation_error``). ``units`` as in :meth:`evaluate`.
        The same function and numbers, bit for bit, as ``instpol correct``. With a Mueller
        field (``model == "MUELLER"``) the field's linear block is inverted exactly (only
        ``method="exact"``; the zero angle its maps were turned by) and ``parang_deg``, ``band`` raise
        InputError.

        A calibration holding a telescope model (``telescope_bands`` not empty, from
        ``instpol fit-standards --output``, with ``--field-cal`` beside a field model, or
        alone: ``model == "TELESCOPE"``) needs each row's parallactic angle ``parang_deg``
        (deg; ``parang_end_deg`` the exposure's end: the model is averaged over the track);
        the field is undone first, then the telescope of ``band`` (default: the calibration's
        filter, or a telescope-only file's only band), as ``instpol correct`` does with the
        columns ``parang_deg`` and ``parang_end_deg``. Without such a model, ``parang_deg``
        raises InputError (the telescope's polarization would not be removed). For stars all
        measured in the same exposures, ``recorded=catalog(...)["recorded_angles"]`` (instead
        of ``parang_deg``) undoes the telescope as each exposure saw it, each over its own
        parallactic track, demodulated together, as ``instpol correct`` does with a catalog
        table that recorded them (``telescope_exposures`` in the result). Both models live in
        the sky frame, where chi carries the HWP zero angle: rows are turned there by the field
        calibration's zero angle, less the one ``recorded["hwp_chi_offset_deg"]`` says the
        catalog's q, u carry already (a telescope model alone turns nothing), and the
        exposures' plate angles are taken there too.

        Returns
        -------
        dict
            ``q0, u0, sigma_q0, sigma_u0, cov_qu0, p0, sigma_p0, chi0_deg, sigma_chi0_deg,
            q_inst, u_inst, extrapolated`` in the broadcast shape, ``p0_<estimator>`` when an
            estimator is named (see :func:`bias`), ``n_extrapolated``, and with a telescope
            model ``telescope_model`` and ``telescope_band`` (``q_inst, u_inst`` are then the
            field's and the telescope's together).

        Raises
        ------
        InputError
            A position outside the calibrated field (without ``allow_extrapolation``), arrays
            that do not broadcast, an unknown ``method``, ``units`` or estimator, a telescope
            model without parallactic angles, angles given without one.

        Examples
        --------
        A star of P0 = 2 % at chi0 = 30 deg seen at (2.53', -3.23') through the demo's V field:
        the measured (q, u) are made here with Eq. 17 [eq:instpol] in numpy (the instrument's
        p, phi at that position from :meth:`evaluate`), and the correction gives the star back.

        >>> import tempfile, numpy as np, instpol
        >>> tmp = tempfile.TemporaryDirectory()
        >>> _ = instpol.demo(tmp.name, frames=False)
        >>> cal = instpol.Calibration.load(f"{tmp.name}/cal_V.fits")
        >>> e = cal.evaluate(2.53, -3.23)
        >>> p, c, s = np.hypot(e["q"], e["u"]), e["q"] / np.hypot(e["q"], e["u"]), e["u"] / np.hypot(e["q"], e["u"])
        >>> q0, u0 = 0.02 * np.cos(np.radians(60)), 0.02 * np.sin(np.radians(60))
        >>> i1 = 1 + p * c * q0 + p * s * u0
        >>> q1 = (q0 + p * c - p * s**2 * q0 + p * c * s * u0) / i1
        >>> u1 = (u0 + p * s + p * c * s * q0 - p * c**2 * u0) / i1
        >>> r = cal.correct(2.53, -3.23, q1, u1, 1e-4, 1e-4)
        >>> print(f"P0 = {100 * r['p0']:.3f} %, chi0 = {r['chi0_deg']:.2f} deg")
        P0 = 2.000 %, chi0 = 30.00 deg
        >>> tmp.cleanup()
        """
        if product is not None:
            instrument, filter, plate, hwp_chi_offset_deg, sky_pa_deg = _from_product(
                product, instrument=instrument, filter=filter, plate=plate,
                hwp_chi_offset_deg=hwp_chi_offset_deg, sky_pa_deg=sky_pa_deg)
        names = ["x", "y", "q", "u", "sigma_q", "sigma_u"]
        arrs = [x, y, q, u, sigma_q, sigma_u]
        optional = {"cov_qu": cov_qu, "parang_deg": parang_deg, "parang_end_deg": parang_end_deg}
        for name, a in optional.items():
            if a is not None:
                names.append(name)
                arrs.append(a)
        shape, flat = _broadcast(names, arrs)
        got = dict(zip(names, flat))
        d = self._c._correct(
            *flat[:6], got.get("cov_qu"), str(units), str(method), bool(allow_extrapolation),
            float(extrapolation_error), None if estimator is None else str(estimator),
            got.get("parang_deg"), got.get("parang_end_deg"), None if band is None else str(band), recorded,
            None if hwp_chi_offset_deg is None else float(hwp_chi_offset_deg),
            None if instrument is None or filter is None else (str(instrument), str(filter), None if plate is None else str(plate)),
            bool(allow_mismatch),
            None if sky_pa_deg is None else float(sky_pa_deg),
            product,
        )
        for w in d.pop("warnings"):
            warnings.warn(w, stacklevel=2)
        return _reshape(d, shape, flat[0].shape[0])

    def correct_map(
        self,
        input: PathLike,
        output: Optional[PathLike] = None,
        *,
        method: str = "exact",
        allow_extrapolation: bool = False,
        extrapolation_error: float = 0.5,
        parang_deg: Optional[Union[float, Sequence[float]]] = None,
        rotator_deg: Optional[float] = None,
        band: Optional[str] = None,
        allow_mismatch: bool = False,
    ) -> "StokesMap":
        """Remove the instrumental polarization from a whole Stokes map file, as
        ``instpol correct --cal CAL --in MAP.fits --out OUT.fits`` does.

        ``input``: a map from :func:`reduce` (``output=``) or ``instpol reduce``; a map that
        was already corrected (``INSTCORR`` in its header) raises InputError, as does a map of
        another instrument or filter unless ``allow_mismatch``. Every valid bin is corrected
        at its centre with the scatter and the photon-noise errors each propagated: the field
        (``method`` as in :meth:`correct`, the HWP zero angle added to chi), or a Mueller field
        (exactly), or, with a telescope model, the field then the telescope over the
        exposures' angles: each exposure at its own when the map recorded them (:func:`reduce`
        and ``instpol reduce`` do when the instrument's ``[telescope]`` names the header
        keywords), else over the set's recorded track; ``parang_deg`` ``(START, END)`` (deg)
        replaces the recorded angles with one track for the whole set; ``rotator_deg`` for a
        model fitted with rotator angles, ``band`` as in :meth:`correct`
        (default: the field calibration's filter, else the map's). ``output``: the corrected
        map, written atomically with the correction's record in its primary header
        (``INSTCORR``, ``CORRMETH``, ``CORRHWP``; ``TELMODEL``, ``TELBAND``, ``TELROT`` with a
        telescope model).

        Returns
        -------
        StokesMap
            The corrected map; ``correction`` holds ``calibration``, ``method``,
            ``hwp_chi_offset_deg``, ``n_bins``, ``n_extrapolated`` (and ``telescope_model``,
            ``telescope_band``, ``rotator_deg``, ``parang_deg`` with a telescope model).
            Notes (a recorded parallactic angle replaced, a rotator angle ignored) are in
            ``warnings`` and issued as Python warnings.

        Examples
        --------
        Simulated frames of the paper's V empty field (sky P = 1.74 %, chi = -53.8 deg, Table 1
        [tab:empty]) through the paper's V instrumental field, reduced to a map, then corrected
        with the demo's V calibration: every bin gives back the sky (chi modulo 180 deg).

        >>> import tempfile, numpy as np, instpol
        >>> tmp = tempfile.TemporaryDirectory()
        >>> d = tmp.name
        >>> _ = instpol.demo(d, frames=False)
        >>> scene = {"instrument": "fors1", "filter": "V", "seed": 102,
        ...          "sky": {"brightness_e": 12000, "p": 0.0174, "chi_deg": -53.8},
        ...          "effects": {"instpol": {"kind": "radial", "coeffs_percent": [0, 0.012, 0.046, 0.002]},
        ...                      "photon_noise": True, "read_noise": True}}
        >>> frames = instpol.simulate(scene, f"{d}/frames")["outputs"]
        >>> m = instpol.reduce(frames, "fors1", output=f"{d}/map_V.fits")
        >>> c = instpol.Calibration.load(f"{d}/cal_V.fits").correct_map(f"{d}/map_V.fits", f"{d}/map_V_corr.fits")
        >>> for name, mp in [("before", m), ("after", c)]:
        ...     lo, hi = np.percentile(100 * mp.p[mp.valid], [1, 99])
        ...     print(f"{name}: P from {lo:.1f} to {hi:.1f} % in 98 % of the bins")
        before: P from 0.8 to 2.8 % in 98 % of the bins
        after: P from 1.7 to 1.8 % in 98 % of the bins
        >>> print(f"median P = {100 * np.median(c.p[c.valid]):.2f} %, chi = {np.median(c.chi_deg[c.valid]):.1f} deg")
        median P = 1.74 %, chi = 126.2 deg
        >>> tmp.cleanup()
        """
        pa = None
        if parang_deg is not None:
            pa = [float(parang_deg)] if np.ndim(parang_deg) == 0 else [float(a) for a in parang_deg]
        d = self._c._correct_map(
            os.fspath(input), _opt_path(output), str(method), bool(allow_extrapolation),
            float(extrapolation_error), pa, None if rotator_deg is None else float(rotator_deg),
            None if band is None else str(band), bool(allow_mismatch),
        )
        for w in d["warnings"]:
            warnings.warn(w, stacklevel=2)
        return StokesMap(d)



class _BinnedMap:
    """What a binned map from :func:`reduce` holds: its header values, its warnings, and the
    arrays its class names in ``_ARRAYS``, each of shape ``(ny, nx)``."""

    _ARRAYS: Tuple[str, ...] = ()

    def __init__(self, d: Dict[str, Any]) -> None:
        self.header: Dict[str, Any] = d["header"]
        self.warnings = list(d["warnings"])
        # What the map is (instrument file's and inputs' BLAKE3, plate, ...), as its header
        # records it; None for a map that records none.
        self.product: Optional[Dict[str, Any]] = d.get("product")
        shape = (self.header["ny"], self.header["nx"])
        for k in self._ARRAYS:
            setattr(self, k, d[k].reshape(shape))


class StokesMap(_BinnedMap):
    """A binned Stokes map from :func:`reduce`: 2-D arrays of shape ``(ny, nx)`` (bin row j,
    column i) and the map's header values.

    Attributes: ``q, u`` (Q/I, U/I fractions), ``sigma_q, sigma_u, cov_qu`` (scatter errors of
    the bin means), ``sigma_q_phot, sigma_u_phot`` (photon and read noise), ``p`` (Eq. 1
    [eq:poldeg]), ``chi_deg`` (Eq. 2 [eq:polang], [0, 180)), ``n_pixels``, ``intensity``,
    ``intensity_snr``, ``valid``, ``x_arcmin, y_arcmin`` (bin centres from the detector centre),
    ``header`` (instrument, filter, hwp_angles_deg, bin_px, origin_x/y, nx, ny,
    pixel_scale_arcsec, detector_nx/ny, and hwp_zero_angle_deg: the HWP zero angle of the
    filter, which the map's q, u do not carry, ``HWPZERO``; None when not recorded),
    ``product`` (what the map is, as :func:`catalog`'s ``product``: the instrument file's and
    the inputs' BLAKE3, the plate, ...; None when not recorded) and ``warnings``.

    Examples
    --------
    The map of four simulated frames of a uniformly polarized sky (P = 1.74 %, chi = -53.8 deg):
    its ``p`` is Eq. 1 [eq:poldeg] of its ``q, u`` and every valid bin holds the sky's value.

    >>> import tempfile, numpy as np, instpol
    >>> tmp = tempfile.TemporaryDirectory()
    >>> scene = {"instrument": "fors1", "filter": "V",
    ...          "sky": {"brightness_e": 12000, "p": 0.0174, "chi_deg": -53.8}, "effects": {"photon_noise": True}}
    >>> m = instpol.reduce(instpol.simulate(scene, tmp.name)["outputs"], "fors1", bin=60)
    >>> m.q.shape == (m.header["ny"], m.header["nx"]), m.header["bin_px"]
    (True, 60)
    >>> bool(np.allclose(m.p[m.valid], np.hypot(m.q, m.u)[m.valid]))
    True
    >>> print(f"{100 * np.median(m.p[m.valid]):.2f} %, {np.median(m.chi_deg[m.valid]):.1f} deg")
    1.74 %, 126.2 deg
    >>> tmp.cleanup()
    """

    _ARRAYS = (
        "q", "u", "sigma_q", "sigma_u", "cov_qu", "sigma_q_phot", "sigma_u_phot", "p", "chi_deg",
        "n_pixels", "intensity", "intensity_snr", "valid", "x_arcmin", "y_arcmin",
    )

    def __init__(self, d: Dict[str, Any]) -> None:
        super().__init__(d)
        # A corrected map's record (Calibration.correct_map); None for a map from reduce().
        self.correction: Optional[Dict[str, Any]] = d.get("correction")

    def __repr__(self) -> str:
        h = self.header
        return (
            f"<instpol.StokesMap {h['instrument']} {h['filter']}: {h['nx']} x {h['ny']} bins of "
            f"{h['bin_px']} px, {int(self.valid.sum())} valid>"
        )


class CircularMap(_BinnedMap):
    """A binned circular-polarization map from :func:`reduce` on frames taken through a
    quarter-wave plate: 2-D arrays of shape ``(ny, nx)`` (bin row j, column i) and the map's
    header values. Its FITS file (``output=``) says ``STOKES = 'V'``; it holds no Q/I, U/I.

    Attributes: ``v`` (V/I, fraction, IAU sign), ``sigma_v`` (scatter error of the bin means),
    ``sigma_v_phot`` (photon and read noise), ``n_pixels``, ``intensity``, ``intensity_snr``,
    ``valid``, ``x_arcmin, y_arcmin`` (bin centres from the detector centre), ``header``
    (instrument, filter, stokes = "V", plate_angles_deg, qwp_zero_angle_deg: the plate's zero
    angle the demodulation added, bin_px, origin_x/y, nx, ny, pixel_scale_arcsec,
    detector_nx/ny) and ``warnings``.

    Examples
    --------
    A small strip instrument of one's own with a quarter-wave plate (an instrument file:
    docs/guide/instrument-file.md), its sky of V/I = 2 % seen at plate angles -45 and 45 deg:

    >>> import tempfile, numpy as np, instpol
    >>> tmp = tempfile.TemporaryDirectory()
    >>> inst = f"{tmp.name}/qwp.toml"
    >>> _ = open(inst, "w").write('''name = "TINYQWP"
    ... [detector]
    ... nx = 128
    ... ny = 128
    ... pixel_scale_arcsec = 0.2
    ... gain_e_per_adu = 1.0
    ... read_noise_e = 5.0
    ... saturation_adu = 65535.0
    ... [field]
    ... width_arcmin = 0.4
    ... height_arcmin = 0.4
    ... [polarimetry]
    ... plate = "quarter_wave"
    ... throw_arcsec = 8.0
    ... strip_axis = "y"
    ... strip_count = 1
    ... first_strip_y_px = 20
    ... hwp_angle_keyword = "HWPANG"
    ... filter_keyword = "FILTER"
    ... exptime_keyword = "EXPTIME"
    ... [[filters]]
    ... name = "V"
    ... lambda_eff_nm = 554.0
    ... ''')
    >>> scene = {"instrument": inst, "filter": "V", "hwp_angles_deg": [-45, 45], "seed": 8,
    ...          "sky": {"brightness_e": 4000, "p": 0.03, "chi_deg": 20, "v": 0.02}, "effects": {"photon_noise": True}}
    >>> m = instpol.reduce(instpol.simulate(scene, f"{tmp.name}/frames")["outputs"], inst, bin=8)
    >>> type(m).__name__, m.header["stokes"], m.v.shape
    ('CircularMap', 'V', (14, 16))
    >>> print(f"V/I = {100 * np.median(m.v[m.valid]):.1f} %")
    V/I = 2.0 %
    >>> tmp.cleanup()
    """

    _ARRAYS = (
        "v", "sigma_v", "sigma_v_phot", "n_pixels", "intensity", "intensity_snr", "valid", "x_arcmin", "y_arcmin",
    )

    def __repr__(self) -> str:
        h = self.header
        return (
            f"<instpol.CircularMap {h['instrument']} {h['filter']} V/I: {h['nx']} x {h['ny']} bins of "
            f"{h['bin_px']} px, {int(self.valid.sum())} valid>"
        )


def _paths(frames: Union[PathLike, Sequence[PathLike]]) -> list:
    if isinstance(frames, (str, os.PathLike)):
        frames = [frames]
    return [os.fspath(f) for f in frames]


def _opt_path(p: Optional[PathLike]) -> Optional[str]:
    return None if p is None else os.fspath(p)


def _is_frame_object(f: Any) -> bool:
    return not isinstance(f, (str, os.PathLike))


@contextlib.contextmanager
def _frame_files(frames: Any) -> Iterator[list]:
    """The frames as FITS paths: a path as given; an ``HDUList``, a ``CCDData`` or an
    ``(array, header)`` pair written to a temporary file for the call (the library reads FITS
    files: headers carry the HWP angle, filter and exposure). Errors that name a temporary file
    name the frame's place in the list instead."""
    if isinstance(frames, (str, os.PathLike)) or (isinstance(frames, tuple) and len(frames) == 2 and hasattr(frames[0], "shape")):
        frames = [frames]
    frames = list(frames)
    if not any(_is_frame_object(f) for f in frames):
        yield [os.fspath(f) for f in frames]
        return
    try:
        from astropy.io import fits
    except ImportError:  # pragma: no cover - astropy is what makes such objects
        raise InputError("frames given as objects need astropy installed") from None
    with tempfile.TemporaryDirectory(prefix="instpol-frames-") as tmp:
        paths, names = [], {}
        for i, f in enumerate(frames):
            if not _is_frame_object(f):
                paths.append(os.fspath(f))
                continue
            path = os.path.join(tmp, f"frame_{i:04d}.fits")
            if isinstance(f, fits.HDUList):
                hdul = f
            elif hasattr(f, "to_hdu"):  # CCDData: its data and header, no mask or uncertainty
                hdul = f.to_hdu(hdu_mask=None, hdu_uncertainty=None, hdu_flags=None)
            elif isinstance(f, tuple) and len(f) == 2:
                hdul = fits.HDUList([fits.PrimaryHDU(data=np.asarray(f[0]), header=f[1])])
            else:
                raise InputError(
                    f"frames[{i}]: a {type(f).__name__}; expected a path, an HDUList, a CCDData or (array, header)"
                )
            hdul.writeto(path)
            paths.append(path)
            names[path] = f"frames[{i}] ({type(f).__name__})"
        try:
            yield paths
        except (InputError, FileError) as e:
            msg = str(e)
            for path, name in names.items():
                msg = msg.replace(path, name)
            raise type(e)(msg) from None


#: Units of catalog columns by name (astropy unit strings); a name ending in ``_deg`` is in deg,
#: one ending in ``_arcmin`` in arcmin; the rest are dimensionless fractions or counts.
_COLUMN_UNITS = {"x": "pix", "y": "pix", "x_e": "pix", "y_e": "pix", "fwhm_px": "pix", "aperture_px": "pix",
                 "flux_e": "electron", "a0": "electron"}

#: What a catalog holds once for all its stars (the rest is one value per star).
_CATALOG_META = ("hwp_deg", "filter", "chi_offset_deg", "oe_offset_px", "unpaired", "unpaired_why", "unpaired_shift_px",
                 "n_sources", "warnings", "recorded_angles", "chi_offset_applied_deg", "n_extrapolated",
                 "telescope_model", "telescope_band", "telescope_exposures", "camera_transform",
                 "qwp_zero_angle_deg", "product")


def _unit_of(name: str) -> Optional[str]:
    return _COLUMN_UNITS.get(name) or ("deg" if name.endswith("_deg") else "arcmin" if name.endswith("_arcmin") else None)


def _table(d: Dict[str, Any]) -> Any:
    """A catalog dict as an astropy table (:class:`CatalogTable`): one row per star, each
    column with its unit (:data:`_COLUMN_UNITS`, ``*_deg`` in deg, ``*_arcmin`` in arcmin),
    the catalog-wide values (:data:`_CATALOG_META`) in ``meta``."""
    t = CatalogTable()
    for k, v in d.items():
        if k in _CATALOG_META:
            t.meta[k] = v
            continue
        arr = np.array(v, dtype=object) if isinstance(v, list) and v and isinstance(v[0], list) else np.asarray(v)
        t[k] = arr
        unit = _unit_of(k)
        if unit and arr.dtype.kind in "fi":
            t[k].unit = unit
    return t


try:
    from astropy.table import Table as _AstropyTable

    class CatalogTable(_AstropyTable):
        """The stars of :func:`catalog` as an astropy ``Table``: one row per star, columns with
        their units (``t["x"].unit`` is px, ``t["chi_deg"].unit`` deg; plain arrays in
        arithmetic, as the dict's were), the catalog-wide values in ``meta``. ``t["filter"]``
        and the other catalog-wide keys are looked up in ``meta`` too, so that code written for
        the dict reads a table unchanged; ``QTable(t)`` gives quantities.

        Examples
        --------
        >>> import tempfile, instpol
        >>> tmp = tempfile.TemporaryDirectory()
        >>> scene = {"instrument": "calcite", "filter": "V", "hwp_angles_deg": [0, 22.5, 45, 67.5], "seed": 7,
        ...          "stars": [{"x": 150, "y": 200, "coords": "pixel", "flux_e": 4e5, "p": 0.0572,
        ...                     "chi_deg": 136.0, "fwhm_arcsec": 1.0}], "effects": {"photon_noise": True}}
        >>> frames = instpol.simulate(scene, tmp.name)["outputs"]
        >>> t = instpol.catalog(frames, "calcite", hwp_angles=[0, 22.5, 45, 67.5], aperture=9)
        >>> len(t), str(t["x"].unit), str(t["chi_deg"].unit), t["filter"]
        (1, 'pix', 'deg', 'V')
        >>> tmp.cleanup()
        """

        def __getitem__(self, item: Any) -> Any:
            if isinstance(item, str) and item not in self.colnames and item in self.meta:
                return self.meta[item]
            return super().__getitem__(item)

    _HAVE_ASTROPY = True
except ImportError:  # pragma: no cover - the dict is then what catalog() returns
    CatalogTable = None  # type: ignore[assignment,misc]
    _HAVE_ASTROPY = False


def reduce(
    frames: Union[PathLike, Sequence[PathLike]],
    instrument: Optional[str] = None,
    *,
    bin: int = 30,
    nsigma: float = 3.0,
    allow_incomplete: bool = False,
    bias: Optional[PathLike] = None,
    flat: Optional[PathLike] = None,
    hwp_angles: Optional[Sequence[float]] = None,
    assembled: bool = False,
    output: Optional[PathLike] = None,
    correct_again: bool = False,
) -> Union[StokesMap, CircularMap]:
    """Reduce dual-beam frames (one filter, N HWP angles) to a binned Stokes map, as ``instpol
    reduce``: per pixel F_i (Eq. 5 [eq:F]) and Q/I, U/I (Eq. 7 [eq:Q], Eq. 8 [eq:U]) from the
    ordinary and extraordinary images of every mask strip, then a sigma-clipped mean per ``bin``
    x ``bin`` px bin. For an instrument with a quarter-wave plate (``plate = "quarter_wave"``)
    the result is a :class:`CircularMap` of V/I instead (the circular demodulation of
    ``stokes::circular`` in place of Eq. 7 [eq:Q], Eq. 8 [eq:U]). ``frames``: paths of FITS
    files, or astropy ``HDUList``, ``CCDData`` or ``(array, header)`` objects (written to
    temporary FITS files for the call: the headers must carry what a file's would, the HWP
    angle, filter and exposure time, or give ``hwp_angles``). ``instrument``: a built-in name or
    an instrument TOML file; ``bias``, ``flat``: master frames; ``bin``: the bin side (px);
    ``nsigma``: the clipping threshold (robust standard deviations); ``hwp_angles``: degrees per
    frame for headers without the keyword; ``assembled=True``: frames already trimmed and
    assembled by another pipeline (bias-subtracted, one detector-sized image each), for an
    instrument whose raw frames are chip files (FORS2, EFOSC2); ``output``: also write the FITS
    map there (atomically); ``correct_again=True``: apply ``bias``/``flat`` to frames the
    instrument file declares already corrected (``[format] already_corrected``, level-1 frames;
    refused otherwise, naming the option).

    Raises
    ------
    FileError
        A frame, master or the output cannot be read or written.
    InputError
        An incomplete angle set, mixed filters or sizes, a missing header keyword, a maskless
        instrument (its beams' skies overlap), a bin side out of range.

    Returns
    -------
    StokesMap or CircularMap
        (ny, nx) arrays of the bins: fractions for q, u, p and their errors, degrees for chi.

    Examples
    --------
    Four simulated FORS1 frames of a sky polarized as the paper's V empty field (P = 1.74 %,
    chi = -53.8 deg, Table 1 [tab:empty]) and no instrumental polarization: the map's bins give
    the sky back (chi in [0, 180)).

    >>> import tempfile, numpy as np, instpol
    >>> tmp = tempfile.TemporaryDirectory()
    >>> scene = {"instrument": "fors1", "filter": "V", "hwp_angles_deg": [0, 22.5, 45, 67.5],
    ...          "sky": {"brightness_e": 12000, "p": 0.0174, "chi_deg": -53.8},
    ...          "effects": {"photon_noise": True, "read_noise": True}}
    >>> frames = instpol.simulate(scene, tmp.name)["outputs"]
    >>> m = instpol.reduce(frames, instrument="fors1", bin=30)
    >>> print(f"{m.header['nx']} x {m.header['ny']} bins, median P = {100 * np.median(m.p[m.valid]):.2f} %, "
    ...       f"chi = {np.median(m.chi_deg[m.valid]):.1f} deg")
    69 x 68 bins, median P = 1.74 %, chi = 126.2 deg
    >>> tmp.cleanup()
    """
    if isinstance(bin, bool) or not isinstance(bin, (int, np.integer)) or bin < 0:
        raise InputError(f"bin {bin!r}: expected a bin side in pixels (a positive integer)")
    with _frame_files(frames) as paths:
        d = _instpol._reduce(
            paths, None if instrument is None else str(instrument), int(bin), float(nsigma), bool(allow_incomplete), _opt_path(bias),
            _opt_path(flat), None if hwp_angles is None else [float(a) for a in hwp_angles], bool(assembled),
            _opt_path(output), correct_again=bool(correct_again),
        )
    return CircularMap(d) if d["header"].get("stokes") == "V" else StokesMap(d)


def catalog(
    frames: Union[PathLike, Sequence[PathLike]],
    instrument: Optional[str] = None,
    *,
    fwhm: float = 4.0,
    threshold: float = 5.0,
    aperture: Union[float, str] = 8.0,
    annulus: Tuple[float, float] = (12.0, 20.0),
    bias: Optional[PathLike] = None,
    flat: Optional[PathLike] = None,
    hwp_angles: Optional[Sequence[float]] = None,
    assembled: bool = False,
    kappa: Optional[float] = None,
    kappa_from_data: bool = False,
    pair_tol: float = 1.5,
    cal: Optional[PathLike] = None,
    allow_extrapolation: bool = False,
    force: bool = False,
    as_table: Optional[bool] = None,
    correct_again: bool = False,
) -> Any:
    """Every paired star of a frame set measured, as ``instpol catalog``: detection on the first
    frame, ordinary/extraordinary pairing through the instrument's beam layout, aperture
    photometry per frame with the background removed in each beam, then Q/I, U/I, P, chi (Eq. 7
    [eq:Q], Eq. 8 [eq:U], Eq. 1 [eq:poldeg], Eq. 2 [eq:polang]) with propagated and
    scatter-based errors and flags.

    The stars' columns (one value per star: ``id, x, y, x_e, y_e, x_arcmin, y_arcmin,
    fwhm_px, aperture_px, flux_e, q, u, sigma_q, sigma_u, cov_qu, p, sigma_p, chi_deg, sigma_chi_deg, a0,
    kappa, kappa_applied, chi2_mod, dof_mod, sigma_q_scatter, sigma_u_scatter, flags, flag_names, note``,
    with ``ra_deg, dec_deg`` when the frames carry a celestial WCS, and ``f`` of shape (stars, N)) and metadata (``hwp_deg, filter, chi_offset_deg, oe_offset_px,
    unpaired, unpaired_why, unpaired_shift_px, n_sources, warnings``, and ``recorded_angles``: the exposures'
    telescope angles from their headers, ``{"parang_deg": (start, end), "rotator_deg": ...,
    "exposures": [(hwp_deg, start_deg, end_deg), ...], "hwp_chi_offset_deg": ...}`` (the last:
    the HWP zero angle the stars' q, u carry, ``chi_offset_deg``), or None when the instrument
    names no header keyword for them; :meth:`Calibration.correct` takes it as ``recorded``).

    ``fwhm``: the stars' expected FWHM (px) for detection; ``threshold``: the detection
    threshold (standard deviations of the filtered image's noise); ``annulus``: the background
    annulus's inner and outer radii (px); ``kappa``: a dimensionless ratio, (t - s)/(t + s).
    ``aperture``: a radius in px, ``"2.5fwhm"`` (a multiple of each star's FWHM) or ``"best"``
    (the radius of best S/N on each star's curve of growth). ``kappa`` applies a known Wollaston
    imbalance; ``kappa_from_data=True`` estimates it per star (Eq. 15 [eq:kappa2]) and applies it.
    ``pair_tol``: how far (px) a detected e image may sit from where the instrument's o/e offset
    puts it (a warning gives the shift when many sit further off, e.g. another filter's throw).
    ``assembled=True``: frames already trimmed and assembled (as for :func:`reduce`).
    ``correct_again=True``: give ``bias``/``flat`` to frames the instrument declares already
    corrected (level-1 frames; refused otherwise, as for :func:`reduce`).

    ``frames``: paths of FITS files, or astropy ``HDUList``, ``CCDData`` or ``(array, header)``
    objects (as for :func:`reduce`). Returned, where astropy is installed (``as_table=None``, the
    default, or ``True``), as a :class:`CatalogTable`: an astropy ``Table``, one row per star,
    columns with their units (px, arcmin, deg, electrons; q, u, P fractions), the catalog-wide
    values in ``meta`` and also by key (``t["filter"]``); ``as_table=False``: the dict below.

    ``force=True``: measure the stars even when the photometry is estimated beyond 2e10 pixel
    visits (stars x frames x the annulus's area; a threshold far below the noise or a huge
    annulus is refused with the estimate otherwise).

    With an instrument whose plate is a quarter-wave plate (``plate = "quarter_wave"``) the
    stars' V/I is measured instead: columns ``v, sigma_v`` (fractions, IAU sign) and the
    catalog-wide ``qwp_zero_angle_deg``; the linear columns are NaN and ``cal`` is refused.

    ``cal``: a calibration file to remove the instrumental polarization with in the same run, as
    ``instpol catalog --cal``: adds the columns ``q0, u0, sigma_q0, sigma_u0, cov_qu0, p0,
    sigma_p0, chi0_deg, sigma_chi0_deg, q_inst, u_inst, extrapolated`` and ``chi_offset_applied_deg,
    n_extrapolated, telescope_model, telescope_band, telescope_exposures``. A telescope model in
    it is undone after the field exposure by exposure, each over its own parallactic track from
    the frames' headers. ``allow_extrapolation``: correct stars outside the calibrated field
    too (flagged, errors inflated).

    Raises
    ------
    FileError, InputError
        As :func:`reduce`; also an ``annulus`` that is not two radii in px, an unknown
        ``aperture``.

    Examples
    --------
    A 5.72 % star at chi = 136 deg simulated through the maskless calcite example instrument at
    eight HWP angles (its headers carry no angle: ``hwp_angles`` gives them), measured with an
    aperture of 9 px; its P lies within 3 sigma of the truth:

    >>> import tempfile, instpol
    >>> tmp = tempfile.TemporaryDirectory()
    >>> angles = [0, 22.5, 45, 67.5, 90, 112.5, 135, 157.5]
    >>> scene = {"instrument": "calcite", "filter": "V", "hwp_angles_deg": angles, "seed": 7,
    ...          "sky": {"brightness_e": 300},
    ...          "stars": [{"x": 150, "y": 200, "coords": "pixel", "flux_e": 4e5, "p": 0.0572,
    ...                     "chi_deg": 136.0, "fwhm_arcsec": 1.0}],
    ...          "effects": {"photon_noise": True, "read_noise": True}}
    >>> frames = instpol.simulate(scene, tmp.name)["outputs"]
    >>> cat = instpol.catalog(frames, "calcite", hwp_angles=angles, aperture=9, annulus=(14, 24))
    >>> star = cat[0]
    >>> print(f"P = {100 * star['p']:.1f} %", abs(star["p"] - 0.0572) < 3 * star["sigma_p"], star["flags"])
    P = 5.7 % True 0
    >>> tmp.cleanup()
    """
    try:
        r_in, r_out = (float(a) for a in annulus)
    except (TypeError, ValueError):
        raise InputError(f"annulus {annulus!r}: expected two radii in px, e.g. (12, 20)") from None
    with _frame_files(frames) as paths:
        d = _instpol._catalog(
            paths, None if instrument is None else str(instrument), float(fwhm), float(threshold), str(aperture), (r_in, r_out),
            _opt_path(bias), _opt_path(flat), None if hwp_angles is None else [float(a) for a in hwp_angles],
            bool(assembled), None if kappa is None else float(kappa), bool(kappa_from_data), float(pair_tol),
            _opt_path(cal), bool(allow_extrapolation), bool(force), correct_again=bool(correct_again),
        )
    if as_table is None:
        as_table = _HAVE_ASTROPY
    if as_table and not _HAVE_ASTROPY:
        raise InputError("as_table=True needs astropy installed")
    return _table(d) if as_table else d


def calibrate(
    map: PathLike,
    sky_p_percent: float,
    sky_chi_deg: float,
    instrument: Optional[str] = None,
    *,
    out: Optional[PathLike] = None,
    model: str = "radial3",
    include_c0: bool = False,
    free_centre: bool = False,
    exclude: Sequence[str] = (),
    residual_map: bool = False,
) -> Dict[str, Any]:
    """The instrumental polarization over the field from a Stokes map of an empty field whose
    sky polarization is known, as ``instpol calibrate --map``: the paper's sky-field method
    (section 10 [sec:instr]). In each bin the measured Stokes vector is the sky's seen through the
    instrument's M_I, so Eq. 17 [eq:instpol] is solved exactly for p and phi (the
    first-order Eq. 18 [eq:approx] kept for comparison); the bins' instrumental (q, u) are then
    fitted by robust weighted least squares with the radial model p(r) = sum_k c_k r^k (r in
    arcmin, the paper's third-degree polynomial by default) and the polar-angle test is run.

    Parameters
    ----------
    map : path
        A Stokes map file from :func:`reduce` (``output=``) or ``instpol reduce`` (not yet
        corrected), in the plate frame: the filter's HWP zero angle is applied here.
    sky_p_percent : float
        The sky's polarization degree in PERCENT (Table 1 [tab:empty]: B 6.45, V 1.74, I 1.34).
    sky_chi_deg : float
        The sky's polarization angle (deg, any sign, taken modulo 180).
    instrument : str, optional
        A built-in name or an instrument file; None: the one the map's ``INSTRUME`` names.
    out : path, optional
        Write the calibration file (FITS) there, readable by :meth:`Calibration.load`.
    model : str
        ``"radialN"`` (a polynomial of degree N in r about the optical axis), ``"polyN"`` (of
        total degree N in x and y for each of q and u) or ``"plane"``.
    include_c0, free_centre : bool
        Fit a constant term c_0 too; fit the optical-axis centre (arcmin) instead of fixing it
        at the detector centre.
    exclude : list of str
        Parts of the field left out: ``"sector:FROM:TO"`` (polar angle, deg), ``"ring:R0:R1"``
        or ``"box:X0:X1:Y0:Y1"`` (arcmin).
    residual_map : bool
        Keep an interpolant of the residuals in the model (fields that are not radial).

    Returns
    -------
    dict
        ``instpol calibrate --json``'s keys less ``provenance``: ``coefficients`` c_k and
        ``sigma_coefficients`` (fractions per arcmin^k, for the ``powers`` k),
        ``centre_arcmin``, ``rms_residual`` (fraction per component), ``chi2_dof``, the
        polar-angle test (``polar_angle_slope``, ...), ``output`` (the calibration file).

    Raises
    ------
    InputError
        A sky polarization that is not a number, an unknown model or exclusion, a map that was
        corrected already, too few valid bins.
    FileError
        The map cannot be read or ``out`` written.

    Examples
    --------
    The paper's V field (section 11 [sec:fors1]: p(r) = 0.012 r + 0.046 r^2 + 0.002 r^3 %, phi the
    polar angle) in simulated frames of its empty field (P_sky = 1.74 %, chi_sky = -53.8 deg),
    reduced, then calibrated: the fit gives back the polynomial's coefficients within their
    errors, and p(3') = 0.50 %:

    >>> import tempfile, numpy as np, instpol
    >>> scene = {"instrument": "fors1", "filter": "V", "seed": 102,
    ...          "sky": {"brightness_e": 12000, "p": 0.0174, "chi_deg": -53.8},
    ...          "effects": {"instpol": {"kind": "radial", "coeffs_percent": [0, 0.012, 0.046, 0.002]},
    ...                      "photon_noise": True, "read_noise": True}}
    >>> tmp = tempfile.TemporaryDirectory()
    >>> d = tmp.name
    >>> frames = instpol.simulate(scene, f"{d}/frames")["outputs"]
    >>> _ = instpol.reduce(frames, "fors1", output=f"{d}/map_V.fits")
    >>> fit = instpol.calibrate(f"{d}/map_V.fits", 1.74, -53.8, "fors1", out=f"{d}/cal_V.fits")
    >>> paper = [0.012e-2, 0.046e-2, 0.002e-2]
    >>> all(abs(c - t) < 3 * e for c, t, e in zip(fit["coefficients"], paper, fit["sigma_coefficients"]))
    True
    >>> e = instpol.Calibration.load(f"{d}/cal_V.fits").evaluate(3.0, 0.0)
    >>> print(f"p(3') = {100 * np.hypot(e['q'], e['u']):.2f} %")
    p(3') = 0.50 %
    >>> tmp.cleanup()
    """
    return json.loads(
        _instpol._calibrate(
            os.fspath(map), None if instrument is None else str(instrument), (float(sky_p_percent), float(sky_chi_deg)),
            str(model), bool(include_c0), bool(free_centre), [str(e) for e in exclude], bool(residual_map), _opt_path(out),
        )
    )


def calibrate_stars(
    catalogs: Union[PathLike, Sequence[PathLike]],
    instrument: Optional[str] = None,
    *,
    filter: str,
    out: Optional[PathLike] = None,
    interstellar: Union[str, Tuple[float, float]] = "free",
    offsets: Optional[Sequence[Tuple[float, float]]] = None,
    model: str = "radial3",
    free_centre: bool = False,
    reject_alpha: float = 1e-3,
    match_radius_arcsec: float = 1.0,
    allow_mismatch: bool = False,
) -> Dict[str, Any]:
    """The instrumental field from field stars, as ``instpol calibrate-stars``.

    ``instrument``: a built-in name or an instrument file; None: the built-in one the
    catalogs' keywords say (``INSTRUME``), else FORS1, each with a warning. A catalog whose
    keywords say another instrument or filter than ``instrument``, ``filter`` raises InputError
    naming both, unless ``allow_mismatch``.

    ``catalogs``: the star catalogs ``catalog(..., out=)`` or ``instpol catalog --out`` wrote,
    one per dithered pointing of a dense field. Each star's measured ``q, u`` is the
    instrument's field at its detector position plus one interstellar polarization common to
    the stars: ``interstellar="free"`` (fitted), ``"zero"``, or ``(P_percent, chi_deg)``.
    ``offsets``: each pointing's ``(dx, dy)`` in arcmin (the first ``(0, 0)``); None measures
    them from the stars the catalogs share. ``model``: ``"radialN"``, ``"polyN"`` or ``"plane"``
    (a plane needs the interstellar term fixed: its constant and a free interstellar term are
    the same at every position). Stars polarized in themselves are rejected by their residual
    chi^2 at the false-rejection probability ``reject_alpha`` and named.

    Returns
    -------
    dict
        ``instpol calibrate-stars --json``'s keys (``fit``, ``interstellar``, ``rejected``,
        ``offsets_arcmin``, ...) with the same numbers, less ``provenance`` and the plots; the
        calibration is written to ``out`` when given (the file ``calibrate`` writes, ``IP
        SOURCE = field stars``), readable by :meth:`Calibration.load`.

    Raises
    ------
    FileError, InputError

    Examples
    --------
    Catalogs of two dithered pointings (0 and (0.6', 0.3')) of 49 unpolarized stars on a grid,
    written here as CSV tables with numpy (q, u in the sky frame: the HWP zero angle they carry,
    ``hwp_chi_offset_deg``, is 0), each star's measured (q, u) the instrument's plane
    field q = 0.10 % + 0.03 % x, u = -0.04 % + 0.025 % y (x, y in arcmin on the detector); the
    fit gives the plane's coefficients back (in %, for the terms 1, x, y):

    >>> import tempfile, numpy as np, instpol
    >>> tmp = tempfile.TemporaryDirectory()
    >>> gx, gy = np.meshgrid(np.linspace(-2.4, 2.4, 7), np.linspace(-2.4, 2.4, 7))
    >>> files = []
    >>> for k, (dx, dy) in enumerate([(0.0, 0.0), (0.6, 0.3)]):
    ...     x, y = gx.ravel() - dx, gy.ravel() - dy
    ...     q, u = 1e-3 + 3e-4 * x, -4e-4 + 2.5e-4 * y
    ...     rows = np.column_stack([np.arange(1, 50), x, y, q, u, np.full(49, 5e-4), np.full(49, 5e-4), np.zeros(49)])
    ...     files.append(f"{tmp.name}/p{k}.csv")
    ...     np.savetxt(files[-1], rows, delimiter=",", fmt="%.10g", comments="",
    ...                header="id,x_arcmin,y_arcmin,q,u,sigma_q,sigma_u,hwp_chi_offset_deg")
    >>> s = instpol.calibrate_stars(files, "fors1", filter="V", model="plane", interstellar="zero",
    ...                             offsets=[(0, 0), (0.6, 0.3)], out=f"{tmp.name}/cal_plane.fits")
    >>> print(np.round(100 * np.array(s["poly"]["q"]), 4), np.round(100 * np.array(s["poly"]["u"]), 4))
    [0.1  0.03 0.  ] [-0.04   0.     0.025]
    >>> tmp.cleanup()
    """
    cats = [catalogs] if isinstance(catalogs, (str, os.PathLike)) else list(catalogs)
    free, given = False, None
    if isinstance(interstellar, str):
        name = interstellar.strip().lower()
        if name == "free":
            free = True
        elif name not in ("zero", "none"):
            raise InputError(f"interstellar {interstellar!r}: expected 'free', 'zero' or (P_percent, chi_deg)")
    else:
        try:
            p, chi = (float(v) for v in interstellar)
        except (TypeError, ValueError):
            raise InputError(f"interstellar {interstellar!r}: expected 'free', 'zero' or (P_percent, chi_deg)") from None
        given = (p, chi)
    offs = None
    if offsets is not None:
        try:
            offs = [(float(a), float(b)) for a, b in offsets]
        except (TypeError, ValueError):
            raise InputError(f"offsets {offsets!r}: expected one (dx, dy) in arcmin per catalog") from None
        if len(offs) != len(cats):
            raise InputError(f"{len(offs)} offsets for {len(cats)} catalogs: give one per catalog, (0, 0) for the first")
    return json.loads(
        _instpol._calibrate_stars(
            [os.fspath(c) for c in cats], None if instrument is None else str(instrument), str(filter), _opt_path(out), free, given, offs,
            str(model), bool(free_centre), float(reject_alpha), float(match_radius_arcsec), bool(allow_mismatch),
        )
    )


def demo(out_dir: PathLike, *, frames: bool = True, keep_frames: bool = False, seed: int = 2006) -> Dict[str, Any]:
    """The main job end to end on the paper's three empty fields, as ``instpol demo``.

    The paper's FORS1 fields (section 11 [sec:fors1]: V and I as fitted there, B scaled from V by
    the wavelength law with an asymmetric component) are seen on the empty fields of Table 1
    [tab:empty]: through simulated frames (photon and read noise) reduced in 30 x 30 px bins, or
    with ``frames=False`` as binned maps measured directly through the same M_I (fast). Each
    filter is calibrated by the sky-field method (``out_dir/cal_<filter>.fits``), the
    wavelength law is fitted, and the V calibration is validated on a simulated unpolarized
    standard in the lower-right corner (the paper's check). ``keep_frames`` keeps the
    simulated frames in ``out_dir``. The same library call as the CLI's.

    Returns
    -------
    dict
        The report of ``instpol demo --json`` (``filters``, ``wavelength_law``, ``validation``,
        ``through_frames``, ``output``) with the same numbers, less the CLI's ``provenance``;
        no plots are drawn, so each filter's ``plot_outputs`` is empty.

    Raises
    ------
    FileError
        ``out_dir`` cannot be created or written.

    Examples
    --------
    The V field's fitted polynomial (%, for r, r^2, r^3 with r in arcmin) against the paper's
    (section 11 [sec:fors1]: 0.012, 0.046, 0.002), and the check on the corner star: its measured P
    against the P the calibration predicts there, in units of its error (a pull):

    >>> import tempfile, instpol
    >>> tmp = tempfile.TemporaryDirectory()
    >>> r = instpol.demo(tmp.name, frames=False)
    >>> v = next(f for f in r["filters"] if f["filter"] == "V")
    >>> print([round(100 * c, 3) for c in v["input_coefficients"]], [round(100 * c, 3) for c in v["fitted_coefficients"]])
    [0.012, 0.046, 0.002] [0.011, 0.047, 0.002]
    >>> abs(r["validation"]["pull"]) < 3
    True
    >>> tmp.cleanup()
    """
    return json.loads(_instpol._demo(os.fspath(out_dir), bool(frames), bool(keep_frames), int(seed)))


def _first_non_finite(v: Any, key: str) -> Optional[Tuple[str, float]]:
    """The dotted key and value of the first float of a nested table that is NaN or infinite."""
    if isinstance(v, float) and not np.isfinite(v):
        return key, v
    items = v.items() if isinstance(v, dict) else enumerate(v) if isinstance(v, (list, tuple)) else ()
    for k, w in items:
        found = _first_non_finite(w, f"{key}.{k}" if key else str(k))
        if found is not None:
            return found
    return None


def simulate(
    scene: Union[PathLike, Dict[str, Any]],
    out: PathLike,
    *,
    field: Optional[PathLike] = None,
    force: bool = False,
) -> Dict[str, Any]:
    """Raw-like dual-beam frames of a scene, as ``instpol simulate``: one FITS file per HWP
    angle in ``out`` (created if needed), with the detector, the mask strips, the ordinary and
    extraordinary images and the header keywords the instrument describes, and ``truth.json``
    with every input. Each beam's flux follows Eq. 4 [eq:ord] through the instrument's optics,
    so the frames reduce to the scene's polarization by Eq. 5 [eq:F], Eq. 7 [eq:Q] and Eq. 8
    [eq:U]; only the effects the scene's ``effects`` table lists are computed (photon and read
    noise, an instrumental field ``instpol`` seen through Eq. 17 [eq:instpol], a Wollaston
    imbalance as Eq. 12 [eq:WP], ...).

    Parameters
    ----------
    scene : path or dict
        A scene file (TOML; instruments/scenes/ has examples) or the same table as a dict:
        ``instrument`` (a built-in name or an instrument file), ``filter``, ``hwp_angles_deg``
        (deg), ``exposure_s`` (s), ``seed``, ``sky`` (``brightness_e``: e- per pixel per
        exposure, ``p``: a fraction, ``chi_deg``: deg), ``stars`` (``x``, ``y`` in px or arcmin
        as ``coords`` says, ``flux_e``: e- per exposure, ``p``, ``chi_deg``, ``fwhm_arcsec``),
        ``effects``, ``output``. Fluxes are electrons per exposure, polarization degrees
        fractions, angles degrees. A dict's file paths are taken as they are; a file's are
        relative to it.
    out : path
        The output folder; a frame never lands on the scene, its instrument file or ``field``.
    field : path, optional
        A calibration file (of the scene's instrument and filter) whose model replaces the
        scene's ``effects.instpol``, as ``instpol simulate --field``.
    force : bool
        Write the frames even when they take more than 16 GB.

    Returns
    -------
    dict
        ``outputs`` (the frame files, in HWP-angle order), ``truth_output`` (``truth.json``)
        and, for chip instruments whose bias no overscan removes, ``bias_outputs``: the keys of
        ``instpol simulate --json`` less ``provenance``.

    Raises
    ------
    InputError
        A scene that is not valid (an unknown key, a value out of range), a calibration of
        another instrument or filter, frames beyond 16 GB without ``force``.
    FileError
        ``out`` cannot be created or written.

    Examples
    --------
    Four frames of an empty FORS1 field in V whose sky is polarized as the paper's V field
    (Table 1 [tab:empty]: P = 1.74 %, chi = -53.8 deg):

    >>> import os, tempfile, instpol
    >>> scene = {"instrument": "fors1", "filter": "V", "hwp_angles_deg": [0, 22.5, 45, 67.5],
    ...          "sky": {"brightness_e": 12000, "p": 0.0174, "chi_deg": -53.8},
    ...          "effects": {"photon_noise": True, "read_noise": True}}
    >>> with tempfile.TemporaryDirectory() as d:
    ...     w = instpol.simulate(scene, d)
    ...     print(len(w["outputs"]), os.path.basename(w["truth_output"]))
    4 truth.json
    """
    if isinstance(scene, dict):
        bad = _first_non_finite(scene, "")
        if bad is not None:
            raise InputError(f"scene: {bad[0]} = {bad[1]}: not a finite number")
        try:
            text = json.dumps(scene)
        except (TypeError, ValueError) as e:
            raise InputError(f"scene: not a table of numbers, strings, lists and tables ({e})") from None
        label = "<scene dict>"
    else:
        label, text = os.fspath(scene), None
    return json.loads(_instpol._simulate(label, text, os.fspath(out), _opt_path(field), bool(force)))


def scan(
    dirs: Union[PathLike, Sequence[PathLike]],
    instrument: str,
    products: PathLike,
    *,
    sky: Optional[Union[Dict[str, Tuple[float, float]], PathLike]] = None,
    standards: Optional[PathLike] = None,
    pointing_tol_arcsec: float = 60.0,
    max_gap_min: float = 60.0,
    bin: int = 30,
    fwhm: float = 4.0,
    aperture: float = 8.0,
    out: Optional[PathLike] = None,
) -> Dict[str, Any]:
    """Sort folders of raw files by their headers into a plan of work, as ``instpol scan``.

    Units: ``pointing_tol_arcsec`` (arcsec: exposures this close are one pointing),
    ``max_gap_min`` (minutes: a longer gap starts a new set), ``bin``, ``fwhm``, ``aperture``
    (px, the options of the units' ``reduce`` and ``catalog``); ``sky`` values (percent, deg).

    Every file is classified from its headers alone (the instrument file's ``[headers]``
    table): bias, flat, polarimetric exposure or standard, or left out with the reason. Chip
    files of one exposure are grouped, exposures into complete HWP sets (repeated cycles kept),
    masters matched by night, binning and filter, standards matched to the standards list by
    name or position. ``sky`` maps a sky field's target name to its known polarization
    ``(p_percent, chi_deg)``: its map is calibrated; or it names a table (CSV, ECSV, FITS,
    VOTable) with the columns ``target``, ``p_percent``, ``chi_deg``, as ``instpol scan
    --sky-table``. The products go under ``products``.

    Returns
    -------
    dict
        The plan (``version``, ``instrument``, ``records``, ``units``, ``files``,
        ``left_out``): the keys of ``instpol scan --json`` less ``provenance``. Filter or edit
        it (drop units, change a command's options) and hand it to :func:`run`. ``out``:
        also written there (TOML, or JSON for a ``.json`` name), as the CLI writes it.

    Examples
    --------
    A folder holding the raw chip files of one FORS2 empty-field set (simulated with the ESO
    archive's names and DPR keywords), whose sky polarization is known: the plan reduces the
    set to a map, then calibrates the instrument on it.

    >>> import tempfile, instpol
    >>> tmp = tempfile.TemporaryDirectory()
    >>> keys = {"HIERARCH ESO DPR CATG": "SCIENCE", "HIERARCH ESO DPR TYPE": "OBJECT",
    ...         "HIERARCH ESO DPR TECH": "POLARIMETRY", "HIERARCH ESO OBS TARG NAME": "EMPTY V",
    ...         "RA": 10.0, "DEC": -20.0}
    >>> scene = {"instrument": "fors2", "filter": "v_HIGH", "seed": 3,
    ...          "sky": {"brightness_e": 12000, "p": 0.0174, "chi_deg": -53.8},
    ...          "output": {"archive": {"start_mjd": 58546.9, "cadence_s": 60}, "keywords": keys},
    ...          "effects": {"photon_noise": True, "read_noise": True}}
    >>> len(instpol.simulate(scene, f"{tmp.name}/raw")["outputs"])
    8
    >>> plan = instpol.scan(f"{tmp.name}/raw", "fors2", f"{tmp.name}/products", sky={"EMPTY V": (1.74, -53.8)})
    >>> [u["id"] for u in plan["units"]]
    ['reduce-20190304-EMPTY_V-v_HIGH', 'calibrate-20190304-EMPTY_V-v_HIGH']
    >>> tmp.cleanup()
    """
    sky_list, sky_table = [], None
    if isinstance(sky, (str, os.PathLike)):
        sky_table, sky = os.fspath(sky), None
    for target, value in (sky or {}).items():
        try:
            p, chi = value
            sky_list.append((str(target), float(p), float(chi)))
        except (TypeError, ValueError):
            raise InputError(f"sky[{target!r}] = {value!r}: expected (p_percent, chi_deg)") from None
    return json.loads(
        _instpol._scan(
            _paths(dirs), str(instrument), os.fspath(products), sky_list, sky_table, _opt_path(standards),
            float(pointing_tol_arcsec), float(max_gap_min), int(bin), float(fwhm), float(aperture), _opt_path(out),
        )
    )


def _instpol_binary(instpol_bin: Optional[PathLike]) -> Optional[str]:
    import shutil

    if instpol_bin is not None:
        if not os.path.isfile(os.fspath(instpol_bin)):
            raise InputError(f"instpol_bin {os.fspath(instpol_bin)!r}: no such file")
        return os.fspath(instpol_bin)
    b = os.environ.get("INSTPOL_BIN") or shutil.which("instpol")
    return os.fspath(b) if b is not None and os.path.isfile(os.fspath(b)) else None


def run(
    plan: Union[Dict[str, Any], PathLike],
    *,
    jobs: int = 1,
    units: Optional[Sequence[str]] = None,
    dry_run: bool = False,
    instpol_bin: Optional[PathLike] = None,
) -> Dict[str, Any]:
    """Run a plan from :func:`scan` (a dict, edited or not, or a plan file), as ``instpol run``.
    ``jobs``: how many units run at once (a count).

    Units run in dependency order, ``jobs`` at once; a unit whose record says its inputs and
    outputs are unchanged is skipped; a failing unit is reported and the units that follow it
    are blocked, the others run. ``units``: only these ids and what they follow. Each unit runs
    in process through the library calls the CLI's commands make, so the products are those of
    the CLI and no binary is needed for masters, maps, catalogs and calibrations; a command the
    library runner does not know whole (``zero-angle``, ``photometry``, ``fit-standards``,
    ``validate``, or an option added to a plan by hand) runs the ``instpol`` binary
    (``instpol_bin``, else ``$INSTPOL_BIN``, else the one on ``PATH``), and fails saying so when
    there is none.

    Returns
    -------
    dict
        The report (``outcomes``: ``id``, ``kind``, ``status`` of ``done``, ``up_to_date``,
        ``would_run``, ``failed``, ``blocked`` or ``check_failed``, ``reason``, ``seconds``): the keys of
        ``instpol run --json`` less ``provenance``.

    Examples
    --------
    The plan of :func:`scan`'s example run in process, then
    run again: the second run finds every product up to date.

    >>> import tempfile, instpol
    >>> tmp = tempfile.TemporaryDirectory()
    >>> keys = {"HIERARCH ESO DPR CATG": "SCIENCE", "HIERARCH ESO DPR TYPE": "OBJECT",
    ...         "HIERARCH ESO DPR TECH": "POLARIMETRY", "HIERARCH ESO OBS TARG NAME": "EMPTY V",
    ...         "RA": 10.0, "DEC": -20.0}
    >>> scene = {"instrument": "fors2", "filter": "v_HIGH", "seed": 3,
    ...          "sky": {"brightness_e": 12000, "p": 0.0174, "chi_deg": -53.8},
    ...          "output": {"archive": {"start_mjd": 58546.9, "cadence_s": 60}, "keywords": keys},
    ...          "effects": {"photon_noise": True, "read_noise": True}}
    >>> _ = instpol.simulate(scene, f"{tmp.name}/raw")
    >>> plan = instpol.scan(f"{tmp.name}/raw", "fors2", f"{tmp.name}/products", sky={"EMPTY V": (1.74, -53.8)})
    >>> [(o["kind"], o["status"]) for o in instpol.run(plan)["outcomes"]]
    [('reduce', 'done'), ('calibrate', 'done')]
    >>> [o["status"] for o in instpol.run(plan)["outcomes"]]
    ['up_to_date', 'up_to_date']
    >>> tmp.cleanup()
    """
    text, path = (json.dumps(plan), None) if isinstance(plan, dict) else (None, os.fspath(plan))
    only = None if units is None else [str(u) for u in units]
    return json.loads(_instpol._run(text, path, int(jobs), only, bool(dry_run), _instpol_binary(instpol_bin)))

