"""instpol.stokes against `instpol stokes --json` (same input, same numbers to the last bit) and
against a numpy implementation of eq:F, eq:Q, eq:U written here."""

import numpy as np
import pytest

import instpol
from conftest import ROOT, key, num, same

DATA = ROOT / "tests" / "data"


def read_csv(path):
    """hwp_deg, f_o, f_e, (sigma_o, sigma_e) of an `instpol stokes` input (# comments)."""
    lines = [l for l in open(path) if l.strip() and not l.startswith("#")]
    head = lines[0].strip().split(",")
    t = {h: np.array([float(l.split(",")[i]) for l in lines[1:]]) for i, h in enumerate(head)}
    sig = (t["sigma_o"], t["sigma_e"]) if "sigma_o" in t else (None, None)
    return t["hwp_deg"], t["f_o"], t["f_e"], sig


SCALARS = ["q", "u", "p", "chi_deg", "sigma_p", "sigma_chi_deg", "a0", "mean_kappa", "sigma_q", "sigma_u",
           "cov_qu", "snr", "sigma_p_analytic", "sigma_chi_analytic_deg", "sigma_a0"]


def compare_with_cli(py, j):
    for k in SCALARS:
        assert same(py[k], num(key(j, k))), (k, py[k], key(j, k))
    assert py["n_hwp"] == key(j, "n_hwp")
    assert py["chi_defined"] == key(j, "chi_defined")
    assert py["estimator"] == key(j, "estimator")
    assert py["warnings"] == key(j, "warnings")
    for k in ["f", "sigma_f", "kappa"]:
        assert same(py[k], num(key(j, k))), k
    four = key(j, "fourier")
    assert py["fourier"]["k"] == [h["k"] for h in four]
    for k in ["a", "b", "sigma_a", "sigma_b", "power"]:
        assert same(py["fourier"][k], [h[k] for h in four]), k


@pytest.mark.parametrize("name", ["example_n4.csv", "fors1_v_star_n16.csv"])
def test_stokes_matches_cli_json(run_json, name):
    hwp, fo, fe, (so, se) = read_csv(DATA / name)
    j = run_json("stokes", "--input", DATA / name)
    compare_with_cli(instpol.stokes(hwp, fo, fe, so, se), j)


def test_stokes_kappa_and_least_squares_match_cli(run_json, tmp_path):
    """A non-optimal angle set (weighted least squares) with explicit errors and --kappa."""
    hwp = np.array([0.0, 30.0, 50.0, 80.0, 100.0])
    rng = np.random.default_rng(3)
    fo = 1e5 * (1 + 0.03 * np.cos(np.radians(4 * hwp - 40))) + rng.normal(0, 300, 5)
    fe = 1e5 * (1 - 0.03 * np.cos(np.radians(4 * hwp - 40))) + rng.normal(0, 300, 5)
    so, se = np.full(5, 310.0), np.array([300.0, 320, 330, 290, 305])
    p = tmp_path / "in.csv"
    with open(p, "w") as f:
        f.write("hwp_deg,f_o,f_e,sigma_o,sigma_e\n")
        for row in zip(hwp, fo, fe, so, se):
            f.write(",".join(repr(float(v)) for v in row) + "\n")
    j = run_json("stokes", "--input", p, "--kappa", "0.004")
    py = instpol.stokes(hwp, fo, fe, so, se, kappa=0.004)
    assert py["estimator"] == "weighted_least_squares"
    compare_with_cli(py, j)


def numpy_eq_q_u(hwp_deg, fo, fe):
    """eq:F then the Fourier sums eq:Q, eq:U (theta_i = i * 22.5 deg), per star (rows)."""
    F = (fo - fe) / (fo + fe)
    n = F.shape[-1]
    i = np.arange(n)
    q = 2.0 / n * np.sum(F * np.cos(np.pi * i / 2), axis=-1)
    u = 2.0 / n * np.sum(F * np.sin(np.pi * i / 2), axis=-1)
    return q, u


def test_batch_against_numpy_fourier_sums():
    rng = np.random.default_rng(1)
    m, n = 500, 16
    hwp = 22.5 * np.arange(n)
    q0 = rng.uniform(-0.05, 0.05, (m, 1))
    u0 = rng.uniform(-0.05, 0.05, (m, 1))
    th = np.radians(hwp)[None, :]
    mod = q0 * np.cos(4 * th) + u0 * np.sin(4 * th)
    tot = rng.uniform(1e4, 1e6, (m, 1))
    fo = rng.poisson(0.5 * tot * (1 + mod)).astype(float)
    fe = rng.poisson(0.5 * tot * (1 - mod)).astype(float)
    r = instpol.stokes(hwp, fo, fe)
    q, u = numpy_eq_q_u(hwp, fo, fe)
    assert r["q"].shape == (m,) and r["f"].shape == (m, n)
    np.testing.assert_allclose(r["q"], q, rtol=0, atol=1e-15)
    np.testing.assert_allclose(r["u"], u, rtol=0, atol=1e-15)
    np.testing.assert_allclose(r["p"], np.hypot(q, u), rtol=0, atol=1e-15)
    chi = np.degrees(0.5 * np.arctan2(u, q)) % 180.0
    d = (r["chi_deg"] - chi + 90.0) % 180.0 - 90.0
    assert np.max(np.abs(d)) < 1e-9
    # Poisson counts, equal weights: var(Q) = sum c_i^2 sigma_F,i^2 with sigma_F^2 = (1 - F^2)/(f_o + f_e)
    F = (fo - fe) / (fo + fe)
    varf = (1 - F**2) / (fo + fe)
    c = 2.0 / n * np.cos(np.pi * np.arange(n) / 2)
    np.testing.assert_allclose(r["sigma_q"], np.sqrt(np.sum(c**2 * varf, axis=1)), rtol=1e-12)
    # one star of the batch is that star alone
    one = instpol.stokes(hwp, fo[7], fe[7])
    assert one["q"] == r["q"][7] and same(one["f"], r["f"][7])


def test_bad_input_raises_input_error_with_the_library_message():
    with pytest.raises(instpol.InputError, match="look like radians"):
        instpol.stokes([0, 0.39, 0.79, 1.18], [1e4] * 4, [1e4] * 4)
    r = instpol.stokes(np.radians([0, 22.5, 45, 67.5]), [1e4] * 4, [1e4] * 4, angles_in_radians=True)
    assert r["p"] == 0.0
    with pytest.raises(instpol.InputError, match="photon counts cannot be negative"):
        instpol.stokes([0, 22.5, 45, 67.5], [1e4, -5, 1e4, 1e4], [1e4] * 4)
    # A repeated plate position is combined as instpol stokes does (it was refused before),
    # and a negative count among repeats is refused naming its column.
    r = instpol.stokes([0, 22.5, 22.5, 67.5], [1e4] * 4, [1e4] * 4)
    assert r["n_hwp"] == 3 and same(r["exposures"]["index"], [0, 1, 2, 3])
    with pytest.raises(instpol.InputError, match="column 2 of f_o, f_e: photon counts cannot be negative"):
        instpol.stokes([0, 22.5, 22.5, 67.5], [1e4, 1e4, -5, 1e4], [1e4] * 4)
    with pytest.raises(instpol.InputError, match=r"star 1 \(row 1"):
        instpol.stokes([0, 22.5, 45, 67.5], [[1e4] * 4, [1e4, 0, 1e4, 1e4]], [[1e4] * 4, [1e4, 0, 1e4, 1e4]])
    with pytest.raises(instpol.InputError, match="sigma_o is given without sigma_e"):
        instpol.stokes([0, 22.5, 45, 67.5], [1e4] * 4, [1e4] * 4, sigma_o=[1.0] * 4)
    with pytest.raises(instpol.InputError, match="one column per HWP angle"):
        instpol.stokes([0, 22.5, 45], [1e4] * 4, [1e4] * 4)
    with pytest.raises(instpol.InputError, match="kappa"):
        instpol.stokes([0, 22.5, 45, 67.5], [1e4] * 4, [1e4] * 4, kappa=1.0)


def exposures_match_cli(ex, j):
    """instpol.stokes' `exposures` against the CLI's JSON list of every exposure's check."""
    jx = key(j, "exposures")
    assert list(ex["index"]) == [e["row"] - 1 for e in jx]
    assert same(ex["hwp_deg"], [e["hwp_deg"] for e in jx])
    assert same(ex["f"], [e["f"] for e in jx]) and same(ex["pull"], [e["pull"] for e in jx])
    assert list(ex["outlier"]) == [e["outlier"] for e in jx]


def test_repeated_angles_combined_as_the_cli(run_json, tmp_path):
    """Two cycles of 8 positions (the second at theta + 360 deg) with one outlier exposure:
    photon counts, and the same fluxes with errors, give the CLI's numbers to the last bit, the
    CLI's exposure checks, and (independently) the reduction of the fluxes summed here."""
    hwp, fo, fe, _ = read_csv(DATA / "repeats_n8x2.csv")
    j = run_json("stokes", "--input", DATA / "repeats_n8x2.csv")
    py = instpol.stokes(hwp, fo, fe)
    compare_with_cli(py, j)
    exposures_match_cli(py["exposures"], j)
    assert py["n_hwp"] == 8 and list(py["exposures"]["outlier"]).count(True) == 2
    summed = instpol.stokes(hwp[:8], fo[:8] + fo[8:], fe[:8] + fe[8:])
    assert summed["exposures"] is None
    for k in ["q", "u", "sigma_q", "sigma_u", "p"]:
        assert py[k] == summed[k], k
    # With per-beam errors (not Poisson): the errors of a position add in quadrature.
    so, se = 0.9 * np.sqrt(fo), 1.1 * np.sqrt(fe)
    p = tmp_path / "errs.csv"
    with open(p, "w") as f:
        f.write("hwp_deg,f_o,f_e,sigma_o,sigma_e\n")
        for row in zip(hwp, fo, fe, so, se):
            f.write(",".join(repr(float(v)) for v in row) + "\n")
    j = run_json("stokes", "--input", p)
    py = instpol.stokes(hwp, fo, fe, so, se)
    compare_with_cli(py, j)
    exposures_match_cli(py["exposures"], j)
    # A batch of two stars: each is that star alone.
    b = instpol.stokes(hwp, np.stack([fo, fo[::-1]]), np.stack([fe, fe[::-1]]))
    one = instpol.stokes(hwp, fo, fe)
    assert b["q"][0] == one["q"] and same(b["exposures"]["pull"][0], one["exposures"]["pull"])
    assert b["exposures"]["f"].shape == (2, 16)
