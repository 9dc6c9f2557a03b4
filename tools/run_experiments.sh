#!/usr/bin/env bash
# Runs every experiment and records its wall time in OUT/run-times.txt.
# Usage: tools/run_experiments.sh [OUT] [--quick-multi]
#   default: single-viewer full preset, the multi-viewer experiments, crc and
#   megaviews with their --quick presets (the full multi-viewer presets take
#   hours on 2 cores; pass --full-multi to run them).
set -euo pipefail
OUT=${1:-out}
MULTI=--quick
[ "${2:-}" = "--full-multi" ] && MULTI=""
SLC=${SLC:-.venv/bin/slc}
mkdir -p "$OUT"
: > "$OUT/run-times.txt"
run() {
  local name=$1; shift
  local t0=$(date +%s)
  "$SLC" run "$name" "$@" --out "$OUT" > "$OUT/$name.log" 2>&1
  echo "$name $* : $(( $(date +%s) - t0 )) s" >> "$OUT/run-times.txt"
}
run single-viewer
for e in overlap random-viewers memory stereo meeting; do run $e $MULTI; done
run crc --quick
run megaviews --quick
"$SLC" bench rays > "$OUT/bench-rays.txt" 2>&1
"$SLC" bench rays --scene sponza >> "$OUT/bench-rays.txt" 2>&1 || true
