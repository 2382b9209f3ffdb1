"""The basis manifest as a type (:class:`Manifest`): files written before read the same."""

import json

import pytest

from mitsuba_manifold.basis.folder import MANIFEST, Manifest, read_manifest, write_manifest
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
    assert m.to_json() == data and read_manifest(tmp_path) == data
    assert m.resolution == (32, 24) and m.images["chrome"]["time_s"] == 2.0
    out = tmp_path / "again"
    out.mkdir()
    m.write(out)
    assert json.loads((out / MANIFEST).read_text()) == data


def test_what_a_manifest_leaves_unsaid_has_its_meaning():
    old, new = Manifest.from_json(V1), Manifest.from_json(V2)
    assert (old.sensor, old.sensor_index, old.held_components) == (None, 0, ["l1"])
    assert (new.sensor_index, new.held_components, new.extra) == (
        1,
        ["l1", "l2+", "cross"],
        {"chunk_key": "k"},
    )
    assert (
        old.differences(dict(V1, sensor=0)) == [] and new.differences(V2, ignore=("sensor",)) == []
    )
    assert Manifest.from_json(dict(V1, spp=32)).differences(V1) == ["spp"]


@pytest.mark.parametrize(
    "field, value, words",
    [
        ("spp", 0, "spp must be a positive integer"),
        ("resolution", [32], "resolution must be [width, height]"),
        ("mode", "fast", "mode must be one of"),
        ("scene_hash", "xyz", "'scene_hash' must be a SHA-256"),
    ],
)
def test_a_bad_field_is_refused_naming_the_file_and_the_field(tmp_path, field, value, words):
    (tmp_path / MANIFEST).write_text(json.dumps(dict(V1, **{field: value})))
    with pytest.raises(MismatchError, match=str(tmp_path)) as e:
        Manifest.read(tmp_path)
    assert words in str(e.value)
    bad = Manifest.from_json(V1)
    setattr(bad, field, value)
    with pytest.raises(MismatchError, match=words.replace("[", r"\[")):
        write_manifest(tmp_path / "nowhere", bad)
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
