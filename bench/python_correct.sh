#!/usr/bin/env bash
# Must show of issue 15: `pip install` of the built wheel into a fresh venv, then a Python script
# corrects 1e6 catalog positions through a FORS1 calibration (the demo's V file): the same
# numbers as `instpol correct` to the last bit, and the rate on one core side by side with a
# straightforward numpy implementation of the same exact inversion (bench/python_correct.py).
# usage: bench/python_correct.sh [N] [REPS]       (defaults 1e6 and 7)
# Release builds; run on a quiet machine (the 2 cores are shared: check `uptime`). The script
# reports wall-clock and CPU time; the one-core figure is RAYON_NUM_THREADS=1's CPU time. Two
# JSON objects: default malloc (with the bit-for-bit check against the CLI), then glibc's
# huge-page malloc.
set -euo pipefail
cd "$(dirname "$0")/.."
N=${1:-1e6}
REPS=${2:-7}
T=${CARGO_TARGET_DIR:-target}
W=$(mktemp -d)
trap 'rm -rf "$W"' EXIT
echo "load before: $(uptime)" >&2
command -v python3 >/dev/null || { echo "python3 is required (with venv)" >&2; exit 1; }
python3 -m venv "$W/venv"
"$W/venv/bin/pip" install --quiet maturin numpy astropy
(cd crates/python && "$W/venv/bin/maturin" build --release --quiet -o "$W/wheels" >&2)
# A fresh venv that gets only the wheel (and what it declares: numpy) plus astropy for the
# numpy peer's header reading.
python3 -m venv "$W/fresh"
"$W/fresh/bin/pip" install --quiet "$W"/wheels/instpol-*.whl astropy
cargo build --release -q -p instpol >&2
BIN="$T/release/instpol"
export OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1   # one core for numpy too
"$BIN" demo --no-frames --out "$W/demo" > /dev/null
RAYON_NUM_THREADS=1 "$W/fresh/bin/python" bench/python_correct.py "$W/demo/cal_V.fits" "$BIN" "$W" "$N" "$REPS"
# The same timing with glibc's malloc backing large blocks by transparent huge pages (glibc >=
# 2.35; both sides benefit): fresh output arrays then fault in 2 MB pages instead of 4 kB ones.
SKIP_CLI=1 GLIBC_TUNABLES=glibc.malloc.hugetlb=1 RAYON_NUM_THREADS=1 \
  "$W/fresh/bin/python" bench/python_correct.py "$W/demo/cal_V.fits" "$BIN" "$W" "$N" "$REPS"
echo "load after: $(uptime)" >&2
