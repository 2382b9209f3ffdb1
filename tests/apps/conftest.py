"""Fixtures of the guarantee tests (``test_guarantees_*.py``): the plugins registered on the
LLVM variant, and a tiny database, manifold and basis made once per module."""

import pytest


@pytest.fixture
def plugins():
    """The ``llvm_ad_rgb`` variant, with the package's plugins registered on it."""
    import mitsuba as mi

    import mitsuba_manifold

    mi.set_variant("llvm_ad_rgb")
    mitsuba_manifold.register()
    return mi


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A 4-material database at 8x8x16, a q=2 manifold on it, and a rendered 8x8 basis."""
    import mitsuba as mi
    from guarantees_helpers import make_tiny

    mi.set_variant("llvm_ad_rgb")
    return make_tiny(tmp_path_factory.mktemp("tiny"))
