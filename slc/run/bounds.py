r"""Error bounds: every method family's error on built-in scenes, recorded and compared.

One run per (scene, method) at a fixed small configuration (:data:`CONFIG`:
160x90, one viewer on the scene's first camera path, a few frames, seed 0)
gives FLIP and relative MSE against the method's own reference
(:func:`slc.reference.references.reference_for`: the 2048-sample direct ground truth,
the indirect reference, or both), on the last frame. Each figure is also
divided by the same figure of the method's *partner* in the same run, a
baseline compared with the same reference:

=============  ======================  =========================================
output         partner                 methods
=============  ======================  =========================================
``direct``     ``rt48``                rtN, restir, slc, sh, adaptive
``indirect``   ``pt:output=indirect``  crc, megaviews, manylods, brute
``full``       ``pt``                  osc-gi
=============  ======================  =========================================

A partner has no ratio of its own (it would be 1); its absolute figures are
bounded like every other method's.

The figures live in one table (``tests/data/error_bounds.json``), written
by ``python tools/record_error_bounds.py`` and checked by
``tests/test_error_bounds.py``; both measure with :func:`measure_scene` and
judge with :func:`compare`. A figure more than :data:`TOLERANCE` (10%) above
its recorded value is *worse* (the test fails); more than 10% below it is
*better* (the test passes with a warning asking for a re-record, so that the
bound follows an improvement). Runs are deterministic up to the order of
floating-point atomics, far inside 10%.

Adding a scene: one line in :data:`SCENES` (and in :data:`SCENE_METHODS` to measure some
methods only), then a re-record.
"""
from __future__ import annotations

import json
import math
import re
from dataclasses import asdict, dataclass
from pathlib import Path

from slc import methods as registry
from slc.core.spec import parse_spec
from slc.run.experiment import release_scenes
from slc.run.pipeline import RunConfig, run_sequence
from slc.scene import scenes, views

TABLE = Path(__file__).resolve().parents[2] / "tests" / "data" / "error_bounds.json"
TOLERANCE = 0.10
FIGURES = ("flip", "rel_mse")

# scene -> why it is in the table (one line per scene)
SCENES = {
    "cornell": "closed box, one square ceiling light, a glossy and a diffuse block",
    "atrium": "large court, three small round lamps and one large light, colonnades",
    "village": "glossy slate and iron under a 10 m moon far away and 8 cm torches close by",
    "spheres": "dark room, four spherical lights (radii 0.03-1 m, radiances 1-1e4) over glossy plates",
    "box_export": "Cornell box as exporters write it: rectangles and cubes by matrices, a mirrored cube",
    "lamp_export": "room lit by a small bright rectangle inside a lamp shade and a second rectangle",
    "preview_export": "smooth plastic, glass and metal on a checkered plane under an environment map with a sun",
    "sun_export": "one directional light: hard shadows only",
    "gallery_export": "objects by instances on a rough aluminium floor under a spot, a point and a disk light",
}

# the VPL methods with 1024 VPLs and depth-5 hierarchies (the defaults, 4096 VPLs and depth 7,
# take minutes per frame on a CPU)
_VPL = ":views=1024,scene_depth=5,view_depth=5"

# the method families, each with its settings as run (defaults but for the VPL methods)
METHODS = ("rt16", "rt48", "restir", "regir", "slc", "slc:fetch=bilinear", "sh", "adaptive", "adaptive:polygon_lights=off",
           "crc", "megaviews" + _VPL, "manylods" + _VPL, "brute" + _VPL, "osc-gi", "sharc", "pt", "pt:output=indirect")

# scenes measured with some methods only (the others: every method of METHODS): the exported
# scenes hold the direct-light cache methods a user picks, and their partner
SCENE_METHODS = {name: ("rt48", "slc", "adaptive")
                 for name in ("box_export", "lamp_export", "preview_export", "sun_export", "gallery_export")}

# methods whose frame depends on nothing carried from earlier frames (rtN: any N): only the
# evaluated (last) frame is rendered, the very image a run of every frame ends with
STATELESS = ("rtN", "pt", "megaviews", "manylods", "brute")

# ratio partner of each output kind (slc.methods.OUTPUTS)
PARTNERS = {"direct": "rt48", "indirect": "pt:output=indirect", "full": "pt"}


@dataclass(frozen=True)
class Config:
    """The one configuration every bound is measured at."""
    width: int = 160
    height: int = 90
    frames: int = 10
    seed: int = 0
    path: int = 0           # the scene's camera path of the single viewer

    def key(self) -> dict:
        return asdict(self)


CONFIG = Config()


@dataclass(frozen=True)
class Finding:
    """One figure of one (scene, method) judged against its recorded value."""
    scene: str
    method: str
    figure: str             # flip, rel_mse, flip_ratio or rel_mse_ratio
    recorded: float | None
    measured: float | None
    verdict: str            # worse, better, same, new (not recorded) or missing (recorded, not measured)

    def line(self) -> str:
        def f(v):
            return "-" if v is None else f"{v:.4g}"
        change = ""
        if self.recorded and self.measured is not None and math.isfinite(self.measured):
            change = f" ({(self.measured / self.recorded - 1) * 100:+.1f}%)"
        return (f"{self.verdict:7s} {self.scene}/{self.method} {self.figure}: "
                f"{f(self.recorded)} -> {f(self.measured)}{change}")


# -----------------------------------------------------------------------------
# Measuring
# -----------------------------------------------------------------------------

def stateless(spec: str) -> bool:
    """Whether the method ``spec`` is one of :data:`STATELESS`."""
    name = parse_spec(spec)[0]
    return name in STATELESS or ("rtN" in STATELESS and re.fullmatch(r"rt\d+", name) is not None)


def partner_of(output: str) -> str:
    return PARTNERS[output]


def methods_for(scene_name: str) -> tuple:
    """The methods the table holds for ``scene_name`` (:data:`SCENE_METHODS`, else :data:`METHODS`)."""
    return SCENE_METHODS.get(scene_name, METHODS)


def measure_scene(scene_name: str, methods=None, cfg: Config = CONFIG, progress=None) -> dict:
    """{method: {"partner", "flip", "rel_mse"[, "flip_ratio", "rel_mse_ratio"]}} of one
    scene: every method of ``methods`` (default :func:`methods_for` the scene; and the
    partners they need) run once in this process, the scene loaded once. ``progress(spec)``
    is called before each run."""
    methods = methods_for(scene_name) if methods is None else methods

    def run_cfg(spec):
        n = 1 if stateless(spec) else cfg.frames
        return RunConfig(width=cfg.width, height=cfg.height, frames=n, start_frame=cfg.frames - n, warmup=0,
                         seed=cfg.seed, keep_images=False, measure_overlap=False)
    scene = scenes.load(scene_name)
    try:
        viewers = [views.single(scene, cfg.path)[0]]
        made = {spec: registry.create(spec, scene, seed=cfg.seed) for spec in methods}
        for spec in list(made):
            p = partner_of(made[spec].output)
            if p not in made:
                made[p] = registry.create(p, scene, seed=cfg.seed)
        raw = {}
        for spec, m in made.items():
            if progress is not None:
                progress(spec)
            res = run_sequence(scene, m, viewers, run_cfg(spec))
            raw[spec] = {"output": m.output, **{k: float(res.metrics[k]) for k in FIGURES}}
            made[spec] = None            # release the method's state before the next run
    finally:
        del scene
        release_scenes()
    out = {}
    for spec, r in raw.items():
        p = partner_of(r["output"])
        row = {"partner": None if p == spec else p, **{k: r[k] for k in FIGURES}}
        if p != spec:
            for k in FIGURES:
                row[f"{k}_ratio"] = _ratio(r[k], raw[p][k])
        out[spec] = row
    return out


def _ratio(a: float, b: float) -> float:
    if b > 0.0 and math.isfinite(b):
        return a / b
    return math.inf if a > 0.0 else 1.0


# -----------------------------------------------------------------------------
# Judging (the one comparison, used by the recording tool and the test)
# -----------------------------------------------------------------------------

def judge(recorded: float | None, measured: float | None, tol: float = TOLERANCE) -> str:
    """``worse`` above ``(1 + tol)`` x recorded (or not finite), ``better`` below
    ``(1 - tol)`` x recorded, else ``same``; ``new`` / ``missing`` when one side is absent."""
    if recorded is None:
        return "new"
    if measured is None:
        return "missing"
    if not math.isfinite(measured):
        return "same" if measured == recorded else "worse"
    if measured > recorded * (1.0 + tol):
        return "worse"
    if measured < recorded * (1.0 - tol):
        return "better"
    return "same"


def compare_row(scene: str, method: str, recorded: dict | None, measured: dict | None,
                tol: float = TOLERANCE) -> list[Finding]:
    """Findings of every figure of one (scene, method): absolute and ratio."""
    recorded, measured = recorded or {}, measured or {}
    out = []
    for fig in (*FIGURES, *(f"{k}_ratio" for k in FIGURES)):
        r, m = recorded.get(fig), measured.get(fig)
        if r is None and m is None:
            continue
        out.append(Finding(scene, method, fig, r, m, judge(r, m, tol)))
    if recorded and measured and recorded.get("partner") != measured.get("partner"):
        out.append(Finding(scene, method, "partner", None, None, "worse"))
    return out


def compare(recorded: dict, measured: dict, tol: float = TOLERANCE) -> list[Finding]:
    """Findings of two tables' ``scenes`` parts ({scene: {method: row}}), over the
    scenes and methods of ``measured``; a recorded scene not measured is skipped."""
    out = []
    for scene, rows in measured.items():
        rec = recorded.get(scene, {})
        for method in {**rec, **rows}:
            out += compare_row(scene, method, rec.get(method), rows.get(method), tol)
    return out


# -----------------------------------------------------------------------------
# The table
# -----------------------------------------------------------------------------

def load_table(path: Path = TABLE) -> dict:
    """The recorded table: {"config": ..., "tolerance": ..., "scenes": {scene: {method: row}}}."""
    path = Path(path)
    if not path.exists():
        return {"config": CONFIG.key(), "tolerance": TOLERANCE, "scenes": {}}
    return json.loads(path.read_text())


def write_table(scenes: dict, path: Path = TABLE, cfg: Config = CONFIG) -> None:
    def rounded(row):
        return {k: (float(f"{v:.6g}") if isinstance(v, float) else v) for k, v in row.items()}
    obj = {"config": cfg.key(), "tolerance": TOLERANCE,
           "scenes": {s: {m: rounded(r) for m, r in rows.items()} for s, rows in scenes.items()}}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=1) + "\n")
