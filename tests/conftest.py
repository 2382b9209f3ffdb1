"""Shared fixtures: a small reduced-resolution surrogate database, a manifold fit on it, and
``variant``, the Mitsuba variant of the rendering tests.

Tests that render, or start Ray, carry the ``render`` marker (``pytestmark = [pytest.mark.render,
pytest.mark.usefixtures("variant")]`` for a module), so ``-m "not render"`` runs the NumPy-only
part without starting either.
"""

import os

import pytest

# -m "not render" starts neither Mitsuba, Dr.Jit nor Ray (the session fails if it does).
from numpy_only import pytest_sessionfinish  # noqa: F401

#: The variant every rendering test runs in: ``MM_VARIANT`` (e.g. ``cuda_ad_rgb`` on a GPU, as
#: tools/gpu_check.sh runs them), else ``llvm_ad_rgb``.
VARIANT = os.environ.get("MM_VARIANT") or "llvm_ad_rgb"


def pytest_configure(config):
    """Before any test module imports Dr.Jit: importing the rendering subsystem selects a libLLVM
    >= 16 (Debian's libLLVM 15 aborts renders) and registers the plugins for every variant
    (:mod:`mitsuba_manifold.render`). Runs that deselect rendering do neither."""
    if "not render" not in (config.getoption("markexpr", "") or ""):
        try:
            import mitsuba_manifold.render  # noqa: F401
        except ImportError:  # no Mitsuba: the rendering tests skip
            pass


@pytest.fixture
def variant():
    """:data:`VARIANT` active, with the package's plugins, during the test and after it (a test
    may switch variants); skips without Mitsuba."""
    mi = pytest.importorskip("mitsuba")
    import mitsuba_manifold.render  # noqa: F401  (the plugins, for this variant and every later one)

    mi.set_variant(VARIANT)
    yield VARIANT
    mi.set_variant(VARIANT)


SMALL_DIMS = (32, 32, 64)
SMALL_MATERIALS = [
    "white-diffuse-bball",
    "gold-paint",
    "blue-acrylic",
    "chrome",
    "steel",
    "color-changing-paint3",
    "pink-fabric",
    "black-obsidian",
]


@pytest.fixture(scope="session")
def small_db(tmp_path_factory):
    """Folder with 8 surrogate materials at 32x32x64 bins."""
    from mitsuba_manifold.data import database

    folder = tmp_path_factory.mktemp("db32")
    database.make_database(folder, SMALL_DIMS, SMALL_MATERIALS)
    return str(folder)


@pytest.fixture(scope="session")
def small_manifold_paper(small_db, tmp_path_factory):
    """Path of a manifold fit on :func:`small_db` with the paper's formulation (``preset="paper"``)."""
    from mitsuba_manifold.manifold.model import Manifold

    path = os.path.join(str(tmp_path_factory.mktemp("manifold_paper")), "manifold.npz")
    Manifold.fit(small_db, preset="paper").save(path)
    return path


@pytest.fixture(scope="session")
def small_manifold(small_db, tmp_path_factory):
    """Path of a q=2 manifold fit on :func:`small_db` (default preset otherwise)."""
    from mitsuba_manifold.manifold.model import Manifold

    path = os.path.join(str(tmp_path_factory.mktemp("manifold")), "manifold.npz")
    Manifold.fit(small_db, q=2).save(path)
    return path


@pytest.fixture(scope="session")
def measured_files(tmp_path_factory):
    """``{name: path}`` of three Mitsuba ``measured`` files made for the tests (a blue paper, a
    metallic paint, a glossy yellow film: :mod:`measured_files`)."""
    import measured_files as made

    return made.write_all(str(tmp_path_factory.mktemp("measured")))
