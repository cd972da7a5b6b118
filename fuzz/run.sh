#!/usr/bin/env bash
# Fuzz every input reader for a bounded time and record the result in fuzz/FINDINGS.md.
# Usage: fuzz/run.sh [SECONDS_PER_TARGET] [SEED]
#
# With a nightly toolchain and cargo-fuzz (`cargo install cargo-fuzz`), the cargo-fuzz targets
# of fuzz/fuzz_targets/ run in-process over the library loaders (coverage-guided libFuzzer);
# otherwise the byte-mutation tests of crates/cli/tests/it/fuzz.rs run (FUZZ_BYTES=1 forces them).
# Environment: FUZZ_TARGET_DIR (nightly build folder, default target/fuzz-nightly),
# FUZZ_TARGETS (space-separated subset). Corpora grow in fuzz/corpus/<target>/ (not committed;
# seeded from fuzz/seeds/<target>/ and, for the FITS readers, generated here), findings land in
# fuzz/artifacts/<target>/ (not committed).
set -u
cd "$(dirname "$0")/.."
SECS=${1:-30}
SEED=${2:-}
status=0

notes() {
  # Keep the hand-written notes below the generated table.
  if [ -f fuzz/FINDINGS.md ] && grep -q '^## Notes' fuzz/FINDINGS.md; then
    echo >> fuzz/FINDINGS.md.new
    sed -n '/^## Notes/,$p' fuzz/FINDINGS.md >> fuzz/FINDINGS.md.new
  fi
  mv fuzz/FINDINGS.md.new fuzz/FINDINGS.md
  cat fuzz/FINDINGS.md
}

if [ -z "${FUZZ_BYTES:-}" ] && cargo +nightly fuzz --version >/dev/null 2>&1; then
  # ---- cargo-fuzz (libFuzzer) ----
  TD=${FUZZ_TARGET_DIR:-target/fuzz-nightly}
  case "$TD" in /*) ;; *) TD="$PWD/$TD" ;; esac
  SEED=${SEED:-1}
  TARGETS=${FUZZ_TARGETS:-instrument_toml scene_toml field_file stokes_csv calibration_file frame_fits sim_map import_map}
  SCRATCH=$(mktemp -d)
  export TMPDIR=$SCRATCH # the targets' per-process scratch folders go here
  trap 'rm -rf "$SCRATCH"' EXIT
  # Build from a snapshot: the committed crates (git HEAD) plus this tree's fuzz/ crate, so
  # that others' half-done edits in a shared tree neither break the build nor get fuzzed, and
  # a finding is reproducible at a commit. FUZZ_WORKTREE=1 builds the working tree instead.
  if [ -n "${FUZZ_WORKTREE:-}" ]; then
    SRC=$PWD
  else
    SRC=${FUZZ_SRC:-$TD/src}
    tmp=$(mktemp -d)
    git archive HEAD Cargo.toml Cargo.lock crates instruments | tar -x -C "$tmp"
    mkdir -p "$tmp/fuzz" && cp -r fuzz/Cargo.toml fuzz/Cargo.lock fuzz/src fuzz/fuzz_targets fuzz/seeds "$tmp/fuzz/"
    # Copy only what changed (unchanged files keep their times: no full rebuild).
    (cd "$tmp" && find . -type f) | while read -r f; do
      if ! cmp -s "$tmp/$f" "$SRC/$f"; then mkdir -p "$(dirname "$SRC/$f")" && cp "$tmp/$f" "$SRC/$f"; fi
    done
    rm -rf "$tmp"
    echo "fuzzing $(git rev-parse --short HEAD) + working-tree fuzz/ (snapshot in $SRC)"
  fi
  fz() { (cd "$SRC/fuzz" && cargo +nightly fuzz "$@"); }
  fz build --target-dir "$TD" >/dev/null 2>&1 || { echo "cargo fuzz build failed"; fz build --target-dir "$TD" 2>&1 | grep -E '^error' | head; exit 1; }
  REPORT=$(mktemp)
  for t in $TARGETS; do
    C=fuzz/corpus/$t
    A=fuzz/artifacts/$t
    mkdir -p "$C" "$A"
    [ -d fuzz/seeds/$t ] && cp -n fuzz/seeds/$t/* "$C"/ 2>/dev/null
    if [ "$t" = frame_fits ] && [ -z "$(ls -A "$C")" ]; then
      INSTPOL_FUZZ_SEEDS=$PWD/$C fz run --target-dir "$TD" "$t" -- -runs=0 >/dev/null 2>&1
    fi
    if { [ "$t" = sim_map ] || [ "$t" = import_map ]; } && [ -z "$(ls -A "$C")" ]; then
      INSTPOL_FUZZ_SEEDS=$PWD/$C fz run --target-dir "$TD" "$t" -- -runs=0 >/dev/null 2>&1
    fi
    if [ "$t" = calibration_file ] && [ -z "$(ls -A "$C")" ]; then
      # Full-size calibrations from the demo, shrunk by the target's seed mode.
      cargo run -q --manifest-path "$SRC/Cargo.toml" -p instpol -- demo --no-frames --out "$SCRATCH/demo" >/dev/null 2>&1 || echo "demo failed: no calibration seeds"
      INSTPOL_FUZZ_DEMO=$SCRATCH/demo INSTPOL_FUZZ_SEEDS=$PWD/$C fz run --target-dir "$TD" "$t" -- -runs=0 >/dev/null 2>&1
    fi
    echo "== $t ($SECS s, $(ls "$C" | wc -l) corpus files)"
    LOG=$SCRATCH/$t.log
    fz run --target-dir "$TD" "$t" "$PWD/$C" -- -max_total_time="$SECS" -seed="$SEED" -timeout=10 \
      -rss_limit_mb=2048 -max_len=65536 -close_fd_mask=1 -print_final_stats=1 -artifact_prefix="$PWD/$A/" >"$LOG" 2>&1
    rc=$?
    runs=$(grep -oE 'stat::number_of_executed_units: *[0-9]+' "$LOG" | grep -oE '[0-9]+$' | tail -1)
    [ -z "$runs" ] && runs=$(grep -oE '^#[0-9]+' "$LOG" | tail -1 | tr -d '#')
    last=$(grep -E '^#[0-9]+.*cov: ' "$LOG" | tail -1)
    cov=$(echo "$last" | grep -oE 'cov: [0-9]+' | grep -oE '[0-9]+')
    ft=$(echo "$last" | grep -oE 'ft: [0-9]+' | grep -oE '[0-9]+')
    files=$(ls "$C" | wc -l)
    if [ $rc -eq 0 ]; then
      find="0 findings"
    else
      status=1
      art=$(grep -oE 'Test unit written to [^ ]+' "$LOG" | tail -1 | sed "s/Test unit written to //; s#^$PWD/fuzz/artifacts/##")
      why=$(grep -v 'Running `' "$LOG" | grep -E -A1 'panicked at|ERROR: libFuzzer|ERROR: AddressSanitizer|out-of-memory|timeout after|allocation of' | head -2 | tr '\n' ' ' | cut -c1-220)
      find="1 finding: ${art:-?}: ${why:-exit $rc}"
    fi
    echo "| $t | ${runs:-?} | $files | ${cov:-?} | ${ft:-?} | $find |" | tee -a "$REPORT"
  done
  {
    echo "# Fuzzing findings"
    echo
    echo "Last run: $(date -u +%Y-%m-%dT%H:%MZ), $SECS s per target, seed $SEED, \`fuzz/run.sh $SECS $SEED\`."
    echo "cargo-fuzz (libFuzzer, AddressSanitizer, debug assertions; fuzz/fuzz_targets/), in-process"
    echo "over the library loaders of commit $(git rev-parse --short HEAD). runs = executions this run; corpus = files in fuzz/corpus/<target>/"
    echo "after the run (it grows from run to run); cov / ft = libFuzzer's coverage edges / features at"
    echo "the end. A target stops at its first finding (input in fuzz/artifacts/<target>/, not committed)."
    echo
    echo "| target | runs | corpus (files) | cov | ft | findings |"
    echo "|---|---|---|---|---|---|"
    cat "$REPORT"
  } > fuzz/FINDINGS.md.new
  rm -f "$REPORT"
  notes
  exit $status
fi

# ---- fallback: byte mutation through crates/cli/tests/it/fuzz.rs ----
SEED=${SEED:-11400714819323198485}
REPORT=$(mktemp)
export FUZZ_SECS=$SECS FUZZ_SEED=$SEED FUZZ_REPORT=$REPORT
rm -rf fuzz/findings
cargo test -p instpol --test it --no-run -q 2>/dev/null || { echo "build failed"; exit 1; }
for t in fuzz_instrument_toml fuzz_scene_toml fuzz_stokes_csv fuzz_calibration_file fuzz_frame_fits; do
  echo "== $t ($SECS s)"
  cargo test -q -p instpol --test it -- --ignored --exact "fuzz::$t" --nocapture 2>&1 | grep -E '\| [0-9]+ runs|panicked|FAILED|error' | head -5 || true
done
{
  echo "# Fuzzing findings"
  echo
  echo "Last run: $(date -u +%Y-%m-%dT%H:%MZ), $SECS s per target, seed $SEED, \`FUZZ_BYTES=1 fuzz/run.sh $SECS $SEED\`."
  echo "Byte-mutation fuzzing (crates/cli/tests/it/fuzz.rs; nightly cargo-fuzz not available). Corpus size ="
  echo "distinct outcome classes reached (first error line with digits removed). Findings' inputs"
  echo "are kept in fuzz/findings/<target>/ (not committed)."
  echo
  echo "| target | runs | corpus (distinct outcomes) | findings |"
  echo "|---|---|---|---|"
  sed -E 's/^([^|]*)\| ([0-9]+) runs \| ([0-9]+) distinct outcomes \| (.*)$/| \1| \2 | \3 | \4 |/' "$REPORT"
} > fuzz/FINDINGS.md.new
rm -f "$REPORT"
notes
