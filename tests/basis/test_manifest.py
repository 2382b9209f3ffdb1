"""The basis manifest as a type (:class:`Manifest`): files written before read the same."""

import dataclasses
import json
import re

import pytest

from mitsuba_manifold.basis.folder import (
    MANIFEST,
    NOT_RECORDED,
    CrossEntry,
    ImageEntry,
    Manifest,
    RenderSettings,
)
from mitsuba_manifold.errors import MismatchError

#: A manifest of format version 1, as the first releases wrote it: no sensor, no components.
V1 = {
    "format": "mitsuba-manifold-basis",
    "version": 1,
    "scene": "/s/sphere.xml",
    "scene_hash": "a" * 64,
    "manifold": "/m/manifold.npz",
    "manifold_hash": "b" * 64,
    "resolution": [32, 24],
    "spp": 16,
    "variant": "llvm_ad_rgb",
    "seed": 0,
    "max_depth": 8,
    "mode": "per-material",
    "targets": ["material"],
    "images": {
        "base": {"file": "base.exr", "time_s": 1.5},
        "chrome": {"file": "chrome.exr", "time_s": 2.0},
    },
}
#: A full-GI manifest of version 2 with a key this version does not know.
V2 = dict(
    V1,
    version=2,
    mode="onepass",
    sensor=1,
    components=["l1", "l2+", "cross"],
    levels=5,
    gi_images={"chrome": {"file": "chrome.gi.exr", "time_s": 3.0}},
    cross={"file": "cross.npz", "pairs": 0, "tol": 0.01},
    left_out={},
    chunk_key="k",
)


@pytest.mark.parametrize("data", [V1, V2], ids=["v1", "v2"])
def test_a_manifest_written_before_reads_and_writes_back_the_same(tmp_path, data):
    (tmp_path / MANIFEST).write_text(json.dumps(data))
    m = Manifest.read(tmp_path)
    assert m.to_json() == data and list(m.to_json()) == list(data)
    assert m.resolution == (32, 24) and m.images["chrome"] == ImageEntry("chrome.exr", 2.0)
    out = tmp_path / "again"
    out.mkdir()
    m.write(out)
    assert json.loads((out / MANIFEST).read_text()) == data


def test_the_file_entries_are_typed_and_keep_what_this_version_does_not_know(tmp_path):
    data = dict(
        V2,
        images={
            "base": {"file": "base.exr", "time_s": 1, "sha256": "c" * 64},
            "chrome": {"file": "chrome.exr", "time_s": 2.5, "note": [1]},
        },
        gi_images={"chrome": {"file": "chrome.gi.exr"}},
        cross={"file": "cross.npz", "pairs": 3, "tol": 0.01, "sha256": "d" * 64},
    )
    m = Manifest.from_json(data)
    assert m.images == {
        "base": ImageEntry("base.exr", 1, "c" * 64),
        "chrome": ImageEntry("chrome.exr", 2.5, extra={"note": [1]}),
    }
    assert m.gi_images == {"chrome": ImageEntry("chrome.gi.exr")}
    assert m.cross == CrossEntry("cross.npz", pairs=3, tol=0.01, sha256="d" * 64)
    m.write(tmp_path)
    assert (tmp_path / MANIFEST).read_text() == json.dumps(data, indent=1) + "\n"


def test_what_a_manifest_leaves_unsaid_has_its_meaning():
    old, new = Manifest.from_json(V1), Manifest.from_json(V2)
    assert (old.sensor, old.sensor_index, old.held_components) == (None, 0, ["l1"])
    assert (new.sensor_index, new.held_components, new.extra) == (
        1,
        ["l1", "l2+", "cross"],
        {
            "chunk_key": "k"
        },  # a chunked render's mark: kept for render.jobs.chunks, not the format's
    )
    assert old.scene_resolution is NOT_RECORDED and old.loaded_resolution == (32, 24)
    assert (
        old.differences(dict(V1, sensor=0)) == [] and new.differences(V2, ignore=("sensor",)) == []
    )
    assert Manifest.from_json(dict(V1, spp=32)).differences(V1) == ["spp"]


#: The bytes of a ``manifest.json`` the renderers wrote before :class:`Manifest` held a
#: :class:`RenderSettings` (a merged chunk of a full-GI basis, with a key of a later version).
WRITTEN_BEFORE = """{
 "format": "mitsuba-manifold-basis",
 "version": 2,
 "scene": "/s/sphere.xml",
 "scene_hash": "aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa",
 "manifold": "/m/m.npz",
 "manifold_hash": "bbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbbb",
 "resolution": [
  8,
  6
 ],
 "spp": 4,
 "variant": "llvm_ad_rgb",
 "seed": 3,
 "max_depth": -1,
 "mode": "onepass",
 "targets": [
  "mat"
 ],
 "images": {
  "base": {
   "file": "base.exr",
   "time_s": 0.5,
   "sha256": "cccccccccccccccccccccccccccccccccccccccccccccccccccccccccccccccc"
  },
  "steel": {
   "file": "steel.exr",
   "time_s": 0.5,
   "sha256": "dddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddd"
  }
 },
 "sensor": 0,
 "chunks": 2,
 "components": [
  "l1",
  "l2+",
  "cross"
 ],
 "levels": 4,
 "gi_images": {
  "steel": {
   "file": "steel.gi.exr",
   "time_s": 0.5
  }
 },
 "cross": {
  "file": "cross.npz",
  "pairs": 1,
  "tol": 0.01
 },
 "left_out": {},
 "gi_stats": {
  "render_s": 1.0
 },
 "integrator": {
  "type": "path",
  "max_depth": -1,
  "rr_depth": 5,
  "hide_emitters": false,
  "source": "scene"
 },
 "scene_resolution": null,
 "chunk_complete": true,
 "chunk_run": {
  "seconds": 1.5,
  "host": "h",
  "pid": 7
 },
 "chunk_key": "eeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeeee",
 "future_key": [
  1,
  2
 ]
}
"""


def test_a_file_written_before_reads_the_same_and_is_written_back_byte_for_byte(tmp_path):
    (tmp_path / MANIFEST).write_text(WRITTEN_BEFORE)
    m = Manifest.read(tmp_path)
    assert m.settings == RenderSettings((8, 6), 4, "llvm_ad_rgb", 3, -1, "onepass", sensor=0)
    assert (m.resolution, m.spp, m.seed, m.max_depth, m.mode, m.sensor) == (
        (8, 6),
        4,
        3,
        -1,
        "onepass",
        0,
    )
    assert m.integrator["source"] == "scene" and m.scene_resolution is None
    assert m.loaded_resolution is None  # loaded at the scene's own film size
    assert m.chunks == 2
    assert list(m.extra) == ["chunk_complete", "chunk_run", "chunk_key", "future_key"]
    assert [k for k, _ in m.entries()] == ["base", "steel", "gi:steel"]
    assert m.listed_files() == {"base.exr", "steel.exr", "steel.gi.exr", "cross.npz"}
    assert list(m.to_json()) == list(json.loads(WRITTEN_BEFORE))
    out = tmp_path / "again"
    out.mkdir()
    m.copy().write(out)
    assert (out / MANIFEST).read_text() == WRITTEN_BEFORE


@pytest.mark.parametrize(
    "field, value, words",
    [
        ("spp", 0, "its spp field must be a positive integer (samples per pixel), got 0"),
        ("resolution", [32], "its resolution field must be [width, height]"),
        ("mode", "fast", "its mode field must be one of ('per-material', 'onepass'), got 'fast'"),
        ("scene_hash", "xyz", "its scene_hash field must be a SHA-256 hex digest, got 'xyz'"),
        ("seed", True, "its seed field must be an integer (the images' seed), got True"),
        ("targets", ["a", "a"], "its targets field must name distinct BSDF ids"),
        ("images", {"base": {"file": "../base.exr", "time_s": 1}}, "its images field at base.file"),
    ],
)
def test_a_bad_field_is_refused_naming_the_file_and_the_field(tmp_path, field, value, words):
    (tmp_path / MANIFEST).write_text(json.dumps(dict(V1, **{field: value})))
    with pytest.raises(MismatchError, match=str(tmp_path)) as e:
        Manifest.read(tmp_path)
    assert words in str(e.value) and str(e.value).endswith(
        "; render the basis again with render_basis"
    )
    assert "\n" not in str(e.value)
    bad = Manifest.from_json(V1)
    if field in {f.name for f in dataclasses.fields(RenderSettings)}:
        bad.settings = dataclasses.replace(bad.settings, **{field: value})
    elif field == "images":
        bad.images = {k: ImageEntry.from_json(v) for k, v in value.items()}
    else:
        setattr(bad, field, value)
    with pytest.raises(MismatchError, match=re.escape(words)):
        bad.write(tmp_path / "nowhere")
    assert not (tmp_path / "nowhere").exists()


def test_a_blend_call_reads_its_basis_once(tmp_path, small_manifold, monkeypatch):
    """blend and blend_path given a folder read and check its manifest once per call; given a
    Basis, none (the manifold is checked once per Basis, however many blends)."""
    import numpy as np
    from helpers import write_basis

    from mitsuba_manifold.basis import blend as bl
    from mitsuba_manifold.manifold.model import Manifold

    m = Manifold.load(small_manifold)
    rng = np.random.default_rng(0)
    images = {"base": rng.random((3, 4, 3), np.float32)}
    images.update({n: rng.random((3, 4, 3), np.float32) for n in m.names})
    write_basis(str(tmp_path / "b"), small_manifold, images)
    reads = []
    real = Manifest.read.__func__
    monkeypatch.setattr(
        Manifest, "read", classmethod(lambda cls, folder: reads.append(folder) or real(cls, folder))
    )
    bl.blend(str(tmp_path / "b"), small_manifold, x=m.latent[0])
    assert len(reads) == 1
    bl.blend_path(str(tmp_path / "b"), small_manifold, m.names[0], m.names[1], steps=3)
    assert len(reads) == 2
    basis = bl.Basis.load(str(tmp_path / "b"))
    checks = []
    check = basis.check_manifold
    monkeypatch.setattr(basis, "check_manifold", lambda mf=None: checks.append(mf) or check(mf))
    for x in m.latent[:3]:
        bl.blend(basis, small_manifold, x=x)
    assert len(reads) == 3 and len(checks) == 3 and len(basis._checked) == 1


def test_a_version_1_manifest_upgrades_given_the_manifold_it_was_made_with(small_manifold):
    """Version 1 recorded the manifold file's SHA-256 and raw names; the upgrade to version 2
    (the manifold's content identity, escaped keys) needs that file, so it is
    :meth:`Manifest.upgraded`, not a rewrite of the JSON alone."""
    from mitsuba_manifold._util.cache import file_hash
    from mitsuba_manifold.basis.folder import manifold_file_identity

    v1 = dict(
        V1,
        manifold=small_manifold,
        manifold_hash=file_hash(small_manifold),
        images=dict(V1["images"], **{"Odd Name": {"file": "Odd Name.exr", "time_s": 1.0}}),
    )
    old = Manifest.from_json(v1)
    new = old.upgraded(small_manifold)
    assert (new.version, new.manifold_hash) == (2, manifold_file_identity(small_manifold))
    assert set(new.images) == {"base", "chrome"}  # a raw name that escaping changes is dropped
    assert new.check() is new and old.version == 1  # the one read is left as it was
    other = Manifest.from_json(dict(v1, manifold_hash="f" * 64))
    assert other.upgraded(small_manifold) is other  # made with another file: kept as it is


@pytest.mark.render  # the chunk bookkeeping belongs to the jobs that write chunks (render.jobs)
def test_a_file_written_before_keeps_its_chunk_mark(tmp_path):
    from mitsuba_manifold.render.jobs.chunks import ChunkMark

    (tmp_path / MANIFEST).write_text(WRITTEN_BEFORE)
    mark = ChunkMark.of(Manifest.read(tmp_path))
    assert (mark.chunk_complete, mark.chunk_run.pid, mark.chunk_key) == (True, 7, "e" * 64)


@pytest.mark.render
def test_the_chunk_marks_read_through_their_old_names_with_a_deprecation_warning():
    from mitsuba_manifold.render.jobs.chunks import ChunkMark

    m = Manifest.from_json(V2)
    with pytest.deprecated_call():
        assert m.chunk_key == "k"
    with pytest.deprecated_call():
        m.chunk_key = None
    assert "chunk_key" not in m.to_json() and ChunkMark.of(m) == ChunkMark()
