"""The crc experiment's protocol of the CRC paper's Table 1 (experiments/crc.py, docs/sh-crc.md):
Lab RMSE and pdiff of the final frame and of the indirect light alone, against Y3Co3Cg3 and
RGB3, under the row fields of results.json; the attribution of Y3Co1Cg1's difference to pixels
and lights; the scenes it adds (``village:sun=1``, ``lamps:lights=2``)."""
import json

import mitsuba as mi
import numpy as np
import pytest

from slc import methods
from slc.methods.crc.quality import pdiff
from slc.reference.metrics import lab_rmse
from slc.run import experiment as ex
from slc.scene import scenes, views
from slc.scene.gbuffer import to_image

from helpers import render_frames, slc_cli

W, H = 32, 18
#: a cheap configuration: coarse grid, few samples, small RSMs
CHEAP = dict(resolution=6, samples=8, rsm_size=8, bounces=1)


@pytest.fixture(scope="module")
def protocol():
    return ex.load_part("crc_protocol")


def _row(encoding, chroma="offset", variant="", occupancy=True, time_ms=10.0):
    return dict(encoding=encoding, chroma=chroma, variant=variant, occupancy=occupancy, visibility="march",
                time_ms=time_ms)


def _images(direct, indirect):
    return {7: {"direct": direct, "indirect": indirect, "final": direct + indirect}}


def test_protocol_fields_and_references(protocol):
    """``compare``: every PROTOCOL field of every row, named for the image and the reference
    (``lab_rmse_final``, ``pdiff_final`` against Y3Co3Cg3 as results.json's contract names
    them; ``*_vs_rgb3``); zero against itself; the final frame at the scene's exposure (a
    grey 0.18 -> 0.2016 step is dE76 2.52, one pdiff failure per differing pixel only when
    above threshold); the indirect light alone at the exposure its reference gives (scaling
    both indirect images alike changes nothing); variants without a reference get None."""
    class S:
        exposure = 1.0
    direct = np.full((16, 16, 3), 0.09)
    ind = np.full((16, 16, 3), 0.09)
    test_ind = ind.copy()
    test_ind[:4] = 0.09 + 0.0216            # the top quarter: final 0.18 -> 0.2016
    group = [_row("rgb3", occupancy=False, time_ms=20.0), _row("rgb3"), _row("y3co3cg3"), _row("y3co1cg1"),
             _row("y3co1cg1", variant="dense")]
    imgs = [_images(direct, ind), _images(direct, ind), _images(direct, ind), _images(direct, test_ind),
            _images(direct, test_ind)]
    protocol.compare(group, imgs, S)
    keys = {protocol.field_name(m, i, r) for m in protocol.PROTOCOL["measures"] for i in protocol.PROTOCOL["images"]
            for r in protocol.PROTOCOL["references"]}
    assert {"lab_rmse_final", "pdiff_final", "lab_rmse_indirect", "pdiff_indirect", "lab_rmse_final_vs_rgb3",
            "pdiff_final_vs_rgb3", "lab_rmse_indirect_vs_rgb3", "pdiff_indirect_vs_rgb3"} == keys
    unopt, rgb3, y333, y311, dense = group
    assert all(y333[k] == 0.0 and rgb3[k] == 0.0 for k in keys)
    assert all(dense[k] is None for k in keys) and unopt["lab_rmse_final"] is None
    assert unopt["lab_rmse_final_vs_rgb3"] == 0.0            # its own RGB3 row (occupancy off)
    # final frame: dE76 2.52 on a quarter of the pixels -> RMS 1.26 (percent: dE 1 = 1%)
    assert y311["lab_rmse_final"] == pytest.approx(2.52 / 2, abs=0.02)
    assert y311["lab_rmse_final_vs_rgb3"] == y311["lab_rmse_final"]
    assert y311["de76_fraction_final"] == pytest.approx(25.0)
    assert y311["pdiff_final"] == pdiff(direct + ind, direct + test_ind, 1.0)
    # the indirect light alone is shown at 0.8 / p99 of its reference: 0.09 -> 0.8, 0.1116 -> 0.992
    want = lab_rmse(ind, test_ind, 0.8 / 0.09)
    assert y311["lab_rmse_indirect"] == pytest.approx(want, rel=1e-9) and want > 3 * y311["lab_rmse_final"]
    assert y311["pdiff_indirect"] == pdiff(ind, test_ind, 0.8 / 0.09)
    scaled = [_images(direct, 3.0 * im[7]["indirect"]) for im in imgs]
    g2 = [dict(r) for r in group]
    protocol.compare(g2, scaled, S)
    assert g2[3]["lab_rmse_indirect"] == pytest.approx(y311["lab_rmse_indirect"], rel=1e-6)
    assert g2[3]["lab_rmse_final"] != pytest.approx(y311["lab_rmse_final"], rel=1e-3)
    assert y311["time_vs_rgb3"] == 1.0 and y311["time_vs_unoptimized"] == 0.5


def test_village_sun_is_one_directional_light_feeding_the_cache():
    """``village:sun=1``: one emitter, a directional light (no moon, no torch lights), a name
    of its own (references never mix with the night village's); its RSM gives the cache
    indirect light (finite, non-negative, not zero) at a small frame."""
    night, day = scenes.load("village"), scenes.load("village:sun=1")
    kinds = [e.class_name() for e in day.mi_scene.emitters()]
    assert kinds == ["DirectionalEmitter"], kinds
    assert len(night.mi_scene.emitters()) == 8 and day.name == "village:sun=1" != night.name
    del night
    with pytest.raises(scenes.SceneError, match="sun must be 0 or 1"):
        scenes.load("village:sun=noon")
    m = methods.create("crc", day, **CHEAP)
    imgs, gbs = render_frames(day, m, views.single(day), 1, W, H)
    ind = to_image(gbs[0], m.shade(methods.FrameContext(0), None, 0, gbs[0]))
    assert np.isfinite(ind).all() and (ind >= 0).all() and ind.mean() > 0


def test_only_light_splits_the_cache_into_its_lights():
    """The attribution's per-light runs: with all but one light off (``only_light``) the
    Y3Co3Cg3 caches of the two lights of ``lamps:lights=2`` add up to the cache of both (the
    coefficients are linear in the lights; the images too but where the clamp of negative
    irradiance to 0 acts), each light gives some of it, and leaving the block restores every
    light exactly."""
    terms = ex.load_part("crc_terms")
    s = scenes.load("lamps:lights=2")          # a private copy: its lights are switched off and on
    before = [{k: np.array(v) for k, v in mi.traverse(e).items() if k in terms.LIGHT_PARAMS}
              for e in s.mi_scene.emitters()]
    v = views.single(s)

    def cache():
        m = methods.create("crc", s, encoding="y3co3cg3", **CHEAP)
        render_frames(s, m, v, 1, W, H)
        return np.array(m.cache)
    both = cache()
    parts = []
    for k in range(2):
        with terms.only_light(s, k):
            parts.append(cache())
    assert all(np.abs(p).sum() > 1e-3 * np.abs(both).sum() for p in parts)
    assert np.allclose(parts[0] + parts[1], both, rtol=1e-4, atol=1e-5 * np.abs(both).max())
    after = [{k: np.array(v) for k, v in mi.traverse(e).items() if k in terms.LIGHT_PARAMS}
             for e in s.mi_scene.emitters()]
    assert all(a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a) for a, b in zip(after, before))
    assert terms.light_names(s) == ["wall_lamp_011 (PointLight)", "ceiling_spot_012 (SpotLight)"]


@pytest.mark.slow
def test_experiment_writes_the_protocol_fields(tmp_path):
    """``slc run crc`` at a tiny size: every Table 1 row of results.json carries the
    protocol's fields (``lab_rmse_final``, ``pdiff_final`` against Y3Co3Cg3 and the others),
    Y3Co3Cg3 and RGB3 give the same images (0 against each other), Y3Co1Cg1 differs; the
    attribution rows split its final-frame error into pixels (shares within [0, 1]) and name
    the light; the report has the targets and the attribution's figure."""
    out = tmp_path / "out"
    r = slc_cli(["run", "crc", "--quick", "--scene", "cornell", "--res", "32x18", "--frames", "3", "--grid", "4",
                 "--bounces", "1", "--out", out])
    assert r.returncode == 0, r.stderr
    res = json.loads((out / "crc" / "results.json").read_text())
    std = {(x["encoding"], x["chroma"]): x for x in res["rows"] if x["variant"] == "" and x["occupancy"]}
    for x in std.values():
        for k in ("lab_rmse_final", "pdiff_final", "lab_rmse_indirect", "pdiff_indirect", "lab_rmse_final_vs_rgb3",
                  "pdiff_final_vs_rgb3", "lab_rmse_indirect_vs_rgb3", "pdiff_indirect_vs_rgb3",
                  "lab_rmse_final_vs_ref", "flip"):
            assert isinstance(x[k], float) and np.isfinite(x[k]), (k, x)
    assert std[("rgb3", "offset")]["lab_rmse_final"] < 1e-3 and std[("y3co3cg3", "offset")]["lab_rmse_final"] == 0
    y311 = std[("y3co1cg1", "offset")]
    assert y311["lab_rmse_final"] > 1e-3 and y311["lab_rmse_indirect"] > y311["lab_rmse_final"]
    (a,) = res["attribution"]
    assert a["lab_rmse_final"] == pytest.approx(y311["lab_rmse_final"], rel=1e-6)
    assert 0 <= a["indirect_lit_error_share"] <= 1 and 0 < a["surface_pixels"] <= 1
    assert [x["light"] for x in a["lights"]] == ["light_008 (AreaLight)"]
    md = (out / "crc" / "results.md").read_text()
    assert "## Targets" in md and "final frame Lab RMSE" in md
    assert (out / "crc" / "protocol_cornell_b1.png").exists()
