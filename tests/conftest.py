import os
import sys
from pathlib import Path

import pytest

# References are cached on disk under a key that holds everything they depend on
# (slc.reference.cache: estimator version, the reference and scene code, the scene's
# content, camera, time, G-buffer), so a cached reference is the one a test would
# compute; the tests keep theirs apart from the experiments' cache.
os.environ.setdefault("SLC_CACHE", str(Path.home() / ".cache" / "slc-tests"))
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import slc  # noqa: E402,F401  (selects the variant)


@pytest.fixture(scope="session")
def root():
    return ROOT


@pytest.fixture(scope="session")
def scene():
    """``scene(name)``: a built-in scene (or scene file) loaded once per pytest session
    and shared by every test that asks for it. Tests must not modify it (moving a light,
    mi.traverse updates); load a private copy with ``slc.scenes.load`` for that."""
    from slc.scene import scenes
    loaded = {}

    def load(name: str):
        if name not in loaded:
            loaded[name] = scenes.load(name)
        return loaded[name]
    return load


@pytest.fixture(scope="session")
def reference():
    """``reference(kind, scene, gb, frame, spp=None, bounces=1)``: the reference image
    (slc.reference.references.reference_for: ``direct`` ground truth, ``indirect`` or ``full``) of
    the G-buffer, computed once per pytest session and shared across tests and files (the
    reference cache on disk, SLC_CACHE, keys it by scene, camera, frame,
    resolution, samples and the G-buffer's content)."""
    from slc.reference import references

    def ref(kind, scene, gb, frame, spp=None, bounces=1):
        return references.reference_for(kind, scene, gb, frame, gb.viewer, spp=spp, bounces=bounces)
    return ref
