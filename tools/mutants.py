"""Inject named faults into the methods, one at a time, and run the tests that should catch each.

    python tools/mutants.py                 # every fault; one line each, then "killed K of N"
    python tools/mutants.py --list          # the faults and the tests that should kill them
    python tools/mutants.py NAME [NAME...]  # these faults only
    python tools/mutants.py --check         # every fault still applies (its text occurs once); runs no test

Each fault is (name, file, the exact text it replaces, the replacement, the tests that should
fail). The repository's files (tracked and untracked, not ignored, as they are in the working
tree) are copied once into a temporary directory with ``../shared`` beside it; the tests are
run there on the unchanged copy first (they must pass, or a failure would prove nothing), then
for each fault: its file is changed in the copy, its tests run (``pytest -x``), the file is
restored. A fault is *killed* when its tests fail. The working tree is never written.

A fault whose text no longer occurs exactly once in its file (the code it aimed at was changed
or moved) stops the tool with an error naming it: update the fault, don't drop it. The list,
with the tests that kill each fault, is in docs/testing.md.

Exit status: 0 when every fault run is killed, 1 when one survives (or the unchanged copy
fails its tests), 2 on bad input (an unknown fault, a fault that no longer applies).
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Fault:
    name: str
    file: str                 # path in the repository
    old: str                  # exact text, found exactly once in ``file``
    new: str                  # what replaces it
    tests: tuple              # pytest node ids (from the repository root), at least one must fail
    what: str                 # the fault in one line


FAULTS = (
    Fault("cone-radiance-x1.05", "slc/lib/cones/conestate.py",
          "axis=Dw, alpha=A, L=L,", "axis=Dw, alpha=A, L=[x * 1.05 for x in L],",
          ("tests/test_cones.py::test_small_light_diffuse_plane_converges[pixel]",),
          "every cone's radiance L_c read 5% too bright by the shading"),
    Fault("sh-band-2-dropped", "slc/lib/sh/basis.py",
          "A_HAT = (math.pi, 2.0 * math.pi / 3.0, math.pi / 4.0)", "A_HAT = (math.pi, 2.0 * math.pi / 3.0, 0.0)",
          ("tests/test_sh.py::test_clamped_cosine_lobe_coefficients_and_irradiance",),
          "the SH irradiance drops band 2 (its cosine-lobe factor is 0)"),
    Fault("visibility-sample-skipped", "slc/methods/adaptive/visibility/update.py",
          "e.texel, e.key, mix, ls.k), s.ok)", "e.texel, e.key, mix, ls.k), s.ok & (ls.k > 0))",
          ("tests/test_adaptive_polygons.py::test_half_occluded_large_light",),
          "the first light sample of each VISIBILITY update is taken as visible without its shadow ray"),
    Fault("reservoir-weight-without-M", "slc/methods/restir/reuse.py",
          "m_p = share(M_p * p_pp,", "m_p = share(p_pp,",
          ("tests/test_restir.py::test_converges_to_ground_truth",),
          "ReSTIR's temporal pairwise MIS weight of the history reservoir ignores its confidence M"),
    Fault("regir-history-weight-without-M", "slc/methods/regir/method.py",
          "p_old * old.W * M_old * inv", "p_old * old.W * inv",
          ("tests/test_regir.py::test_regir_per_pixel_z_test[regir-4]",),
          "ReGIR's temporal merge weighs a grid reservoir's history without its confidence M"),
    Fault("adaptive-never-switches", "slc/methods/adaptive/choice.py",
          "return dr.select(h.e > 0.0, t, h.tag)", "return mi.UInt32(h.tag)",
          ("tests/test_adaptive.py::test_point_light_chooses_visibility_and_matches_ground_truth",),
          "the adaptive cache keeps every entry in its first representation"),
    Fault("adaptive-forced-to-cones", "slc/methods/adaptive/choice.py",
          "t = dr.select(vis, mi.UInt32(VIS), dr.select(wide, mi.UInt32(SH), mi.UInt32(CONES)))",
          "t = dr.full(mi.UInt32, CONES, dr.width(R))",
          ("tests/test_error_bounds.py::test_error_within_recorded_bound[adaptive-cornell]",),
          "the adaptive cache's choice rule asks for cones for every entry"),
    Fault("adaptive-glossy-rules-dropped", "slc/methods/adaptive/choice.py",
          "return glossy_lobes(scene, si.bsdf(), si.is_valid()) >= GLOSSY_SHARE", "return None",
          ("tests/test_error_bounds.py::test_error_within_recorded_bound[adaptive-gallery_export]",),
          "no entry counts as glossy: a light in a glossy entry's VISIBILITY residual is shaded as uniform "
          "radiance"),
    Fault("new-entry-rays-halved", "slc/methods/cache_method.py",
          "r_new = mi.UInt32(self.new)", "r_new = mi.UInt32(self.new // 2)",
          ("tests/test_error_bounds.py::test_error_within_recorded_bound[slc-atrium]",),
          "a new cache entry traces half the update rays of the ray policy"),
    Fault("polygon-light-flipped", "slc/lib/lights/polygon_lights.py",
          "front = m & (dr.dot(p - p0, dr.cross(e0, e1)) > 0.0)", "front = m & (dr.dot(p - p0, dr.cross(e0, e1)) < 0.0)",
          ("tests/test_adaptive_polygons.py::test_unoccluded_square_light_is_exact",),
          "a polygon light's exact irradiance is taken from its back side"),
    Fault("light-pdf-guard-removed", "slc/scene/emitter_sampling.py",
          "ok = active & (pdf > 0.0)\n", "ok = active\n",
          ("tests/test_hard_cases.py::test_rt_hard_cases_per_pixel_z_test[grazing]",),
          "a light sample of density 0 (the back of a one-sided emitter) is kept: L_e / 0"),
    Fault("megaviews-shadows-skipped", "slc/methods/megaviews/vpl.py",
          "        if shadows:", "        if False:",
          ("tests/test_megaviews.py::test_against_the_indirect_reference[megaviews]",),
          "MegaViews gathers every VPL without its shadow-map test"),
)


def by_name() -> dict:
    return {f.name: f for f in FAULTS}


def problems(root: Path = ROOT, faults=FAULTS) -> list[str]:
    """Why faults no longer apply to the source under ``root`` (empty: every one applies):
    its file missing, its text not found exactly once, a replacement equal to it, or a test
    whose file or function no longer exists."""
    out = []
    names = [f.name for f in faults]
    for n in sorted({n for n in names if names.count(n) > 1}):
        out.append(f"{n}: two faults of this name")
    for f in faults:
        p = root / f.file
        if not p.is_file():
            out.append(f"{f.name}: {f.file} does not exist")
            continue
        n = p.read_text().count(f.old)
        if n != 1:
            out.append(f"{f.name}: its text occurs {n} times in {f.file} (must be once): {f.old.strip()!r}")
        if f.old == f.new:
            out.append(f"{f.name}: the replacement is the text itself")
        if not f.tests:
            out.append(f"{f.name}: no test")
        for t in f.tests:
            path, _, func = t.partition("::")
            func = func.split("[", 1)[0]
            tp = root / path
            if not tp.is_file() or f"def {func}(" not in tp.read_text():
                out.append(f"{f.name}: test {t} not found")
    return out


# -----------------------------------------------------------------------------
# Running
# -----------------------------------------------------------------------------

def copy_repository(dest: Path) -> Path:
    """The repository's files (tracked and untracked, not ignored) copied to ``dest/<name>``,
    with ``dest/shared`` pointing at the data beside the repository; returns the copy."""
    files = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                           capture_output=True, check=True).stdout.decode().split("\0")
    repo = dest / ROOT.name
    for rel in files:
        src = ROOT / rel
        if rel and src.is_file():
            (repo / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, repo / rel)
    shared = ROOT.parent / "shared"
    if shared.exists():
        (dest / "shared").symlink_to(shared.resolve())
    return repo


def run_tests(repo: Path, tests, timeout: int = 3600) -> subprocess.CompletedProcess:
    """``pytest -x`` on ``tests`` in the copy, importing the copy's ``slc``."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(repo) + os.pathsep + env.get("PYTHONPATH", "")
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", "--no-header",
                           *tests], cwd=repo, env=env, capture_output=True, text=True, timeout=timeout)


def _tail(p: subprocess.CompletedProcess, n: int = 25) -> str:
    return "\n".join((p.stdout + p.stderr).strip().splitlines()[-n:])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="*", help="faults to run (default: all; --list names them)")
    ap.add_argument("--list", action="store_true", help="print the faults and their tests, run nothing")
    ap.add_argument("--check", action="store_true",
                    help="check that every fault still applies to the source, run no test")
    ap.add_argument("--keep", action="store_true", help="keep the temporary copy (its path is printed)")
    opts = ap.parse_args(argv)

    known = by_name()
    unknown = [n for n in opts.names if n not in known]
    if unknown:
        print(f"mutants: error: unknown fault '{unknown[0]}' (python tools/mutants.py --list)", file=sys.stderr)
        return 2
    faults = [known[n] for n in opts.names] if opts.names else list(FAULTS)
    if opts.list:
        for f in faults:
            print(f"{f.name}: {f.what}\n    {f.file}\n    killed by: {' '.join(f.tests)}")
        return 0
    bad = problems(ROOT, faults)
    if bad:
        for b in bad:
            print(f"mutants: error: {b}", file=sys.stderr)
        print("mutants: update the fault in tools/mutants.py (and docs/testing.md) to the current code",
              file=sys.stderr)
        return 2
    if opts.check:
        print(f"{len(faults)} faults apply")
        return 0

    tmp = Path(tempfile.mkdtemp(prefix="slc-mutants-"))
    try:
        repo = copy_repository(tmp)
        print(f"copy: {repo}", flush=True)
        tests = list(dict.fromkeys(t for f in faults for t in f.tests))
        t0 = time.perf_counter()
        base = run_tests(repo, tests)
        if base.returncode != 0:
            print(f"the unchanged copy fails its tests (exit status {base.returncode}); nothing is measured:\n"
                  f"{_tail(base)}", file=sys.stderr)
            return 1
        print(f"unchanged: {len(tests)} tests pass ({time.perf_counter() - t0:.0f} s)", flush=True)
        killed, survived = [], []
        for f in faults:
            path = repo / f.file
            text = path.read_text()
            path.write_text(text.replace(f.old, f.new, 1))
            t0 = time.perf_counter()
            try:
                p = run_tests(repo, f.tests)
            finally:
                path.write_text(text)
            dt = time.perf_counter() - t0
            if p.returncode == 1:
                failed = [x.split(" ", 1)[1].split(" - ")[0] for x in p.stdout.splitlines() if x.startswith("FAILED ")]
                why = next((x[1:].strip() for x in p.stdout.splitlines() if x.startswith("E ")), "")
                killed.append(f.name)
                print(f"killed    {f.name} ({dt:.0f} s): {', '.join(failed) or 'tests failed'}\n"
                      f"          {why[:160]}", flush=True)
            elif p.returncode == 0:
                survived.append(f.name)
                print(f"SURVIVED  {f.name} ({dt:.0f} s): {' '.join(f.tests)} pass with the fault", flush=True)
            else:
                print(f"mutants: error: {f.name}: pytest exit status {p.returncode} (not a test failure):\n"
                      f"{_tail(p)}", file=sys.stderr)
                return 2
        print(f"killed {len(killed)} of {len(faults)}")
        return 0 if not survived else 1
    finally:
        if opts.keep:
            print(f"kept: {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
