"""The manifold file's schema (issue 20, item 9 and the crafted-field tracebacks): every crafted
field is one FormatError naming it, in the library and as one `error:` line of a tool."""

import json
import os
import sys
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mitsuba_manifold.errors import FormatError
from mitsuba_manifold.manifold.model import Manifold

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from guarantees_helpers import assert_one_error, run_tool  # noqa: E402


@pytest.fixture(scope="module")
def saved(small_manifold):
    """``(meta, arrays)`` of the small manifold's file."""
    with np.load(small_manifold, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    return json.loads(str(arrays.pop("meta"))), arrays


def craft(path, meta, arrays, **changes):
    """Write ``meta`` and ``arrays`` with ``changes`` (``meta_<field>`` for meta fields) to ``path``."""
    meta, arrays = dict(meta), dict(arrays)
    for key, value in changes.items():
        if key.startswith("meta_"):
            meta[key[5:]] = value
        else:
            arrays[key] = value
    np.savez(path, meta=np.array(json.dumps(meta)), **arrays)
    return path


def _latent(arrays, f):
    a = np.array(arrays["latent"])
    return f(a)


CRAFTED = [  # (field, changes as a function of the saved arrays)
    ("version", lambda a: {"meta_version": True}),
    ("interpolant", lambda a: {"meta_interpolant": None}),
    ("interpolant", lambda a: {"meta_interpolant": {"kind": "shepard", "taper": "x"}}),
    ("interpolant", lambda a: {"meta_interpolant": "gp"}),
    ("history", lambda a: {"history": np.array(["abc"])}),
    ("history", lambda a: {"history": np.ones((2, 2))}),
    ("latent", lambda a: {"latent": np.array("0,0")}),
    ("latent", lambda a: {"latent": a["latent"].astype(complex)}),
    ("latent", lambda a: {"latent": a["latent"] > 0}),
    (
        "latent",
        lambda a: {"latent": _latent(a, lambda x: np.vstack([x[:1], x[:1], x[2:]]))},
    ),  # coincident
    ("latent", lambda a: {"latent": a["latent"][:3]}),
    (
        "latent",
        lambda a: {
            "latent": _latent(
                a, lambda x: np.where(np.arange(x.size).reshape(x.shape) == 0, 1e300, x)
            )
        },
    ),
    ("database", lambda a: {"meta_database": ["a", "b"]}),
    ("hashes", lambda a: {"meta_hashes": [1, 2]}),
    ("info", lambda a: {"meta_info": "fit"}),
    ("info", lambda a: {"meta_info": {"dims": "8x8x16"}}),
    ("length_scale", lambda a: {"meta_length_scale": "1.0"}),
    ("length_scale", lambda a: {"meta_length_scale": -1}),
    ("names", lambda a: {"meta_names": "steel"}),
    ("names", lambda a: {"meta_names": None}),
    ("noise", lambda a: {"meta_noise": [1e-4]}),
    ("features", lambda a: {"meta_features": "sqrt"}),
    ("table_gram", lambda a: {"table_gram": np.zeros_like(a["table_gram"])}),
    ("table_gram", lambda a: {"table_gram": -np.eye(len(a["table_gram"]))}),
    ("table_gram", lambda a: {"table_gram": np.eye(2)}),
    (
        "table_gram",
        lambda a: {"table_gram": np.diag([1.0] * (len(a["table_gram"]) - 1) + [np.inf])},
    ),
    (
        "cos_gram",
        lambda a: {"cos_gram": a["cos_gram"] * np.where(np.eye(len(a["cos_gram"])), 1, 3)},
    ),
    ("gram", lambda a: {"gram": np.triu(a["gram"])}),
    ("albedos", lambda a: {"albedos": a["albedos"][:, :2]}),
]


@pytest.mark.parametrize(
    "field, change", CRAFTED, ids=[f"{f}-{i}" for i, (f, _) in enumerate(CRAFTED)]
)
def test_each_crafted_field_is_one_error_naming_it(tmp_path, saved, small_db, field, change):
    meta, arrays = saved
    path = craft(tmp_path / "m.npz", meta, arrays, **change(arrays))
    with pytest.raises(FormatError) as e:
        Manifold.load(path)
    assert f"its {field} " in str(e.value) and "\n" not in str(e.value), str(e.value)
    rc, _, err = run_tool("project", os.path.join(small_db, "chrome.binary"), "--manifold", path)
    assert_one_error(rc, err, f"its {field} ", str(path))


def test_a_gram_matrix_of_other_tables_is_refused_when_the_tables_are_read(tmp_path, saved):
    """A table_gram that looks like one (symmetric, PSD, positive diagonal) but is not of the
    tables the file names: the first read of the tables says so."""
    meta, arrays = saved
    rng = np.random.default_rng(1)
    other = rng.random((len(meta["names"]), 50))
    for name in ("table_gram", "cos_gram"):
        m = Manifold.load(craft(tmp_path / f"{name}.npz", meta, arrays, **{name: other @ other.T}))
        with pytest.raises(
            FormatError, match=f"manifold's {name} is not the Gram matrix of its tables"
        ):
            m.tables()
    m = Manifold.load(craft(tmp_path / "fine.npz", meta, arrays))
    assert m.tables().shape[0] == len(meta["names"])  # the saved Gram matrices pass


def test_entries_are_refused_by_their_size_before_they_are_read(tmp_path, saved):
    meta, arrays = saved
    path = craft(tmp_path / "m.npz", meta, arrays)
    with zipfile.ZipFile(path, "a", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("junk.npy", b"\x00not an npy" * 1000)  # never read: the load succeeds
    assert Manifold.load(path).names == meta["names"]
    inflated = tmp_path / "inflated.npz"
    craft(inflated, meta, {k: v for k, v in arrays.items() if k != "latent"})
    with (
        zipfile.ZipFile(inflated, "a", compression=zipfile.ZIP_DEFLATED) as zf,
        zf.open("latent.npy", "w") as f,
    ):
        np.lib.format.write_array(f, arrays["latent"])
        f.write(bytes(32 << 20))  # 32 MB of zeros, a few kB stored
    with pytest.raises(
        FormatError, match="its latent array is .* bytes, more than its shape allows"
    ):
        Manifold.load(inflated)
    bad_header = tmp_path / "header.npz"
    craft(bad_header, meta, {k: v for k, v in arrays.items() if k != "history"})
    with zipfile.ZipFile(bad_header, "a") as zf, zf.open("history.npy", "w") as f:
        np.lib.format.write_array_header_1_0(
            f, {"descr": "<f8", "fortran_order": False, "shape": (10**14,)}
        )
    with pytest.raises(
        FormatError, match="its history array is longer than"
    ):  # 10**14 floats, no data
        Manifold.load(bad_header)
    with zipfile.ZipFile(bad_header, "w") as zf:
        zf.writestr("meta.npy", np.lib.format.magic(1, 0) + b"\x10\x00{'descr': '<U5', 'shape': (")
    with pytest.raises(FormatError, match="its meta entry has a damaged header"):
        Manifold.load(bad_header)


JSON = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-10, 10)
    | st.floats(allow_nan=True)
    | st.text(max_size=5),
    lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=4), c, max_size=3),
    max_leaves=6,
)


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    field=st.sampled_from(
        [
            "version",
            "names",
            "database",
            "hashes",
            "length_scale",
            "noise",
            "features",
            "info",
            "interpolant",
        ]
    ),
    value=JSON,
)
def test_any_json_in_a_meta_field_loads_or_is_refused_naming_it(tmp_path, saved, field, value):
    meta, arrays = saved
    path = craft(tmp_path / "m.npz", meta, arrays, **{f"meta_{field}": value})
    try:
        Manifold.load(path)
    except FormatError as e:
        assert f"its {field} " in str(e), str(e)


ARRAY = st.tuples(
    st.sampled_from(["f8", "f4", "i4", "u1", "c16", "?", "U2"]),
    st.lists(st.integers(0, 9), max_size=3),
)


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    field=st.sampled_from(["latent", "history", "albedos", "gram", "table_gram", "cos_gram"]),
    spec=ARRAY,
    seed=st.integers(0, 3),
)
def test_any_array_in_an_array_field_loads_or_is_refused_naming_it(
    tmp_path, saved, field, spec, seed
):
    meta, arrays = saved
    dtype, shape = spec
    value = np.random.default_rng(seed).standard_normal(shape).astype(dtype)
    path = craft(tmp_path / "m.npz", meta, arrays, **{field: value})
    try:
        Manifold.load(path)
    except FormatError as e:
        assert f"its {field} " in str(e), str(e)


def test_api_values_of_the_wrong_kind_are_one_input_error(small_db, small_manifold):
    """Tracebacks of issue 20: a text prune, an empty names list, a text interpolant parameter."""
    from mitsuba_manifold.errors import InputError

    m = Manifold.load(small_manifold)
    with pytest.raises(InputError, match=r"`prune` must be in \[0, 1\), got '0.1'"):
        m.interpolate(m.latent[0], prune="0.1")
    with pytest.raises(InputError, match="`names` is empty"):
        Manifold.fit(small_db, names=[])
    with pytest.raises(InputError, match="interpolant 'shepard'"):
        Manifold.fit(small_db, interpolant={"taper": "x"}, max_iter=1)


def _written_by_version(path, meta, arrays, version):
    """The small manifold as the writer of format ``version`` wrote it: version 1 without the
    interpolant, the preset and the table Gram matrices; the first version-2 files without
    ``cos_gram`` ("2-early"); version 3 with a material added after the fit."""
    meta, arrays = dict(meta), dict(arrays)
    if version == 1:
        meta.pop("interpolant")
        meta["info"] = {k: v for k, v in meta["info"].items() if k != "preset"}
        arrays = {k: arrays[k] for k in ("latent", "history", "albedos", "gram")}
    if version == "2-early":
        arrays.pop("cos_gram")
    if version == 3:
        meta["added"] = [
            {
                "name": meta["names"][-1],
                "source": "file",
                "path": "/tables/added.binary",
                "hash": meta["hashes"][-1],
                "origin": None,
            }
        ]
    meta["version"] = 2 if version == "2-early" else version
    np.savez(path, meta=np.array(json.dumps(meta)), **arrays)
    return path


@pytest.mark.parametrize("version", [1, "2-early", 2, 3])
def test_a_file_of_every_version_written_before_reads_the_same(tmp_path, saved, version):
    from mitsuba_manifold.manifold.file import io

    meta, arrays = saved
    path = _written_by_version(tmp_path / "old.npz", meta, arrays, version)
    old = io.read(str(path))
    now = io.read(str(_written_by_version(tmp_path / "now.npz", meta, arrays, 2)))
    assert old["names"] == now["names"] and np.array_equal(old["latent"], now["latent"])
    if version == 1:  # the paper's GP on the stored length scale and noise, as used then
        assert old["interpolant"] == {"kind": "gp", "exact": True}
        assert old["record"].preset == "paper" and old["table_gram"] is None
    else:
        assert old["interpolant"] == meta["interpolant"]
        assert old["record"].as_info() == now["record"].as_info()
    assert (old["cos_gram"] is None) == (version in (1, "2-early"))
    assert old["added"] == (meta_added(path) if version == 3 else None)
    m = Manifold(**old)
    again = tmp_path / "again.npz"
    m.save(again)  # written as the newest version of what it holds
    with np.load(again) as z:
        assert json.loads(str(z["meta"]))["version"] == (3 if version == 3 else 2)
    assert io.read(str(again))["interpolant"].items() >= old["interpolant"].items()


def meta_added(path):
    with np.load(path) as z:
        return json.loads(str(z["meta"]))["added"]


def test_upgrades_are_declared_for_every_earlier_version():
    from mitsuba_manifold.manifold.file.schema import ManifoldMeta

    assert sorted(ManifoldMeta.UPGRADES) == list(range(1, ManifoldMeta.VERSION))
    v1 = {"format": "mitsuba-manifold", "version": 1, "info": None, "added": "ignored"}
    assert ManifoldMeta.upgrade(v1) == {
        "format": "mitsuba-manifold",
        "version": 3,
        "info": {"preset": "paper"},
        "interpolant": {"kind": "gp", "exact": True},
    }
    assert v1["version"] == 1 and v1["info"] is None  # the object read is left as it was


def test_a_shipped_manifold_saved_again_writes_its_meta_entry_byte_for_byte(tmp_path):
    from mitsuba_manifold.manifold.file.shipped import SHIPPED, resolve_manifold

    for name in SHIPPED:
        path = resolve_manifold(name)
        Manifold.load(path).save(tmp_path / "again.npz")
        with np.load(path) as old, np.load(tmp_path / "again.npz") as new:
            assert str(new["meta"]) == str(old["meta"]), name
