"""Shared fixtures: a small reduced-resolution surrogate database and a manifold fit on it."""

import os

import pytest

# Tests must never pick Debian's libLLVM 15: the package selects a newer one on import.
import mitsuba_manifold  # noqa: F401
# -m "not render" starts neither Mitsuba, Dr.Jit nor Ray (the session fails if it does).
from numpy_only import pytest_sessionfinish  # noqa: F401

SMALL_DIMS = (32, 32, 64)
SMALL_MATERIALS = ["white-diffuse-bball", "gold-paint", "blue-acrylic", "chrome", "steel",
                   "color-changing-paint3", "pink-fabric", "black-obsidian"]


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
