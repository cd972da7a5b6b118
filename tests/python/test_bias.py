"""instpol.bias against `instpol bias --json` for every estimator and interval, and against the
closed forms of the estimators that have one."""

import numpy as np
import pytest

import instpol
from conftest import key, num, same

ESTIMATORS = ["naive", "as", "wk", "ml", "mp2", "mas", "mb", "pr06"]


@pytest.mark.parametrize("interval", ["neyman", "hpd"])
@pytest.mark.parametrize("p,sigma", [(0.012, 0.005), (0.0005, 0.002), (0.05, 0.001)])
def test_bias_matches_cli_json(run_json, interval, p, sigma):
    for est in ESTIMATORS:
        j = run_json("bias", "--p", p, "--sigma", sigma, "--estimator", est, "--interval", interval)
        r = instpol.bias(p, sigma, est, interval)
        assert same(r["estimate"], num(key(j, "estimate"))), est
        lo, hi = key(j, "interval")
        assert same(r["lo"], num(lo)) and same(r["hi"], num(hi)), (est, lo, hi)
        assert r["upper_limit_only"] == key(j, "upper_limit_only")
        assert r["empty"] == key(j, "empty")
        assert r["in_validity_range"] == key(j, "in_validity_range")
        for name, v in key(j, "all_estimators").items():
            assert same(r["all_estimators"][name], num(v)), name


def test_mas_with_unequal_errors_matches_cli(run_json):
    j = run_json("bias", "--p", "0.01", "--sigma", "0.004", "--sigma-q", "0.003", "--sigma-u", "0.006",
                 "--chi", "30", "--cl", "0.9")
    r = instpol.bias(0.01, 0.004, "mas", cl=0.9, sigma_q=0.003, sigma_u=0.006, chi_deg=30.0)
    assert same(r["estimate"], num(key(j, "estimate")))
    assert same(r["hi"], num(key(j, "interval")[1]))


def test_vectorized_closed_forms_and_broadcasting():
    p = np.array([[0.002], [0.01], [0.05]])  # (3, 1)
    sigma = np.array([0.001, 0.002, 0.004, 0.008])  # (4,)
    r = instpol.bias(p, sigma, "as")
    assert r["estimate"].shape == (3, 4)
    pb, sb = np.broadcast_arrays(p, sigma)
    as_ = np.where(pb > sb, np.sqrt(np.maximum(pb**2 - sb**2, 0)), 0.0)
    np.testing.assert_allclose(r["estimate"], as_, rtol=1e-14, atol=1e-18)
    mp2 = np.where(pb > sb, pb - sb**2 / pb, 0.0)
    np.testing.assert_allclose(r["all_estimators"]["mp2"], mp2, rtol=1e-13, atol=1e-18)
    assert same(r["all_estimators"]["naive"], pb)
    # the paper's law: P [1 - (0.62 sigma / P)^1.92] where valid (P/sigma > 4)
    ok = pb / sb > 4
    pr = pb * (1 - (0.62 * sb / pb) ** 1.92)
    np.testing.assert_allclose(r["all_estimators"]["pr06"][ok], pr[ok], rtol=1e-12)
    # the Neyman interval contains the high-SNR measurement
    big = instpol.bias(0.05, 0.001)
    assert big["lo"] < 0.05 < big["hi"]


def test_bad_values_raise_input_error():
    with pytest.raises(instpol.InputError, match="element 1"):
        instpol.bias([0.01, -0.01], 0.002)
    with pytest.raises(instpol.InputError, match="sigma"):
        instpol.bias(0.01, 0.0)
    with pytest.raises(instpol.InputError, match="unknown estimator"):
        instpol.bias(0.01, 0.002, "best")
    with pytest.raises(instpol.InputError, match="unknown interval kind"):
        instpol.bias(0.01, 0.002, "mas", "wide")
    with pytest.raises(instpol.InputError, match="do not broadcast"):
        instpol.bias([0.01, 0.02], [0.001, 0.002, 0.003])


def rice_cdf(x, a, n=200001):
    """P(P/sigma <= x | P0/sigma = a): the Rice pdf x exp(-(x^2 + a^2)/2) I0(a x), integrated
    here with numpy (Simpson's rule; np.i0 scaled by exp(-a x) to stay finite)."""
    t = np.linspace(0.0, x, n)
    f = t * np.exp(-0.5 * (t - a) ** 2) * (np.i0(a * t) * np.exp(-a * t))
    h = t[1] - t[0]
    return h / 3 * (f[0] + f[-1] + 4 * f[1:-1:2].sum() + 2 * f[2:-1:2].sum())


@pytest.mark.parametrize("p,sigma,cl", [(0.012, 0.004, 0.6827), (0.03, 0.005, 0.9)])
def test_neyman_limits_solve_the_rice_cdf(p, sigma, cl):
    """The Neyman central interval: the measured P sits at the (1 + cl)/2 quantile of the
    Rice distribution of the lower limit and at the (1 - cl)/2 quantile of the upper one."""
    r = instpol.bias(p, sigma, interval="neyman", cl=cl)
    x = p / sigma
    assert rice_cdf(x, r["lo"] / sigma) == pytest.approx(0.5 * (1 + cl), abs=1e-7)
    assert rice_cdf(x, r["hi"] / sigma) == pytest.approx(0.5 * (1 - cl), abs=1e-7)
