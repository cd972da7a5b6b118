#!/usr/bin/env bash
# Regenerate the gallery's figures (docs/guide/gallery.md) into docs/guide/img/, with the
# instpol binary given as $INSTPOL (default: instpol on PATH). Run from the repository root:
#   INSTPOL=target/release/instpol bash docs/guide/make-gallery.sh
# The tests draw the same kinds of figure and check them (crates/cli/tests/it/plot_publication.rs:
# fonts, text inside the image, legends off the data); this script only refreshes the images.
set -euo pipefail
cd "$(dirname "$0")/../.."
BIN=${INSTPOL:-instpol}
W=$(mktemp -d)
trap 'rm -rf "$W"' EXIT
IMG=docs/guide/img
"$BIN" demo --no-frames --out "$W/demo-out" > /dev/null
"$BIN" plot "$W/demo-out/cal_B.fits" --out "$W/g" > /dev/null
"$BIN" stokes --input tests/data/fors1_v_star_n16.csv --plot "$W/g/fourier.png" > /dev/null
"$BIN" raytrace --instrument fors1 --filter V --plot "$W/g/raytrace.png" > /dev/null
"$BIN" plan --target-percent 0.05 --sky-rate 2 --bin 200 --candidate 6.45:68.4 --candidate 4:10 \
  --plot "$W/g/plan.png" > /dev/null
"$BIN" mc --sweep --trials 20000 --plot "$W/g/mc_sweep.png" > /dev/null
"$BIN" fit-standards ../shared/data/efosc2-standards/pv_standards.txt --model wiersema \
  --plot-dir "$W/g" > /dev/null 2>&1
cp "$W"/g/cal_B_map.png "$W"/g/cal_B_profile.png "$W"/g/cal_B_residual.png "$W"/g/fourier.png \
  "$W"/g/raytrace.png "$W"/g/plan.png "$W"/g/mc_sweep.png "$IMG"/
cp "$W"/g/standards_wiersema_0.png "$IMG"/fit_standards_V.png
echo "wrote the gallery's figures to $IMG"
