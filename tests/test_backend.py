import pytest

from slc.core import backend


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
