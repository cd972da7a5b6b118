#!/usr/bin/env bash
# Run every fuzz target of crates/cli/tests/fuzz.rs for a bounded time and record the result
# in fuzz/FINDINGS.md. Usage: fuzz/run.sh [SECONDS_PER_TARGET] [SEED]
set -u
cd "$(dirname "$0")/.."
SECS=${1:-30}
SEED=${2:-11400714819323198485}
REPORT=$(mktemp)
export FUZZ_SECS=$SECS FUZZ_SEED=$SEED FUZZ_REPORT=$REPORT
rm -rf fuzz/findings
cargo test -p instpol --test fuzz --no-run -q 2>/dev/null || { echo "build failed"; exit 1; }
status=0
for t in fuzz_instrument_toml fuzz_scene_toml fuzz_stokes_csv fuzz_calibration_file fuzz_frame_fits; do
  echo "== $t ($SECS s)"
  cargo test -q -p instpol --test fuzz -- --ignored --exact "$t" --nocapture 2>&1 | grep -E '\| [0-9]+ runs|panicked|FAILED|error' | head -5 || true
done
{
  echo "# Fuzzing findings"
  echo
  echo "Last run: $(date -u +%Y-%m-%dT%H:%MZ), $SECS s per target, seed $SEED, \`fuzz/run.sh $SECS $SEED\`."
  echo "Byte-mutation fuzzing (crates/cli/tests/fuzz.rs; nightly cargo-fuzz not used). Corpus size ="
  echo "distinct outcome classes reached (first error line with digits removed). Findings' inputs"
  echo "are kept in fuzz/findings/<target>/ (not committed)."
  echo
  echo "| target | runs | corpus (distinct outcomes) | findings |"
  echo "|---|---|---|---|"
  sed -E 's/^([^|]*)\| ([0-9]+) runs \| ([0-9]+) distinct outcomes \| (.*)$/| \1| \2 | \3 | \4 |/' "$REPORT"
} > fuzz/FINDINGS.md.new
# Keep the hand-written notes below the generated table.
if [ -f fuzz/FINDINGS.md ] && grep -q '^## Notes' fuzz/FINDINGS.md; then
  echo >> fuzz/FINDINGS.md.new
  sed -n '/^## Notes/,$p' fuzz/FINDINGS.md >> fuzz/FINDINGS.md.new
fi
mv fuzz/FINDINGS.md.new fuzz/FINDINGS.md
cat fuzz/FINDINGS.md
rm -f "$REPORT"
