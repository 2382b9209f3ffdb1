"""Selection of a libLLVM that Dr.Jit's LLVM backend can use."""

import pytest

from mitsuba_manifold.render.plugin import llvm as _llvm


def test_version_parsing():
    assert _llvm._version("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1") == 19
    assert _llvm._version("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1") == 15
    assert _llvm._version("/usr/lib/llvm-17/lib/libLLVM.so") == 17


def test_select_prefers_newest_and_respects_the_user(monkeypatch):
    monkeypatch.setattr(
        _llvm, "candidates", lambda: [("/x/libLLVM.so.19.1", 19), ("/x/libLLVM-15.so.1", 15)]
    )
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    assert _llvm.select() == "/x/libLLVM.so.19.1"
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "/mine/libLLVM.so")
    assert _llvm.select() == "/mine/libLLVM.so"


def test_no_usable_llvm_gives_a_clear_error(monkeypatch):
    monkeypatch.setattr(_llvm, "candidates", lambda: [("/x/libLLVM-15.so.1", 15)])
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    assert _llvm.select() is None
    with pytest.raises(
        RuntimeError, match=r"libLLVM >= 16, found: /x/libLLVM-15.so.1 \(LLVM 15\).*libllvm19"
    ):
        _llvm.require()
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "/does/not/exist.so")
    with pytest.raises(RuntimeError, match="does not exist"):
        _llvm.require()
