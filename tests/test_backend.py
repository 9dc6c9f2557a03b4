import os
import subprocess
import sys
from pathlib import Path

import pytest

from slc.core import backend

ROOT = Path(__file__).resolve().parents[1]


def test_variant_override_and_errors(monkeypatch):
    monkeypatch.setenv("SLC_VARIANT", "llvm_ad_rgb")
    assert backend.choose_variant() == "llvm_ad_rgb"
    assert backend.choose_variant("cuda_ad_rgb") == "cuda_ad_rgb"
    monkeypatch.setenv("SLC_VARIANT", "bogus")
    with pytest.raises(backend.BackendError, match="unknown variant"):
        backend.choose_variant()
    monkeypatch.delenv("SLC_VARIANT")
    expected = "cuda_ad_rgb" if backend.cuda_available() else "llvm_ad_rgb"
    assert backend.choose_variant() == expected


def test_llvm_check(monkeypatch, tmp_path):
    old = tmp_path / "libLLVM-15.so.1"
    old.write_bytes(b"")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(old))
    with pytest.raises(backend.BackendError, match="apt-get install -y libllvm19"):
        backend.prepare_llvm()
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(tmp_path / "nothing.so"))
    with pytest.raises(backend.BackendError, match="does not exist"):
        backend.prepare_llvm()
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH")
    monkeypatch.setattr(backend, "_LLVM_DIRS", (str(tmp_path),))
    with pytest.raises(backend.BackendError, match="no libLLVM >= 16"):
        backend.prepare_llvm()
    (tmp_path / "libLLVM-19.so").write_bytes(b"")
    backend.prepare_llvm()
    import os
    assert os.environ["DRJIT_LIBLLVM_PATH"].endswith("libLLVM-19.so")


def test_env_info():
    e = backend.env_info()
    assert e["variant"] in backend.SUPPORTED_VARIANTS and e["mitsuba"] == "3.9.1" and e["drjit"] == "1.5.0"


def _fresh(code: str, **env):
    """``code`` run by a new interpreter from the checkout (no variant chosen before it)."""
    e = {k: v for k, v in os.environ.items() if k not in ("SLC_VARIANT", "DRJIT_LIBLLVM_PATH")}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env={**e, **env},
                          timeout=300)


def test_importing_slc_chooses_no_variant():
    """``import slc`` and the command line's module choose no Mitsuba variant; the first package
    that builds Mitsuba types on import does, or ``slc.set_variant`` before it."""
    r = _fresh("import mitsuba as mi\nimport slc, slc.run.cli\nprint(mi.variant())\n"
               "import slc.scene.scenes\nprint(mi.variant())")
    assert r.returncode == 0, r.stderr[-2000:]
    before, after = r.stdout.split()
    assert before == "None" and after in backend.SUPPORTED_VARIANTS, r.stdout
    r = _fresh("import mitsuba as mi\nimport slc\nslc.set_variant('llvm_ad_rgb')\nimport slc.methods\n"
               "print(mi.variant())")
    assert r.returncode == 0 and r.stdout.split() == ["llvm_ad_rgb"], r.stderr[-2000:]


def test_missing_libllvm_is_one_line_on_import(tmp_path):
    """Without a libLLVM >= 16 the import that needs the variant stops with the one-line reason."""
    r = _fresh("import slc.scene", DRJIT_LIBLLVM_PATH=str(tmp_path / "libLLVM-15.so"))
    lines = r.stderr.strip().splitlines()
    assert r.returncode != 0 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert "BackendError" in lines[0] and "does not exist" in lines[0], lines
