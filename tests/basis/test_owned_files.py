"""Which files a basis folder owns (:mod:`mitsuba_manifold.basis.folder.owned_files`)."""

import os

import numpy as np
import pytest
from helpers import write_basis

from mitsuba_manifold.basis.folder import CrossEntry, ImageEntry, Manifest
from mitsuba_manifold.basis.folder.owned_files import basis_entries, remove_basis
from mitsuba_manifold.errors import ForeignFileError


def _full_gi_basis(folder, manifold_path):
    """A one-target basis whose manifest lists full-GI images and cross terms, as a one-pass
    render with ``components="full"`` writes it."""
    image = np.full((4, 4, 3), 0.5, np.float32)
    write_basis(str(folder), manifold_path, {"base": image, "a": image})
    os.remove(folder / "scene.xml")  # the stand-in scene is not the basis's
    m = Manifest.read(folder)
    (folder / "a.gi.exr").write_bytes(b"gi image")
    (folder / "cross.npz").write_bytes(b"cross terms")
    m.components = ["l1", "l2+", "cross"]
    m.gi_images = {"a": ImageEntry(file="a.gi.exr", time_s=0.1)}
    m.cross = CrossEntry(file="cross.npz", pairs=1, tol=0.001)
    m.write(folder)


def test_a_full_gi_basis_owns_its_full_gi_images_and_cross_terms(tmp_path, small_manifold):
    folder = tmp_path / "basis"
    _full_gi_basis(folder, small_manifold)
    own, foreign = basis_entries(folder)
    assert foreign == []
    assert {"a.gi.exr", "cross.npz", "base.exr", "a.exr", "manifest.json"} <= set(own)
    remove_basis(folder)  # rendered again from scratch (the GI comparison's timed basis)
    assert not folder.exists()


def test_a_user_file_in_a_full_gi_basis_keeps_it(tmp_path, small_manifold):
    folder = tmp_path / "basis"
    _full_gi_basis(folder, small_manifold)
    (folder / "b.gi.exr").write_bytes(b"the user's")
    with pytest.raises(ForeignFileError, match="b.gi.exr"):
        remove_basis(folder)
    assert (folder / "b.gi.exr").exists() and (folder / "a.gi.exr").exists()
