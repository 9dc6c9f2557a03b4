"""Ground truth and RT-N against closed forms and each other."""
import numpy as np
import pytest

from helpers import plane_under_rect_light, rect_irradiance
from slc.scene import gbuffer, scenes, views
from slc.reference import groundtruth
from slc import methods
from slc.reference.metrics import rel_mse
from slc.scene.gbuffer import frame_gbuffers


def test_ground_truth_matches_closed_form_irradiance():
    half, h, L, rho = 0.25, 1.0, 10.0, 0.5
    s = plane_under_rect_light(half, h, L, rho)
    gb = frame_gbuffers(s, views.single(s), 0, 48, 48)[0]
    img = groundtruth.ground_truth(s, gb, 0, "v", use_cache=False)
    p = np.array(gb.si.p).T.reshape(48, 48, 3) if np.array(gb.si.p).shape[0] == 3 else np.array(gb.si.p).reshape(48, 48, 3)
    valid = np.array(gb.valid).reshape(48, 48) & (np.abs(p[..., 1]) < 1e-4)
    E = rect_irradiance(p[..., 0], p[..., 2], -half, half, -half, half, h, L)
    expected = rho / np.pi * E
    got = img[..., 0]
    assert valid.sum() > 1000
    rel = np.abs(got[valid].mean() - expected[valid].mean()) / expected[valid].mean()
    assert rel < 0.01, rel
    # per pixel, the 2048-sample estimate stays close to the closed form as well
    per_pixel = np.abs(got[valid] - expected[valid]) / expected[valid]
    assert np.median(per_pixel) < 0.02


@pytest.mark.slow
def test_rt16_vs_rt64_relative_mse_ratio():
    s = scenes.load("cornell")
    gb = frame_gbuffers(s, views.single(s), 0, 64, 48)[0]
    gt = groundtruth.ground_truth(s, gb, 0, "front")
    errs = {}
    for n in (16, 64):
        vals = []
        for seed in range(3):
            m = methods.create(f"rt{n}", s, seed=seed)
            img = gbuffer.to_image(gb, gbuffer.compose(gb, m.shade(methods.FrameContext(0), None, 0, gb)))
            vals.append(rel_mse(gt, img))
        errs[n] = np.mean(vals)
    ratio = errs[16] / errs[64]
    assert 3.0 < ratio < 5.5, (errs, ratio)


def test_ground_truth_is_cached(tmp_path, monkeypatch):
    monkeypatch.setenv("SLC_CACHE", str(tmp_path))
    s = scenes.load("cornell")
    gb = frame_gbuffers(s, views.single(s), 0, 16, 16)[0]
    a = groundtruth.ground_truth(s, gb, 0, "v", spp=64)
    files = list((tmp_path / "gt").glob("*.npy"))
    assert len(files) == 1 and "cornell" in files[0].name and "16x16" in files[0].name
    b = groundtruth.ground_truth(s, gb, 0, "v", spp=64)
    assert np.array_equal(a, b)


def test_reference_of_an_older_scene_build_is_not_served(tmp_path, monkeypatch):
    """The scene-loading version is part of every reference's cache key: once loading
    changes a scene (slc.scene.scenes.LOAD_VERSION raised), the cached reference of the
    former build is not read back."""
    from slc.reference import cache
    monkeypatch.setenv("SLC_CACHE", str(tmp_path))
    s = scenes.load("cornell")
    gb = frame_gbuffers(s, views.single(s), 0, 8, 8)[0]
    groundtruth.ground_truth(s, gb, 0, "v", spp=16)
    before = cache.cache_path("gt", groundtruth._VERSION, s, gb, 0, "v", 16)
    monkeypatch.setattr(cache, "LOAD_VERSION", cache.LOAD_VERSION + 1)
    after = cache.cache_path("gt", groundtruth._VERSION, s, gb, 0, "v", 16)
    assert before.exists() and after != before and not after.exists()
    groundtruth.ground_truth(s, gb, 0, "v", spp=16)
    assert after.exists() and len(list((tmp_path / "gt").glob("*.npy"))) == 2


def test_reference_of_another_light_or_material_is_not_served(tmp_path, monkeypatch):
    """Two scenes of one name seen through the same G-buffer, one with a brighter light,
    one with a darker wall: three cache keys, each served its own ground truth; a change
    of the reference code's source is a new key too."""
    import mitsuba as mi
    from slc.reference import cache
    monkeypatch.setenv("SLC_CACHE", str(tmp_path))
    s = scenes.load("cornell")
    gb = frame_gbuffers(s, views.single(s), 0, 8, 8)[0]
    a = groundtruth.ground_truth(s, gb, 0, "v", spp=16)
    paths = {cache.cache_path("gt", groundtruth._VERSION, s, gb, 0, "v", 16)}
    params = mi.traverse(s.mi_scene)
    light = next(k for k in params.keys() if k.endswith("radiance.value"))
    params[light] = params[light] * 2.0
    params.update()
    b = groundtruth.ground_truth(s, gb, 0, "v", spp=16)
    paths.add(cache.cache_path("gt", groundtruth._VERSION, s, gb, 0, "v", 16))
    wall = next(k for k in params.keys() if k.endswith("reflectance.value"))
    params[wall] = params[wall] * 0.5
    params.update()
    groundtruth.ground_truth(s, gb, 0, "v", spp=16)
    paths.add(cache.cache_path("gt", groundtruth._VERSION, s, gb, 0, "v", 16))
    assert len(paths) == 3 and len(list((tmp_path / "gt").glob("*.npy"))) == 3
    assert b.sum() > 1.5 * a.sum()
    monkeypatch.setattr(cache, "CODE_HASH", "0" * 16)
    assert cache.cache_path("gt", groundtruth._VERSION, s, gb, 0, "v", 16) not in paths
