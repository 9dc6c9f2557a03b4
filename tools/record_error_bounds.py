"""Record the error-bound table (tests/data/error_bounds.json) and print what changed.

    python tools/record_error_bounds.py                 # measure every scene, print changes, write the table
    python tools/record_error_bounds.py --scene cornell # only these scenes (the others' rows are kept)
    python tools/record_error_bounds.py --dry-run       # print changes, write nothing

Every (scene, method) of slc.run.bounds.SCENES x slc.run.bounds.METHODS is run once at
slc.run.bounds.CONFIG (160x90, a few frames) and compared with the recorded row by
slc.run.bounds.compare, the comparison tests/test_error_bounds.py makes: each figure
is printed as worse (> +10%: the test would fail), better (< -10%: the test asks
for a re-record), new or missing; unchanged figures are counted. References come
from the disk cache ($SLC_CACHE) when present. Exit status: 0, or 2 on bad input.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", action="append", default=None,
                   help="scene to measure (repeatable; default: every scene of slc.run.bounds.SCENES)")
    p.add_argument("--dry-run", action="store_true", help="print the changes, do not write the table")
    p.add_argument("--table", default=None, help="table path (default: tests/data/error_bounds.json)")
    opts = p.parse_args(argv)

    from slc.run import bounds
    from slc.methods import MethodError
    from slc.scene.checks import SceneError

    table_path = Path(opts.table) if opts.table else bounds.TABLE
    names = opts.scene or list(bounds.SCENES)
    unknown = [n for n in names if n not in bounds.SCENES]
    if unknown:
        print(f"record_error_bounds: error: scene '{unknown[0]}' is not in slc.run.bounds.SCENES "
              f"({', '.join(bounds.SCENES)})", file=sys.stderr)
        return 2
    table = bounds.load_table(table_path)
    recorded = table.get("scenes", {}) if table.get("config") == bounds.CONFIG.key() else {}
    if table.get("scenes") and not recorded:
        print("recorded table has another configuration: every figure is new")
    measured = {}
    try:
        for name in names:
            t0 = time.perf_counter()
            measured[name] = bounds.measure_scene(name, progress=lambda spec, n=name: print(f"  {n} {spec}",
                                                                                             flush=True))
            print(f"{name}: {len(measured[name])} methods in {time.perf_counter() - t0:.0f} s")
    except (SceneError, MethodError) as e:
        print(f"record_error_bounds: error: {e}", file=sys.stderr)
        return 2
    findings = bounds.compare(recorded, measured)
    same = [f for f in findings if f.verdict == "same"]
    for f in findings:
        if f.verdict != "same":
            print(f.line())
    drift = max((abs(f.measured / f.recorded - 1.0) for f in same if f.recorded), default=0.0)
    print(f"{len(same)} figures within {bounds.TOLERANCE:.0%} of the recorded ones (largest change "
          f"{drift:.2%}), {len(findings) - len(same)} changed, new or missing")
    if opts.dry_run:
        return 0
    rows = {**recorded, **measured}
    bounds.write_table({s: rows[s] for s in bounds.SCENES if s in rows}, table_path)
    print(f"wrote {table_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
