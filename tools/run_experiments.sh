#!/usr/bin/env bash
# Regenerates every published result: runs each experiment and benchmark that README.md and
# docs/ cite, each as a first run on an empty Dr.Jit kernel cache (HOME pointed at a new empty
# folder; SLC_CACHE, the reference cache, kept), and writes into OUT:
#   OUT/NAME.md or OUT/NAME.txt  one file per entry below, its first line the command, date,
#                                machine, code version and wall time (tools/results_index.py stamp)
#   OUT/README.md                the index of every result file in OUT (tools/results_index.py index)
# and, when single-viewer-quick ran, the README's table between <!-- results:single-viewer -->
# and <!-- /results --> (tools/results_index.py fill-readme).
#
# Usage: tools/run_experiments.sh [OUT] [--only NAME...] [--work DIR] [--readme FILE] [--warm] [--list]
#   OUT        output folder (default out/results); docs/results publishes the run
#   --only     run only the named entries (first column of --list)
#   --work     folder for each run's full output and log (default out/experiments)
#   --readme   the file whose results table single-viewer-quick fills (default README.md
#              when OUT is docs/results, else none)
#   --warm     keep HOME (kernel cache from earlier runs): faster, not a first run
#   --list     print the entries with their estimated minutes and exit
# Every experiment runs its --quick preset (or the small form listed; the entry distributed runs
# its full preset, 96x54 on 4 rigs and delays 0-4, about an hour: one Ray process per node). The other full presets (slc run
# NAME without --quick: 320x180, 240 frames, several scenes) take hours each on 2 cores and are
# not run here. The estimates are minutes on 2 idle cores with an empty kernel cache (kernel
# compilation included): about 2 hours for the whole list. Left out as too long:
# megaviews_scale.py at 1M views (ManyLoDs alone about 18 min) and the osc-gi multi-viewer full
# preset.
# The interpreter is .venv/bin/python (or $PYTHON_BIN) running this checkout's slc.
set -uo pipefail
REPO=$(cd "$(dirname "$0")/.." && pwd)
PY=${PYTHON_BIN:-$REPO/.venv/bin/python}
export SLC_CACHE=${SLC_CACHE:-$HOME/.cache/slc}

# name | kind | estimated minutes | command (several separated by " ; ", each on its own empty cache)
# kind: run  = `slc run EXP ...`, its OUT/EXP/results.md becomes NAME.md
#       text = the commands' output becomes NAME.txt
#       jsonl = the JSON lines the command prints become a Markdown table NAME.md
#       md   = the command writes the Markdown file {md} itself
RUNS=(
  "single-viewer-quick|run|1|slc run single-viewer --quick --scene atrium --scene sponza"
  "make-run|run|1|slc run single-viewer --quick --res 240x135 --methods rt16 rt48 slc adaptive --sweep"
  "adaptive-atrium|run|1|slc run single-viewer --quick --methods slc adaptive"
  "area-lights-320x180|run|2|slc run single-viewer --quick --res 320x180 --scene street --scene cornell:variant=classic --scene atrium --scene sponza --methods rt48 restir slc adaptive adaptive:polygon_lights=off adaptive:polygon_glossy=sample adaptive:polygon_glossy=point adaptive:force=cones adaptive:force=visibility,vis_lights=3"
  "single-viewer-street-320x180|run|3|slc run single-viewer --quick --scene street --res 320x180 --methods rt48 slc slc:freeze=off adaptive adaptive:freeze=off"
  "single-viewer-320x180|run|7|slc run single-viewer --quick --res 320x180 --scene atrium --scene cornell --scene garden --scene hangar --scene lamps --scene skylit --scene spheres --scene sponza --scene street --scene two_rooms --scene village --methods rt48 restir slc slc:fetch=bilinear adaptive --sweep"
  "corpus|run|6|slc run corpus --quick"
  "overlap|run|3|slc run overlap --quick"
  "random-viewers|run|2|slc run random-viewers --quick"
  "memory|run|2|slc run memory --quick"
  "stereo|run|3|slc run stereo --quick"
  "meeting-320x180|run|3|slc run meeting --quick --res 320x180"
  "camera-speed|run|1|slc run camera-speed --quick"
  "many-lights|run|2|slc run many-lights --quick"
  "point-lights|run|1|slc run point-lights --quick"
  "envmap|run|1|slc run envmap --quick"
  "slc-error-terms|run|1|slc run slc-error-terms --quick"
  "slc-moving-lights|run|1|slc run slc-moving-lights --quick"
  "crc|run|4|slc run crc --quick"
  "crc-sweeps|md|2|python tools/crc_sweeps.py --md {md}"
  "osc-gi|run|1|slc run osc-gi --quick"
  "osc-gi-160x90|run|2|slc run osc-gi --no-ablations --no-multi --no-memory --retime 3"
  "megaviews|run|1|slc run megaviews --quick"
  "distributed-quick|run|9|slc run distributed --quick"
  "distributed|run|60|slc run distributed"
  "megaviews-scale|jsonl|1|python tools/megaviews_scale.py 65536 262144"
  "regir-sweep|md|1|python tools/regir_sweep.py --scenes atrium sponza --md {md}"
  "bench-rays|text|1|slc bench rays ; slc bench rays --scene sponza"
  "bench-update|text|1|slc bench update --scene atrium ; slc bench update --scene sponza"
)

OUT=out/results
WORK=out/experiments
COLD=1
ONLY=()
LIST=0
README=
pos=0
while [ $# -gt 0 ]; do
  case "$1" in
    --only) shift; while [ $# -gt 0 ] && [ "${1#--}" = "$1" ]; do ONLY+=("$1"); shift; done; continue ;;
    --work) WORK=$2; shift ;;
    --readme) README=$2; shift ;;
    --warm) COLD=0 ;;
    --list) LIST=1 ;;
    -h|--help) sed -n '2,25p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    --*) echo "run_experiments.sh: error: unknown option $1" >&2; exit 2 ;;
    *) [ $pos = 0 ] && OUT=$1 || { echo "run_experiments.sh: error: unexpected argument $1" >&2; exit 2; }; pos=1 ;;
  esac
  shift
done

names=()
total=0
for e in "${RUNS[@]}"; do
  IFS='|' read -r name kind mins cmd <<< "$e"
  names+=("$name")
  total=$((total + mins))
  [ $LIST = 1 ] && printf '%-20s %3s min  %s\n' "$name" "$mins" "$cmd"
done
[ $LIST = 1 ] && { echo "total: about $total min"; exit 0; }
for n in "${ONLY[@]}"; do
  case " ${names[*]} " in *" $n "*) ;; *) echo "run_experiments.sh: error: unknown entry $n (see --list)" >&2; exit 2 ;; esac
done
[ -x "$PY" ] || { echo "run_experiments.sh: error: no interpreter at $PY (make install, or set PYTHON_BIN)" >&2; exit 2; }

mkdir -p "$OUT" "$WORK"
OUT=$(cd "$OUT" && pwd)
WORK=$(cd "$WORK" && pwd)
[ -n "$README" ] && README=$(cd "$(dirname "$README")" && pwd)/$(basename "$README")
cd "$REPO"
[ -z "$README" ] && [ "$OUT" = "$REPO/docs/results" ] && README=$REPO/README.md
tool() { PYTHONPATH="$REPO" "$PY" tools/results_index.py "$@"; }

# One command of an entry: `slc ...` runs this checkout's CLI, `python ...` its interpreter.
exec_cmd() {
  local home=$HOME
  [ $COLD = 1 ] && home=$(mktemp -d)
  local first=$1; shift
  local status=0
  if [ "$first" = slc ]; then
    HOME="$home" PYTHONPATH="$REPO" "$PY" -c 'from slc.run.cli import main; main()' "$@" || status=$?
  else
    HOME="$home" PYTHONPATH="$REPO" "$PY" "$@" || status=$?
  fi
  [ $COLD = 1 ] && rm -rf "$home"
  return $status
}

failed=()
for e in "${RUNS[@]}"; do
  IFS='|' read -r name kind mins cmd <<< "$e"
  if [ ${#ONLY[@]} -gt 0 ]; then
    case " ${ONLY[*]} " in *" $name "*) ;; *) continue ;; esac
  fi
  dir="$WORK/$name"
  rm -rf "$dir"; mkdir -p "$dir"
  ext=md; [ "$kind" = text ] && ext=txt
  log="$dir/run.log"; res="$dir/$name.$ext"
  echo "== $name: $cmd (about $mins min)"
  t0=$(date +%s)
  ok=1
  IFS=';' read -ra parts <<< "$cmd"
  for part in "${parts[@]}"; do
    part=${part//\{md\}/$res}
    read -ra words <<< "$part"
    [ "$kind" = run ] && words+=(--out "$dir")
    if [ "$kind" = text ] || [ "$kind" = jsonl ]; then
      exec_cmd "${words[@]}" 2>>"$log" | tee -a "$res" >>"$log" || ok=0
    else
      exec_cmd "${words[@]}" >>"$log" 2>&1 || ok=0
    fi
  done
  wall=$(( $(date +%s) - t0 ))
  if [ "$kind" = run ]; then
    exp=$(awk '{print $3}' <<< "$cmd")
    cp "$dir/$exp/results.md" "$res" 2>>"$log" || ok=0
  elif [ "$kind" = jsonl ]; then
    tool jsonl-table "$res" "$name: $cmd" > "$res.table" 2>>"$log" && mv "$res.table" "$res" || ok=0
  fi
  if [ $ok = 1 ] && [ -s "$res" ]; then
    tool stamp "$res" --command "$cmd" --wall "$wall" && mv "$res" "$OUT/$name.$ext"
    echo "   $wall s -> $OUT/$name.$ext"
    if [ "$name" = single-viewer-quick ] && [ -n "$README" ]; then
      tool fill-readme "$README" "$OUT/$name.$ext" && echo "   table -> $README" || failed+=("$name:readme")
    fi
  else
    failed+=("$name")
    echo "   FAILED after $wall s (log: $log)"
  fi
done
tool index "$OUT"
echo "index: $OUT/README.md"
if [ ${#failed[@]} -gt 0 ]; then
  echo "failed: ${failed[*]}" >&2
  exit 1
fi
