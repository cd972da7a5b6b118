"""Correct 1e6 catalog positions through a FORS1 calibration with the Python package, check the
numbers against `instpol correct` to the last bit, and time it side by side with a
straightforward numpy implementation of the same exact inversion (issue 15, Must show).

usage: python bench/python_correct.py CAL.fits INSTPOL_BIN WORKDIR [N] [REPS]
Run with RAYON_NUM_THREADS=1 for the one-core figure (bench/python_correct.sh does). Prints one
JSON object.
"""

import json
import os
import subprocess
import sys
import time

import numpy as np

import instpol


def positions(n, seed=2006):
    """n measured stars inside the calibrated field (arcmin from the detector centre)."""
    rng = np.random.default_rng(seed)
    sq = rng.uniform(2e-4, 3e-3, n)
    su = rng.uniform(2e-4, 3e-3, n)
    return {
        "x": rng.uniform(-3.3, 3.3, n),
        "y": rng.uniform(-3.3, 3.3, n),
        "q": rng.normal(0, 0.02, n),
        "u": rng.normal(0, 0.02, n),
        "sigma_q": sq,
        "sigma_u": su,
        "cov_qu": 0.2 * sq * su * rng.uniform(-1, 1, n),
    }


def numpy_correct(h, c):
    """The same exact correction in plain numpy, from the calibration's header keywords: the
    radial model p(r) = sum C_k r^k along the radius with its coefficient covariance, the HWP
    zero angle, the closed-form inverse of the paper's M_I (eq:instpol) and the linear error
    propagation by its Jacobians, then P0, chi0 and their errors."""
    k0, deg = h["HIERARCH IP RADIAL FIRST POWER"], h["HIERARCH IP RADIAL DEGREE"]
    ks = list(range(k0, deg + 1))
    coef = np.array([h[f"HIERARCH IP RADIAL C{k}"] for k in ks])
    npar = len(ks)
    cov = np.array([[h[f"HIERARCH IP COV {min(i, j)} {max(i, j)}"] for j in range(npar)] for i in range(npar)])
    dx, dy = c["x"] - h["HIERARCH IP CENTRE X"], c["y"] - h["HIERARCH IP CENTRE Y"]
    r2 = dx * dx + dy * dy
    r = np.sqrt(r2)
    c2, s2 = (dx * dx - dy * dy) / r2, 2 * dx * dy / r2
    basis = np.stack([r**k for k in ks])  # (npar, n)
    p = coef @ basis
    var_p = sum(cov[i, j] * basis[i] * basis[j] for i in range(npar) for j in range(npar))  # no BLAS threads
    qi, ui = p * c2, p * s2
    vqi, vui, cqi = var_p * c2 * c2, var_p * s2 * s2, var_p * c2 * s2
    off = np.radians(h["HIERARCH IP HWP CHI OFFSET DEG"])
    co, so = np.cos(2 * off), np.sin(2 * off)
    q1, u1 = co * c["q"] - so * c["u"], so * c["q"] + co * c["u"]
    vq, vu, cv = c["sigma_q"] ** 2, c["sigma_u"] ** 2, c["cov_qu"]
    vq1 = co * co * vq + so * so * vu - 2 * co * so * cv
    vu1 = so * so * vq + co * co * vu + 2 * co * so * cv
    cv1 = co * so * (vq - vu) + (co * co - so * so) * cv
    pa = np.hypot(qi, ui)
    nq, nu = np.where(pa > 0, qi / np.where(pa > 0, pa, 1), 0), np.where(pa > 0, ui / np.where(pa > 0, pa, 1), 0)
    nm = nq * q1 + nu * u1
    d = 1 - (qi * q1 + ui * u1)
    q0 = ((1 + pa) * q1 - qi - nm * qi) / d
    u0 = ((1 + pa) * u1 - ui - nm * ui) / d
    jm = [[((1 + pa) - pa * nq * nq + q0 * qi) / d, (-pa * nq * nu + q0 * ui) / d],
          [(-pa * nu * nq + u0 * qi) / d, ((1 + pa) - pa * nu * nu + u0 * ui) / d]]
    ja = [[(-1 - nm * (1 - nq * nq) + q0 * q1) / d, (q1 * nu - nq * u1 + nm * nq * nu + q0 * u1) / d],
          [(u1 * nq - nu * q1 + nm * nu * nq + u0 * q1) / d, (-1 - nm * (1 - nu * nu) + u0 * u1) / d]]

    def sandwich(j, a, b, cc):
        r0 = (j[0][0] * a + j[0][1] * cc, j[0][0] * cc + j[0][1] * b)
        r1 = (j[1][0] * a + j[1][1] * cc, j[1][0] * cc + j[1][1] * b)
        return r0[0] * j[0][0] + r0[1] * j[0][1], r1[0] * j[1][0] + r1[1] * j[1][1], r0[0] * j[1][0] + r0[1] * j[1][1]

    aq, au, ac = sandwich(jm, vq1, vu1, cv1)
    bq, bu, bc = sandwich(ja, vqi, vui, cqi)
    vq0, vu0, cv0 = aq + bq, au + bu, ac + bc
    p0 = np.hypot(q0, u0)
    chi0 = np.degrees(0.5 * np.arctan2(u0, q0)) % 180
    sp0 = np.sqrt(np.maximum(q0 * q0 * vq0 + u0 * u0 * vu0 + 2 * q0 * u0 * cv0, 0) / (p0 * p0))
    sc0 = np.degrees(np.minimum(
        0.5 * np.sqrt(np.maximum(u0 * u0 * vq0 + q0 * q0 * vu0 - 2 * q0 * u0 * cv0, 0)) / (p0 * p0), np.pi / np.sqrt(12)))
    return {"q0": q0, "u0": u0, "sigma_q0": np.sqrt(vq0), "sigma_u0": np.sqrt(vu0), "cov_qu0": cv0, "p0": p0,
            "sigma_p0": sp0, "chi0_deg": chi0, "sigma_chi0_deg": sc0, "q_inst": qi, "u_inst": ui}


def best_of(reps, f):
    """Best wall-clock and best CPU time (this process, all threads) of `reps` runs. On a shared
    machine the CPU time is the time on a core; with RAYON_NUM_THREADS=1 and numpy's
    element-wise loops both sides run on one thread, so it is the one-core figure."""
    best, best_cpu, out = float("inf"), float("inf"), None
    for _ in range(reps):
        t, c = time.perf_counter(), time.process_time()
        out = f()
        best = min(best, time.perf_counter() - t)
        best_cpu = min(best_cpu, time.process_time() - c)
    return best, best_cpu, out


def main():
    cal_path, bin_, work = sys.argv[1], sys.argv[2], sys.argv[3]
    n = int(float(sys.argv[4])) if len(sys.argv) > 4 else 1_000_000
    reps = int(sys.argv[5]) if len(sys.argv) > 5 else 5
    from astropy.io import fits

    h = fits.getheader(cal_path)
    c = positions(n)
    cal = instpol.Calibration.load(cal_path)
    t_py, cpu_py, r = best_of(reps, lambda: cal.correct(**c))
    t_np, cpu_np, ref = best_of(reps, lambda: numpy_correct(h, c))
    report = {
        "n_positions": n,
        "threads": os.environ.get("RAYON_NUM_THREADS", "all"),
        "glibc_tunables": os.environ.get("GLIBC_TUNABLES", ""),
        "instpol_python_s": t_py,
        "numpy_s": t_np,
        "instpol_positions_per_s": n / t_py,
        "numpy_positions_per_s": n / t_np,
        "speedup_vs_numpy": t_np / t_py,
        "instpol_python_cpu_s": cpu_py,
        "numpy_cpu_s": cpu_np,
        "instpol_positions_per_cpu_s": n / cpu_py,
        "numpy_positions_per_cpu_s": n / cpu_np,
        "speedup_vs_numpy_cpu": cpu_np / cpu_py,
        "max_abs_diff_numpy": {k: float(np.max(np.abs(ref[k] - r[k]))) for k in ("q0", "u0", "p0", "sigma_q0", "sigma_p0")},
    }
    if os.environ.get("SKIP_CLI"):
        print(json.dumps(report, indent=1))
        return
    # The CLI on the same catalog: every added column must be the same float, bit for bit.
    inp, out = os.path.join(work, "catalog.csv"), os.path.join(work, "corrected.csv")
    names = list(c)
    np.savetxt(inp, np.column_stack([c[k] for k in names]), delimiter=",", header=",".join(names), comments="",
               fmt="%.17g")
    t0 = time.perf_counter()
    subprocess.run([bin_, "correct", "--cal", cal_path, "--in", inp, "--out", out, "--json"], check=True,
                   capture_output=True)
    t_cli = time.perf_counter() - t0
    with open(out) as f:
        head = f.readline().strip().split(",")
    cli = np.loadtxt(out, delimiter=",", skiprows=1)
    cols = ["q0", "u0", "sigma_q0", "sigma_u0", "cov_qu0", "p0", "sigma_p0", "chi0_deg", "sigma_chi0_deg",
            "q_inst", "u_inst"]
    # the catalog must have gone in exactly: the CLI's copy of the input columns equals ours
    inputs_same = all(np.array_equal(cli[:, head.index(k)], c[k]) for k in names)
    mism = {k: int(np.sum(cli[:, head.index(k)] != r[k])) for k in cols}
    report.update({"cli_correct_csv_s": t_cli, "bit_identical_to_cli": inputs_same and all(v == 0 for v in mism.values()),
                   "mismatches": mism})
    print(json.dumps(report, indent=1))
    if not (inputs_same and all(v == 0 for v in mism.values())):
        sys.exit("the Python correction differs from `instpol correct`")


if __name__ == "__main__":
    main()
