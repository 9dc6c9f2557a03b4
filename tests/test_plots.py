"""Every plot function rendered on small synthetic rows: no text leaves the canvas (the tight
bounding box of every Text artist inside the figure), point labels overlap neither each other
nor the title, a speed-against-error plot keeps its axes at nearly full width with long
settings, and a time axis spanning a decade or more is logarithmic."""
import itertools

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pytest  # noqa: E402
from matplotlib.text import Annotation, Text  # noqa: E402

from slc.run import experiment as ex  # noqa: E402
from slc.run import plots  # noqa: E402

LONG = "osc-gi:direct=cache,texel_rays=32,n_max=8,secondary_scene=0,glossy_samples=8,secondary_cm=30,secondary_rays=32"


@pytest.fixture
def figures(monkeypatch):
    """The figures a plot function made (plt.close deferred), closed afterwards."""
    monkeypatch.setattr(plt, "close", lambda *a, **k: None)
    before = set(plt.get_fignums())
    made = []
    yield lambda: made.extend(plt.figure(n) for n in plt.get_fignums() if n not in before) or made
    plt.close("all")


def text_boxes(fig):
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    hidden = set()          # tick labels outside the view limits: made, never drawn
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            drawn = {id(x) for tick in axis._update_ticks() for x in (tick.label1, tick.label2)}
            hidden |= {id(x) for tick in axis.get_major_ticks() + axis.get_minor_ticks()
                       for x in (tick.label1, tick.label2) if id(x) not in drawn}
    out = []
    for t in fig.findobj(Text):
        if not t.get_visible() or not t.get_text().strip() or id(t) in hidden:
            continue
        if isinstance(t, Annotation):
            t.update_positions(r)
        out.append((t, Text.get_window_extent(t, r)))
    return out


def layout_problems(fig) -> list[str]:
    boxes = text_boxes(fig)
    fb = fig.bbox
    bad = [f"{t.get_text()!r} leaves the canvas ({bb} outside {fb})" for t, bb in boxes
           if bb.x0 < fb.x0 - 1 or bb.y0 < fb.y0 - 1 or bb.x1 > fb.x1 + 1 or bb.y1 > fb.y1 + 1]
    for ax in fig.axes:
        labels = [(t, bb) for t, bb in boxes if t in ax.texts]
        title = [(t, bb) for t, bb in boxes if t in (ax.title, ax._left_title, ax._right_title)]
        for (a, ba), (b, bb) in itertools.combinations(labels + title, 2):
            if ba.overlaps(bb):
                bad.append(f"{a.get_text()!r} overlaps {b.get_text()!r}")
    return bad


def speed_rows():
    pt = [dict(method="pt", label=f"pt:spp={n}", family="pt", time_ms=20.0 * n, flip=0.4 / n ** 0.5)
          for n in (1, 2, 4, 8, 16, 32, 64)]
    osc = [dict(method="osc-gi", label=label, family="osc-gi", time_ms=60 + 2 * i, flip=0.08 + 0.002 * (i % 4))
           for i, label in enumerate(["osc-gi", LONG, "osc-gi:direct=cache", "osc-gi:direct=cones",
                                      "osc-gi:direct=restir", "osc-gi:direct=rt,direct_n=4", LONG + ",bias=1",
                                      "osc-gi:freeze=0", "osc-gi:glossy_hits=0"])]
    return pt + osc


def test_speed_error_plot_reads(tmp_path, figures):
    plots.speed_error_plot(tmp_path / "se.png", speed_rows(), "cornell: full light, time vs FLIP (160x90)")
    (fig,) = figures()
    assert layout_problems(fig) == []
    ax = fig.axes[0]
    assert ax.get_xscale() == "log"                     # 20 .. 1280 ms
    assert ax.get_position().width > 0.75               # the key of long settings sits under the axes
    texts = [t.get_text() for t in ax.texts]
    assert max(len(t) for t in texts) <= plots.SHORT_NAME and "spp=64" in texts
    assert (tmp_path / "se.png").stat().st_size > 0


def test_speed_error_plot_names_points_by_what_differs(tmp_path, figures):
    rows = [dict(method="pt", label=f"pt:spp={n},output=indirect", family="pt", time_ms=2.0 * n, flip=0.3 / n ** 0.5)
            for n in (1, 2, 4, 8, 16)] + [dict(method="osc-gi", label="osc-gi:output=indirect", family="osc-gi",
                                               time_ms=40.0, flip=0.1)]
    plots.speed_error_plot(tmp_path / "se.png", rows, "cornell: indirect light, time vs FLIP (64x36)")
    (fig,) = figures()
    assert layout_problems(fig) == []
    ax = fig.axes[0]
    assert sorted(t.get_text() for t in ax.texts) == sorted(["output=indirect"] + [f"spp={n}" for n in (1, 2, 4, 8, 16)])
    assert "pt (output=indirect)" in [t.get_text() for t in ax.get_legend().get_texts()]


def test_speed_error_plot_linear_when_times_are_close(tmp_path, figures):
    rows = [dict(method=m, label=m, time_ms=t, flip=f) for m, t, f in
            [("rt16", 10.0, 0.2), ("rt48", 28.0, 0.12), ("slc", 12.0, 0.1), ("restir", 15.0, 0.11)]]
    plots.speed_error_plot(tmp_path / "se.png", rows, "atrium: time vs FLIP (160x90)")
    (fig,) = figures()
    assert layout_problems(fig) == [] and fig.axes[0].get_xscale() == "linear"


def test_time_vs_viewers_plot_reads(tmp_path, figures):
    rows = [dict(method=m, overlap=o, viewers=n, time_ms=(5 if m == "slc" else 20) * n ** (0.5 if o else 1.0),
                 measured_overlap=100.0 * o * (n > 1)) for m in ("slc", "rt48", "restir")
            for o in (0.0, 0.5, 1.0) for n in (1, 4, 16)]
    plots.time_vs_viewers_plot(tmp_path / "t.png", rows, "atrium: time against viewers (96x54, 24 frames)",
                            group=("method", "overlap"))
    (fig,) = figures()
    assert layout_problems(fig) == []
    assert fig.axes[0].get_yscale() == "log"            # 5 .. 320 ms


def test_metric_vs_value_plot_reads(tmp_path, figures):
    specs = ["rt48", "restir", "slc:max_cones=1", "slc:max_cones=2", "slc:max_cones=3", "slc:max_cones=4", "adaptive"]
    rows = [dict(method=s.split(":")[0], setting=s, lights=n, flip=0.1 + 0.01 * i, time_ms=10.0 + i * n)
            for i, s in enumerate(specs) for n in (3, 12, 24)]
    plots.metric_vs_value_plot(tmp_path / "m.png", rows, "lights", "hangar: FLIP and time against the light count")
    (fig,) = figures()
    assert layout_problems(fig) == []


def test_experiment_stage_plots_read(tmp_path, figures):
    crc, osc_gi = ex.load_part("crc_report"), ex.load("osc-gi")
    from slc.methods.crc.cache import CRCCache
    stages = CRCCache.FIXED_STAGES + CRCCache.COEFFICIENT_STAGES
    sweep = [dict(resolution=n, occupancy_ratio=0.3 + 0.1 * i, **{k: 1.0 + i for k in stages})
             for i, n in enumerate((16, 32, 64, 128))]
    crc.plot_sweep(tmp_path / "fig10.png", sweep, "Fig. 10: cornell, 2 bounces, Y3Co1Cg1")
    rows = [dict(variant="", visibility="march", chroma="offset", encoding=e, occupancy=occ, time_ms=3.0 + i,
                 lab_rmse_final=0.5 * i, lab_rmse_final_vs_ref=1.0 + i, coefficients=c)
            for i, (e, c, occ) in enumerate([("rgb3", 27, True), ("y3co1cg1", 11, True), ("y2co2cg2", 12, True),
                                             ("rgb3", 27, False)])]
    crc.plot(tmp_path / "crc.png", rows, "cornell, 2 bounce(s), 160x90")
    import numpy as np
    img = {"final": np.full((9, 16, 3), 0.3), "indirect": np.full((9, 16, 3), 0.05)}

    class Scene:
        name, exposure = "village:sun=1", 1.0
    crc.protocol_strip(tmp_path, Scene, 1, {"lab_rmse_final": 0.92, "indirect_lit_pixels": 0.041,
                                            "_images": {"y3co3cg3": img, "y3co1cg1": img},
                                            "_de_map": np.linspace(0, 4, 144).reshape(9, 16),
                                            "_indirect_lit": np.eye(9, 16, dtype=bool)})
    osc_gi._reuse_plot(tmp_path / "reuse.png", {"bins": [1, 2, 4, 8, 16, 1 << 21], "counts": [50, 30, 10, 5, 1]},
                       "cornell: primary rays per secondary cell")
    figs = figures()
    assert len(figs) == 4
    for fig in figs:
        assert layout_problems(fig) == [], fig.axes[0].get_title()


def test_megaviews_plots_read(tmp_path, figures):
    mv, report = ex.load("megaviews"), ex.load_part("megaviews_report")
    rows = [dict(scene=s, sweep=sw, method=m, views=v, resolution=res, time_ms=(1 + i) * v / 64 * res / 16,
                 memory_mb=(1 + i) * v / 256, views_per_render=v / 64)
            for s in ("cornell", "atrium") for i, m in enumerate(mv.METHODS)
            for sw, pts in (("views", [(v, 16) for v in (256, 1024, 4096, 16384)]),
                            ("resolution", [(1024, r) for r in (16, 32, 64, 128)]))
            for v, res in pts]
    report.plots(mv, tmp_path, rows)
    figs = figures()
    assert len(figs) == 2
    for fig in figs:
        assert layout_problems(fig) == []
