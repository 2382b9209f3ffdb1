"""A basis folder read or written while something is wrong with it: every case one clear
error naming the file, never the wrong image (swapped manifest entries), never a user's link
replaced, and a render in progress said to be one."""

import json
import os

import numpy as np
import pytest
from helpers import write_basis

from mitsuba_manifold._util.cache import file_hash
from mitsuba_manifold._util.locking import FolderLock
from mitsuba_manifold.basis import blend as bl
from mitsuba_manifold.basis.folder import MANIFEST, Manifest
from mitsuba_manifold.basis.folder.output import open_folder
from mitsuba_manifold.errors import InputError, MismatchError
from mitsuba_manifold.imaging import io as imageio
from mitsuba_manifold.manifold.model import Manifold


@pytest.fixture
def basis(tmp_path, small_manifold):
    """A one-target basis of the small manifold's materials (stand-in images)."""
    m = Manifold.load(small_manifold)
    rng = np.random.default_rng(0)
    images = {"base": rng.random((3, 4, 3), np.float32)}
    images.update({n: rng.random((3, 4, 3), np.float32) for n in m.names})
    folder = tmp_path / "b"
    write_basis(str(folder), small_manifold, images)

    def hashes(data):  # as render_basis records them
        for entry in data["images"].values():
            entry["sha256"] = file_hash(str(folder / entry["file"]))

    _edit(folder, hashes)
    return folder, m


def _edit(folder, change):
    path = folder / MANIFEST
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def test_a_deeply_nested_manifest_is_refused_naming_it(basis):
    folder, _ = basis
    (folder / MANIFEST).write_text("[" * 100000 + "]" * 100000)
    for read in (Manifest.read, bl.Basis.load):
        with pytest.raises(MismatchError) as e:
            read(str(folder))
        assert str(folder / MANIFEST) in str(e.value) and "nested" in str(e.value)


def test_swapped_image_entries_are_refused(basis):
    """Two images' ``{file, sha256}`` swapped: each hash matches its file, every material would
    get another's image; the manifest is refused naming both."""
    folder, m = basis
    a, b = m.names[0], m.names[1]

    def swap(data):
        images = data["images"]
        images[a], images[b] = images[b], images[a]

    _edit(folder, swap)
    with pytest.raises(MismatchError) as e:
        bl.Basis.load(str(folder))
    message = str(e.value)
    assert f"image {a!r} lists the file '{b}.exr'" in message and str(folder) in message


def test_a_manifest_of_another_version_says_the_manifold_changed_not_another_one(
    basis, small_manifold
):
    folder, _ = basis
    _edit(folder, lambda d: d.update(version=1))
    with pytest.raises(MismatchError) as e:
        bl.Basis.load(str(folder), manifold=small_manifold)
    message = str(e.value)
    assert message.count(os.path.abspath(small_manifold)) == 1, message
    assert "not the one it was rendered with" in message and "version-1" in message


def test_a_basis_being_rendered_says_so_instead_of_changed(basis, small_manifold):
    folder, m = basis
    key = m.names[2]
    imageio.write_exr(str(folder / f"{key}.exr"), np.ones((3, 4, 3), np.float32))
    x = m.latent[2]
    with pytest.raises(MismatchError, match="was changed after render_basis wrote it"):
        bl.blend(str(folder), small_manifold, x=x)
    with FolderLock(str(folder), "basis folder"):  # what render_basis holds while it writes
        with pytest.raises(MismatchError) as e:
            bl.blend(str(folder), small_manifold, x=x)
    assert "render_basis is writing into this basis now" in str(e.value)
    assert "changed after" not in str(e.value)


def test_a_render_never_replaces_a_link_in_its_basis_folder_even_forced(basis, tmp_path):
    folder, m = basis
    theirs = tmp_path / "theirs.exr"
    theirs.write_bytes(b"the user's own file")
    os.symlink(theirs, folder / "new.exr")
    manifest = Manifest.read(folder)
    files = [f"{n}.exr" for n in m.names] + ["base.exr", "new.exr", MANIFEST]
    for read_images in (False, True):
        with pytest.raises(InputError) as e:
            open_folder(str(folder), manifest, files, force=True, read_images=read_images)
        assert "symbolic link" in str(e.value) and str(folder / "new.exr") in str(e.value)
    assert os.path.islink(folder / "new.exr") and theirs.read_bytes() == b"the user's own file"
    os.remove(folder / f"{m.names[0]}.exr")  # a listed image replaced by a link
    os.symlink(theirs, folder / f"{m.names[0]}.exr")
    with pytest.raises(InputError, match="symbolic link"):
        open_folder(str(folder), manifest, files[:-2] + [MANIFEST], force=True)
