#!/usr/bin/env bash
# `instpol scan` of 10,000 raw files (headers only, FORS2-like chip files made by
# bench/peers/scan_peer.py) against an astropy `fits.getheader` loop reading the same keywords
# of the same files (issue 31: target >= 10x). Each timed REPS times, alternating; medians.
# usage: bench/scan.sh [N_FILES]   env: REPS (default 3), SCAN_DIR (kept when set)
set -euo pipefail
cd "$(dirname "$0")/.."
N=${1:-10000}
REPS=${REPS:-3}
T=${CARGO_TARGET_DIR:-target}
LOG=$(mktemp -d)
trap 'rm -rf "$LOG"' EXIT
cargo build --release -q -p instpol >&2
BIN="$T/release/instpol"
DIR=${SCAN_DIR:-$LOG/files}
if [ ! -f "$DIR/.made_$N" ]; then
  rm -rf "$DIR"
  python3 bench/peers/scan_peer.py make "$DIR" "$N"
  touch "$DIR/.made_$N"
fi
ours=(); peer=()
for r in $(seq "$REPS"); do
  s=$(date +%s.%N)
  "$BIN" scan "$DIR" --instrument fors2 --out "$LOG/plan.json" --products "$LOG/p" > /dev/null
  e=$(date +%s.%N)
  ours+=("$(echo "$s $e" | awk '{print $2-$1}')")
  peer+=("$(python3 bench/peers/scan_peer.py scan "$DIR" | python3 -c 'import json,sys; print(json.load(sys.stdin)["seconds"])')")
done
med() { printf '%s\n' "$@" | sort -g | awk '{a[NR]=$1} END {print a[int((NR+1)/2)]}'; }
o=$(med "${ours[@]}"); p=$(med "${peer[@]}")
echo "| scan of $N raw files (headers only) | $o s | astropy getheader loop $p s | $(echo "$p $o" | awk '{printf "%.1fx", $1/$2}') | >= 10x |"
