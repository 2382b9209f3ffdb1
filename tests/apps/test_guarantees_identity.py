"""Nothing stale (issue 20): included scene files in the scene's identity, basis images edited
in place, chunks of other settings, finished and concurrent chunked runs."""

import hashlib
import json
import os
import shutil
import stat

import numpy as np
import pytest
from guarantees_helpers import ROOT, SPHERE, assert_one_error, render_basis_args, run_tool, snapshot

pytestmark = [pytest.mark.render, pytest.mark.usefixtures("plugins")]
mi = pytest.importorskip("mitsuba")
from mitsuba_manifold._util.cache import file_hash  # noqa: E402
from mitsuba_manifold._util.locking import FolderLock  # noqa: E402
from mitsuba_manifold.basis.folder.manifest import Manifest, scene_hash  # noqa: E402
from mitsuba_manifold.errors import FolderLockedError  # noqa: E402
from mitsuba_manifold.imaging import io as imageio  # noqa: E402
from mitsuba_manifold.manifold.model import Manifold  # noqa: E402
from mitsuba_manifold.render.jobs import chunks, executor  # noqa: E402


def _included_scene(folder):
    """The sphere scene with its sky moved into an included XML (``lights/sky.xml``)."""
    folder.mkdir()
    (folder / "lights").mkdir()
    xml = open(SPHERE).read()
    start, end = (
        xml.index('    <emitter type="envmap"'),
        xml.index("</emitter>") + len("</emitter>"),
    )
    (folder / "main.xml").write_text(
        xml[:start] + '    <include filename="lights/sky.xml"/>' + xml[end:]
    )
    (folder / "lights" / "sky.xml").write_text(
        '<scene version="3.0.0"><emitter type="envmap"><string name="filename" value="sky.exr"/></emitter></scene>'
    )
    shutil.copy(os.path.join(ROOT, "scenes", "sky.exr"), folder / "sky.exr")
    return folder / "main.xml"


def test_files_named_by_an_included_xml_are_part_of_the_scene_identity(tmp_path, tiny):
    scene = _included_scene(tmp_path / "scene")
    h0 = scene_hash(scene)
    (tmp_path / "scene" / "lights" / "sky.exr").write_bytes(
        b"a copy beside the include is hashed too"
    )
    h1 = scene_hash(scene)
    sky = imageio.read_exr(tmp_path / "scene" / "sky.exr")
    base = [
        "render_basis",
        scene,
        "--manifold",
        tiny["manifold"],
        "--out",
        tmp_path / "b",
        "--res",
        8,
        "--spp",
        1,
        "--mode",
        "onepass",
    ]
    rc, _, err = run_tool(*base)
    assert rc == 0, err
    imageio.write_exr(tmp_path / "scene" / "sky.exr", sky * 2)  # the envmap of the included XML
    assert len({h0, h1, scene_hash(scene)}) == 3
    before = snapshot(tmp_path / "b")
    rc, _, err = run_tool(*base)  # the basis is stale: not resumed
    assert_one_error(rc, err, "other settings", "scene_hash")
    rc, _, err = run_tool(
        "blend",
        "--basis",
        tmp_path / "b",
        "--scene",
        scene,
        "--x",
        "0,0",
        "--out",
        tmp_path / "blend.exr",
    )
    assert_one_error(rc, err, "another scene")
    assert snapshot(tmp_path / "b") == before


def test_scene_hash_is_unchanged_without_includes_and_ends_on_include_cycles(tmp_path):
    h = hashlib.sha256(open(SPHERE, "rb").read())
    h.update(b"\0sky.exr\0" + file_hash(os.path.join(ROOT, "scenes", "sky.exr")).encode())
    assert scene_hash(SPHERE) == h.hexdigest()  # bases of earlier releases stay valid
    (tmp_path / "a.xml").write_text('<scene version="3.0.0"><include filename="b.xml"/></scene>')
    (tmp_path / "b.xml").write_text(
        '<scene version="3.0.0"><include filename="a.xml"/>'
        '<shape type="ply"><string name="filename" value="m.ply"/></shape></scene>'
    )
    (tmp_path / "m.ply").write_text("one")
    first = scene_hash(tmp_path / "a.xml")
    (tmp_path / "m.ply").write_text("two")
    assert scene_hash(tmp_path / "a.xml") != first


def _edit(path, factor=2.0):
    imageio.write_exr(path, imageio.read_exr(path) * factor)  # in place, same size


def test_a_basis_image_edited_in_place_is_refused_by_blend_and_rendered_again(tmp_path, tiny):
    out = tmp_path / "basis"
    shutil.copytree(tiny["basis"], out)
    entry = Manifest.read(out).images["steel"]
    path = out / entry.file
    original = imageio.read_exr(path)
    assert entry.sha256 == file_hash(path)
    _edit(path)
    m = Manifold.load(tiny["manifold"])
    x = ",".join(f"{v:.17g}" for v in m.latent[m.index("steel")])  # steel alone
    rc, _, err = run_tool(
        "blend",
        "--basis",
        out,
        "--manifold",
        tiny["manifold"],
        "--x",
        x,
        "--out",
        tmp_path / "blend.exr",
    )
    assert_one_error(rc, err, "steel", "changed after render_basis wrote it")
    assert not (tmp_path / "blend.exr").exists()
    cmd = [
        "render_basis",
        SPHERE,
        "--manifold",
        tiny["manifold"],
        "--out",
        out,
        "--res",
        8,
        "--spp",
        1,
        "--mode",
        "per-material",
    ]  # as make_tiny rendered it
    rc, _, err = run_tool(*cmd)
    assert rc == 0, err
    np.testing.assert_array_equal(imageio.read_exr(path), original)  # rendered again, the same
    for replacement in (
        lambda p: _edit(p, 3.0),
        lambda p: imageio.write_exr(p, np.zeros((16, 16, 3), np.float32)),
    ):
        replacement(path)
        os.chmod(path, 0o444)
        before = snapshot(out)
        rc, _, err = run_tool(*cmd)
        assert_one_error(rc, err, "read-only", str(path))
        assert snapshot(out) == before and stat.S_IMODE(os.stat(path).st_mode) == 0o444
        os.chmod(path, 0o644)


OPTIONS = {"mode": "onepass", "resolution": 8}


class _Dies(executor.LocalExecutor):
    """Renders one chunk, then the run is killed."""

    def map(self, fn, items):
        for i, item in enumerate(items):
            if i == 1:
                raise KeyboardInterrupt
            yield fn(item)


def _images(folder):
    m = Manifest.read(folder)
    return {k: imageio.read_exr(os.path.join(folder, e.file)) for k, e in m.images.items()}


def test_chunks_of_other_settings_are_rendered_again_and_a_finished_run_is_not(tmp_path, tiny):
    m = tiny["manifold"]
    clean = chunks.render_chunked(
        SPHERE, m, str(tmp_path / "clean"), spp=4, chunks=2, seed=7, **OPTIONS
    )
    for name, first in (("seed", {"spp": 4, "seed": 0}), ("spp", {"spp": 6, "seed": 7})):
        out = str(tmp_path / name)
        with pytest.raises(KeyboardInterrupt):  # a killed run of other settings leaves one chunk
            chunks.render_chunked(SPHERE, m, out, chunks=2, executor=_Dies(), **first, **OPTIONS)
        run = chunks.render_chunked(SPHERE, m, out, spp=4, chunks=2, seed=7, **OPTIONS)
        assert [r[0] for r in run.rendered] == ["000-of-002", "001-of-002"] and run.resumed == []
        assert run.manifest.spp == 4 and run.manifest.seed == 7
        for key, img in _images(
            out
        ).items():  # the same samples (threads may sum them in another order)
            want = _images(tmp_path / "clean")[key]
            np.testing.assert_allclose(
                img, want, rtol=2e-6, atol=1e-7 * max(1.0, float(want.max()))
            )
    before = snapshot(tmp_path / "clean")
    again = chunks.render_chunked(
        SPHERE, m, str(tmp_path / "clean"), spp=4, chunks=2, seed=7, **OPTIONS
    )
    assert again.rendered == [] and again.manifest.images.keys() == clean.manifest.images.keys()
    assert snapshot(tmp_path / "clean") == before
    with FolderLock(tmp_path / "clean", "basis folder"):  # another run holds the folder
        with pytest.raises(FolderLockedError, match="being written by another process"):
            chunks.render_chunked(
                SPHERE, m, str(tmp_path / "clean"), spp=4, chunks=2, seed=7, **OPTIONS
            )
    assert snapshot(tmp_path / "clean") == before


def test_a_run_that_failed_before_its_first_image_does_not_block_other_settings(tmp_path, tiny):
    """A bad table stops render_basis before any image (one line naming it): a folder the run
    made is removed again, and one that held a manifest listing no image yet (a run killed
    before its first) does not block a run of other settings (chunks)."""
    db = tmp_path / "db"
    shutil.copytree(tiny["db"], db)
    table = db / "gold-paint.binary"
    data = table.read_bytes()
    table.write_bytes(data[: len(data) // 2])
    out = tmp_path / "basis"
    args = render_basis_args(tiny["manifold"], out, "--database", db, spp=2)
    rc, _, err = run_tool("render_basis", *args)
    assert_one_error(rc, err, "gold-paint.binary")
    assert not out.exists()
    table.write_bytes(data)
    rc, _, err = run_tool("render_basis", *args)
    assert rc == 0, err
    manifest = Manifest.read(out).to_json()
    manifest.pop("gi_images", None)
    manifest["images"] = {}  # as a run killed before its first image leaves it
    (out / "manifest.json").write_text(json.dumps(manifest))
    for f in out.iterdir():
        if f.name != "manifest.json":
            f.unlink()
    rc, _, err = run_tool("render_basis", *args, "--chunks", 2)
    assert rc == 0, err
    assert Manifest.read(out).chunks == 2 and Manifest.read(out).images
