import os
import sys
import tempfile
from pathlib import Path

import pytest

# Ground-truth images are cached on disk; tests use a private cache so a
# stale reference from an older run can never satisfy a test.
os.environ.setdefault("SLC_CACHE", tempfile.mkdtemp(prefix="slc-test-cache-"))
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import slc  # noqa: E402,F401  (selects the variant)


@pytest.fixture(scope="session")
def root():
    return ROOT
