#!/usr/bin/env bash
# Runs every experiment as a new user would (first run, empty Dr.Jit kernel
# cache) and records its wall time in OUT/run-times.txt.
# Usage: tools/run_experiments.sh [OUT] [--full-multi] [--warm]
#   default: single-viewer full preset, the multi-viewer experiments and the
#   others with their --quick presets (the full multi-viewer presets take hours
#   on 2 cores; pass --full-multi to run them). Every experiment runs with HOME
#   pointed at a new empty folder, so no kernel compiled by an earlier run is
#   found on disk (SLC_CACHE, the ground-truth cache, is kept); --warm keeps HOME.
set -euo pipefail
OUT=${1:-out}
MULTI=--quick
COLD=1
for a in "${@:2}"; do
  case "$a" in
    --full-multi) MULTI="" ;;
    --warm) COLD=0 ;;
  esac
done
SLC=${SLC:-$(pwd)/.venv/bin/slc}
export SLC_CACHE=${SLC_CACHE:-$HOME/.cache/slc}
mkdir -p "$OUT"
: > "$OUT/run-times.txt"
run() {
  local name=$1; shift
  local t0 home
  t0=$(date +%s)
  home=$HOME
  [ "$COLD" = 1 ] && home=$(mktemp -d)
  local status=ok
  HOME="$home" "$SLC" run "$name" "$@" --out "$OUT" > "$OUT/$name.log" 2>&1 || status="FAILED (see $name.log)"
  echo "$name $* : $(( $(date +%s) - t0 )) s$([ "$COLD" = 1 ] && echo ', empty kernel cache'), $status" >> "$OUT/run-times.txt"
  [ "$COLD" = 1 ] && rm -rf "$home"
  return 0
}
run single-viewer
for e in overlap random-viewers memory stereo meeting; do run $e $MULTI; done
for e in camera-speed many-lights point-lights envmap crc megaviews; do run $e --quick; done
run distributed --quick
"$SLC" bench rays > "$OUT/bench-rays.txt" 2>&1
"$SLC" bench rays --scene sponza >> "$OUT/bench-rays.txt" 2>&1 || true
