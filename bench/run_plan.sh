#!/usr/bin/env bash
# `instpol run` over a night's plan against the same units' commands run one after another by
# a shell script (issue 31: within 5 %), both on one core (`--jobs 1`). The night is the
# simulated one of crates/cli/tests/it/night.rs (~100 exposures of a tiny FORS2, 31 units), so
# what is measured is what `run` adds to the commands: reading the plan, hashing every input
# before and every output after, the records and locks. Each timed REPS times, alternating,
# from an empty products folder; medians.
# A second row: a plan of one unit, the reduction of 16 FORS1 frames of 2048 x 2048 (256 MB,
# made by bench/peers/reduce_peer.py as for bench/run.sh), against the same reduce command
# alone: what `run` adds when the inputs are large (their hashes, which the command reports).
# usage: bench/run_plan.sh     env: REPS (default 5), NIGHT_DIR, FRAMES_DIR (kept when set)
set -euo pipefail
cd "$(dirname "$0")/.."
REPS=${REPS:-5}
T=${CARGO_TARGET_DIR:-target}
LOG=$(mktemp -d)
trap 'rm -rf "$LOG"' EXIT
cargo build --release -q -p instpol >&2
BIN="$(cd "$T/release" && pwd)/instpol"
DIR=${NIGHT_DIR:-$LOG/night}
if [ ! -f "$DIR/.made" ]; then
  rm -rf "$DIR"
  INSTPOL_NIGHT_DIR="$DIR" cargo test --release -q -p instpol --test it -- --ignored --exact night::write_night_for_bench >&2
  touch "$DIR/.made"
fi
PLAN="$LOG/night.json"
"$BIN" scan "$DIR/raw" --instrument instruments/tiny_fors2.toml --out "$PLAN" \
  --products "$LOG/products" --bin 8 --fwhm 3 --aperture 4 \
  --sky EMPTY-V1:1.74:-53.8 --sky EMPTY-V2:1.74:-53.8 --sky EMPTY-I1:1.74:-53.8 --sky EMPTY-I2:1.74:-53.8 > /dev/null
# The units' commands in the plan's order, as a person would run them by hand.
python3 - "$PLAN" "$BIN" > "$LOG/by_hand.sh" <<'PY'
import json, shlex, sys, os
plan = json.load(open(sys.argv[1])); b = shlex.quote(sys.argv[2])
print("set -e")
for u in plan["units"]:
    for o in u["outputs"]:
        print("mkdir -p " + shlex.quote(os.path.dirname(o)))
    cmd = b + " " + " ".join(shlex.quote(c) for c in u["command"])
    if u.get("stdout"):
        # A check that does not pass (exit 1) still writes its output, as run keeps it.
        cmd += " > " + shlex.quote(u["outputs"][0]) + (" || [ $? -eq 1 ]" if u.get("check") else "")
    print(cmd + " > /dev/null" if not u.get("stdout") else cmd)
PY
ours=(); hand=()
for r in $(seq "$REPS"); do
  rm -rf "$LOG/products"
  s=$(date +%s.%N); "$BIN" run "$PLAN" --jobs 1 > /dev/null; e=$(date +%s.%N)
  ours+=("$(echo "$s $e" | awk '{print $2-$1}')")
  rm -rf "$LOG/products"
  s=$(date +%s.%N); bash "$LOG/by_hand.sh"; e=$(date +%s.%N)
  hand+=("$(echo "$s $e" | awk '{print $2-$1}')")
done
med() { printf '%s\n' "$@" | sort -g | awk '{a[NR]=$1} END {print a[int((NR+1)/2)]}'; }
o=$(med "${ours[@]}"); h=$(med "${hand[@]}")
n=$(python3 -c "import json,sys; print(len(json.load(open(sys.argv[1]))['units']))" "$PLAN")
echo "| run over a night's plan ($n units, --jobs 1) | $o s | its commands one after another $h s | $(echo "$o $h" | awk '{printf "%.3f", $1/$2}') | <= 1.05 |"

FR=${FRAMES_DIR:-$LOG/frames}
if [ ! -f "$FR/frame_15.fits" ]; then
  python3 bench/peers/reduce_peer.py make "$FR" >&2
fi
BIG="$LOG/big.json"
python3 - "$BIG" "$FR" "$LOG/bigout" <<'PY'
import json, sys, glob
plan_path, fr, out = sys.argv[1:4]
frames = sorted(glob.glob(fr + "/frame_*.fits"))
m = out + "/map.fits"
unit = {"id": "reduce-16", "kind": "reduce", "inputs": frames, "outputs": [m],
        "command": ["reduce", *frames, "--out", m], "after": []}
json.dump({"version": 1, "instrument": "fors1", "records": out + "/.instpol-run", "units": [unit],
           "files": [], "left_out": []}, open(plan_path, "w"))
PY
ours=(); alone=()
for r in $(seq "$REPS"); do
  rm -rf "$LOG/bigout"; mkdir -p "$LOG/bigout"
  s=$(date +%s.%N); "$BIN" run "$BIG" > /dev/null; e=$(date +%s.%N)
  ours+=("$(echo "$s $e" | awk '{print $2-$1}')")
  rm -rf "$LOG/bigout"; mkdir -p "$LOG/bigout"
  s=$(date +%s.%N); "$BIN" reduce "$FR"/frame_*.fits --out "$LOG/bigout/map.fits" > /dev/null 2>&1; e=$(date +%s.%N)
  alone+=("$(echo "$s $e" | awk '{print $2-$1}')")
done
o=$(med "${ours[@]}"); a=$(med "${alone[@]}")
echo "| run of one reduce unit, 16 x 2048^2 frames | $o s | the reduce command alone $a s | $(echo "$o $a" | awk '{printf "%.3f", $1/$2}') | <= 1.05 |"
