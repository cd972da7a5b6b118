#!/usr/bin/env bash
# Side-by-side throughput of `instpol mc` and the numpy peer (shared/peers/numpy_mc.py) on the
# same work: N = 4 HWP angles, SNR = 100 (5000 counts per beam), P0 = 1 %, chi0 = 30 deg,
# for each noise model, one thread each and all threads (numpy's generator is single-threaded,
# so its one run is the reference for both). Also reports the engine's time against drawing
# the same random numbers alone (--rng-baseline).
#
# usage: bench/mc.sh [TRIALS]          (default 10000000)
# env:   PEER=path/to/numpy_mc.py      (default: ../shared/peers/numpy_mc.py beside the repo)
#        REPS=3                        (each program runs REPS times; the best throughput is
#                                       kept, which matters on a shared, loaded machine)
set -euo pipefail
cd "$(dirname "$0")/.."
TRIALS="${1:-10000000}"
PEER="${PEER:-$(cd .. && pwd)/shared/peers/numpy_mc.py}"
[ -f "$PEER" ] || { echo "error: numpy peer not found at $PEER (set PEER=...)" >&2; exit 2; }

python3 -c "import numpy" 2>/dev/null || python3 -m pip install --quiet numpy \
  || python3 -m pip install --quiet --break-system-packages numpy
cargo build --release -p instpol >&2
BIN="${CARGO_TARGET_DIR:-target}/release/instpol"
NPROC="$(nproc)"
REPS="${REPS:-3}"
OUT="$(mktemp -d)"
trap 'rm -rf "$OUT"' EXIT

for noise in poisson gauss-f gauss-qu; do
  for r in $(seq "$REPS"); do
    echo "running $noise ($r/$REPS): numpy peer ..." >&2
    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 \
      python3 "$PEER" --n-hwp 4 --snr 100 --p0 0.01 --chi0 30 --trials "$TRIALS" --noise "$noise" --seed 1 \
      > "$OUT/numpy_${noise}_$r.json"
    for t in 1 "$NPROC"; do
      echo "running $noise ($r/$REPS): instpol --threads $t ..." >&2
      "$BIN" mc --n-hwp 4 --snr 100 --p0 0.01 --chi0 30 --trials "$TRIALS" --noise "$noise" --seed 1 \
        --threads "$t" --rng-baseline --json > "$OUT/instpol_${noise}_${t}_$r.json"
    done
  done
done

python3 - "$OUT" "$NPROC" "$TRIALS" "$REPS" <<'PY'
import json, sys, os
out, nproc, trials, reps = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
def best(prefix):
    runs = [json.load(open(os.path.join(out, f"{prefix}_{r}.json"))) for r in range(1, reps + 1)]
    b = max(runs, key=lambda d: d["trials_per_second"])
    if "rng_seconds" in b:
        b["engine_over_rng"] = min(d["seconds"] / d["rng_seconds"] for d in runs)
    return b
print(f"N=4, SNR=100, P0=1%, {trials:,} trials; trials/s, best of {reps} (higher is better)")
print(f"{'noise':<9} {'numpy':>12} {'instpol 1t':>12} {'ratio 1t':>9} {'instpol '+nproc+'t':>12} {'ratio '+nproc+'t':>9} {'scaling':>8} {'eng/draw':>9} {'mean_p np':>10} {'mean_p ip':>10} {'rms np':>9} {'rms ip':>9}")
for noise in ["poisson", "gauss-f", "gauss-qu"]:
    n = best(f"numpy_{noise}")
    a = best(f"instpol_{noise}_1")
    b = best(f"instpol_{noise}_{nproc}")
    tn, ta, tb = n["trials_per_second"], a["trials_per_second"], b["trials_per_second"]
    print(f"{noise:<9} {tn:>12.3e} {ta:>12.3e} {ta/tn:>9.2f} {tb:>12.3e} {tb/tn:>9.2f} {tb/ta:>8.2f} {a['engine_over_rng']:>9.2f} "
          f"{n['mean_p']:>10.6f} {a['mean_p']:>10.6f} {n['rms_p']:>9.6f} {a['rms_p']:>9.6f}")
print("ratio = instpol / numpy trials per second; scaling = all threads / one thread;")
print("eng/draw = instpol engine time / time to draw the same random numbers alone (one thread, wall clock)")
PY
