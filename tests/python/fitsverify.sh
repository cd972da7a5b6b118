#!/usr/bin/env bash
# Run fitsverify (HEASARC, Debian package `fitsverify`) on every FITS file under the folders
# given (default: the current folder); exit 1 if any file has an error or a warning, 0 if all
# verify OK. Without fitsverify it says so and exits 0 (CI installs it: apt-get install -y
# fitsverify). test_astropy_outputs.py runs the same check on every command's outputs.
set -euo pipefail
if ! command -v fitsverify >/dev/null 2>&1; then
    echo "WARNING: fitsverify is not installed (apt-get install -y fitsverify): FITS check skipped" >&2
    exit 0
fi
status=0
n=0
while IFS= read -r -d '' f; do
    n=$((n + 1))
    out=$(fitsverify -q "$f" 2>&1 || true)
    case "$out" in
        *"verification OK"*) ;;
        *) echo "$out"; status=1 ;;
    esac
done < <(find "${@:-.}" -type f \( -iname '*.fits' -o -iname '*.fit' -o -iname '*.fts' \) -print0)
echo "fitsverify: $n files checked" >&2
exit $status
