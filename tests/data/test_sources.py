"""Measured materials from every source: NBRDF networks (evaluated as on paper), the built-in
sets, folders mixing kinds, name clashes, Mitsuba measured files refused when anisotropic."""

import json
import math
import os
import struct

import numpy as np
import pytest

from mitsuba_manifold.data import merl, nbrdf, sources
from mitsuba_manifold.data.database import Database, write_database
from mitsuba_manifold.errors import FormatError, InputError, UnknownMaterialError


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("MITSUBA_MANIFOLD_CACHE", str(tmp_path / "cache"))


def _paper_network(name="paper"):
    """A 6-21-21-3 network whose value is worked out by hand below: hidden unit 0 of layer 1 is
    cos(theta_h), unit 0 of layer 2 is relu(2 cos(theta_h) - 0.5), the output (u, u/2, -1)."""
    w1 = np.zeros((1, 6, 21), np.float32)
    w1[0, 2, 0] = 1.0
    w2 = np.zeros((1, 21, 21), np.float32)
    w2[0, 0, 0] = 2.0
    b2 = np.zeros((1, 21), np.float32)
    b2[0, 0] = -0.5
    w3 = np.zeros((1, 21, 3), np.float32)
    w3[0, 0] = [1.0, 0.5, 0.0]
    b3 = np.array([[0.0, 0.0, -1.0]], np.float32)
    return nbrdf.NetworkSet((name,), w1, np.zeros((1, 21), np.float32), w2, b2, w3, b3)


def test_a_network_evaluates_as_computed_by_hand():
    nets = _paper_network()
    # theta_h = 0: h1 = 1, h2 = 2 - 0.5 = 1.5, y = (1.5, 0.75, -1), f = exp(y) - 1 clamped at 0
    v = nbrdf.features([0.0], [0.3], [1.0])
    np.testing.assert_allclose(
        nets.evaluate("paper", v)[0], [math.exp(1.5) - 1, math.exp(0.75) - 1, 0.0], rtol=1e-6
    )
    # theta_h = 60 degrees: h1 = 0.5, h2 = relu(1 - 0.5) = 0.5, y = (0.5, 0.25, -1)
    v = nbrdf.features([math.pi / 3], [0.1], [0.0])
    np.testing.assert_allclose(
        nets.evaluate("paper", v)[0], [math.exp(0.5) - 1, math.exp(0.25) - 1, 0.0], rtol=1e-5
    )
    # theta_h = 80 degrees: h1 = 0.174, h2 = relu(0.347 - 0.5) = 0, y = b3: f = (0, 0, 0)
    v = nbrdf.features([math.radians(80)], [0.1], [0.0])
    np.testing.assert_allclose(nets.evaluate("paper", v)[0], [0.0, 0.0, 0.0], atol=1e-7)


def test_tabulation_puts_the_hand_values_at_the_bins_positions():
    nets, dims = _paper_network(), (4, 3, 6)
    above = merl.above_horizon(dims)
    for positions in nbrdf.POSITIONS:
        table = nbrdf.tabulate(nets, "paper", dims, positions)
        th = nbrdf.grid_positions(dims, positions)[0]
        u = np.maximum(2 * np.cos(th) - 0.5, 0.0)
        np.testing.assert_allclose(
            table[0], np.where(above, np.expm1(u), 0.0), rtol=1e-5, atol=1e-7
        )
        np.testing.assert_allclose(
            table[1], np.where(above, np.expm1(u / 2), 0.0), rtol=1e-5, atol=1e-7
        )
        assert not table[2].any()
    assert nbrdf.tabulate(nets, "paper", dims, "starts")[0, 0, 0, 0] == pytest.approx(
        math.exp(1.5) - 1, rel=1e-6
    )


def test_many_networks_at_once_match_one_at_a_time():
    nets = nbrdf.NetworkSet.load(nbrdf.WEIGHTS_PATH, "nielsen")
    many = nbrdf.tabulate_many(nets, ["notebook", "bluebook"], (8, 8, 16))
    np.testing.assert_array_equal(many[1], nbrdf.tabulate(nets, "bluebook", (8, 8, 16)))


def test_builtin_sets_and_the_unique_names_of_all():
    sizes = {name: len(Database(name).names) for name in ("merl", "rgl", "nielsen", "all", "sgd")}
    assert sizes == {"merl": 100, "rgl": 51, "nielsen": 8, "all": 159, "sgd": 100}
    names = Database("all").names
    assert len(set(names)) == 159
    assert "cardboard" not in names and {"cardboard-rgl", "cardboard-nielsen"} <= set(names)
    assert "cardboard" in Database("rgl").names and "chrome" in names


def test_a_builtin_set_needs_no_files_and_caches_its_tables_by_content(tmp_path):
    db = Database("nielsen@8x8x16")
    assert db.folder == "nielsen@8x8x16" and db.dims == (8, 8, 16)
    table = db.reflectance("bluebook")
    nets = nbrdf.NetworkSet.load(nbrdf.WEIGHTS_PATH, "nielsen")
    exact = nbrdf.tabulate(nets, "bluebook", (8, 8, 16), sources.SET_POSITIONS["nielsen"])
    np.testing.assert_allclose(table, exact, rtol=1e-3)  # float16 cache
    cached = os.listdir(tmp_path / "cache" / "builtin")
    assert cached == [db.hash("bluebook") + ".refl16.npy"]
    assert db.hash("bluebook") != Database("nielsen@8x8x17").hash(
        "bluebook"
    )  # resolution is in the hash
    np.testing.assert_array_equal(Database("nielsen@8x8x16").reflectance("bluebook"), table)


def _write_keras(folder, nets, name):
    """The authors' files of one network: Keras ``save_weights`` layout and the model's JSON."""
    import h5py

    with h5py.File(os.path.join(folder, name + ".h5"), "w") as f:
        layers = ["dense_1", "dense_2", "dense_3", "lambda_1"]
        f.attrs["layer_names"] = [n.encode() for n in layers]
        for k, layer in enumerate(layers[:3]):
            g = f.create_group(layer)
            g.attrs["weight_names"] = [f"{layer}/kernel:0".encode(), f"{layer}/bias:0".encode()]
            g[f"{layer}/kernel:0"] = getattr(nets, f"w{k + 1}")[0]
            g[f"{layer}/bias:0"] = getattr(nets, f"b{k + 1}")[0]
        f.create_group("lambda_1").attrs["weight_names"] = []
    dense = [
        {"class_name": "Dense", "config": {"units": u, "activation": a}}
        for u, a in ((21, "relu"), (21, "relu"), (3, "linear"))
    ]
    with open(os.path.join(folder, name + ".json"), "w") as f:
        json.dump({"class_name": "Sequential", "config": {"layers": dense}}, f)


def test_a_folder_mixes_binary_files_networks_and_the_authors_files(tmp_path):
    folder = tmp_path / "mixed"
    folder.mkdir()
    dims = (8, 8, 16)
    steel = sources.builtin("sgd")[[s.name for s in sources.builtin("sgd")].index("steel")]
    merl.write_binary(folder / "steel.binary", merl.to_stored(steel.table(dims)))
    nielsen = nbrdf.NetworkSet.load(nbrdf.WEIGHTS_PATH, "nielsen")
    nielsen.subset(["notebook"]).save(folder / "my_notebook_rgb.npz")
    _write_keras(folder, nielsen.subset(["bluebook"]), "blue_book")
    db = Database(folder)
    assert db.names == ["blue_book", "my_notebook", "steel"] and db.dims == dims
    assert {n: s.kind for n, s in db.sources.items()} == {
        "blue_book": "nbrdf",
        "my_notebook": "nbrdf",
        "steel": "binary",
    }
    np.testing.assert_allclose(
        db.reflectance("blue_book"), nbrdf.tabulate(nielsen, "bluebook", dims, "starts"), rtol=1e-3
    )
    np.testing.assert_allclose(db.reflectance("steel"), steel.table(dims), rtol=1e-6)
    assert db.stack().shape == (3, 3 * 8 * 8 * 16)


def test_two_files_naming_one_material_are_refused(tmp_path):
    nielsen = nbrdf.NetworkSet.load(nbrdf.WEIGHTS_PATH, "nielsen")
    nielsen.subset(["notebook"]).save(tmp_path / "notebook.npz")
    _write_keras(tmp_path, nielsen.subset(["notebook"]), "notebook_rgb")
    with pytest.raises(
        FormatError, match=r"two files give the material 'notebook'.*notebook.*\.(npz|h5)"
    ):
        Database(tmp_path)


def test_a_users_file_clashing_with_a_builtin_set_is_refused_and_nothing_written(tmp_path):
    folder = tmp_path / "mine"
    folder.mkdir()
    nbrdf.NetworkSet.load(nbrdf.WEIGHTS_PATH, "nielsen").subset(["notebook"]).save(
        folder / "notebook.npz"
    )
    with pytest.raises(FormatError, match="two materials are named 'notebook'.*rename one"):
        write_database(tmp_path / "db", ["nielsen", folder])
    assert not (tmp_path / "db").exists()


def test_a_database_folder_names_its_sources_and_exports_binary_files(tmp_path):
    db = write_database(tmp_path / "db", ["nielsen", "rgl"], (8, 8, 16))
    assert (
        len(db.names) == 59
        and "cardboard-nielsen" in db.names
        and not list((tmp_path / "db").glob("*.binary"))
    )
    out = write_database(
        tmp_path / "exported",
        [tmp_path / "db"],
        (8, 8, 16),
        materials=["cardboard-rgl"],
        export=True,
    )
    assert out.names == ["cardboard-rgl"] and out.files_only
    np.testing.assert_allclose(
        out.reflectance("cardboard-rgl"), db.reflectance("cardboard-rgl"), rtol=1e-3, atol=1e-6
    )
    with pytest.raises(UnknownMaterialError, match="unknown material"):
        write_database(tmp_path / "x", ["nielsen"], (8, 8, 16), materials=["nope"], export=True)
    assert not (tmp_path / "x").exists()


def _tensor_file(path, n_phi):
    """A tensor_file header with ``n_phi`` incident azimuths (the fields Mitsuba's measured reads)."""
    fields = [("phi_i", 10, (n_phi,)), ("theta_i", 10, (4,))]
    head = b"tensor_file\0" + bytes([1, 0]) + struct.pack("<I", len(fields))
    for name, dtype, shape in fields:
        head += (
            struct.pack("<H", len(name)) + name.encode() + struct.pack("<HBQ", len(shape), dtype, 0)
        )
        head += b"".join(struct.pack("<Q", n) for n in shape)
    path.write_bytes(head + bytes(64))


def test_anisotropic_measured_files_are_refused_by_their_header(tmp_path):
    _tensor_file(tmp_path / "brushed_rgb.bsdf", 3)
    with pytest.raises(
        FormatError, match=r"brushed_rgb\.bsdf: an anisotropic measurement \(3 incident azimuths\)"
    ):
        Database(tmp_path)
    (tmp_path / "brushed_rgb.bsdf").unlink()
    _tensor_file(tmp_path / "matte_spec.bsdf", 1)
    assert Database(tmp_path).names == ["matte"]  # named without _spec
    (tmp_path / "junk.bsdf").write_bytes(b"not a tensor")
    with pytest.raises(FormatError, match="junk.bsdf: not a Mitsuba tensor_file"):
        Database(tmp_path)


def test_rgl_layout_files_are_isotropic_tensor_files(measured_files):
    for path in measured_files.values():
        f = os.path.basename(path)
        src = sources.MeasuredFile(sources.material_name(f), path).check()
        assert not src.name.endswith("_rgb")


def test_builtin_names_in_the_command_line_tools(tmp_path):
    from mitsuba_manifold.apps.cli import fit_manifold, make_database

    assert make_database.main(
        ["--out", str(tmp_path / "db"), "--from", "nielsen", "--resolution", "8,8,16"]
    ) in (0, None)
    assert json.loads((tmp_path / "db" / "sources.json").read_text())["from"] == ["nielsen"]
    rc = fit_manifold.main(["nielsen@8x8x16", "--out", str(tmp_path / "m.npz"), "--q", "2"])
    assert rc in (0, None)
    from mitsuba_manifold import Manifold

    m = Manifold.load(tmp_path / "m.npz")
    assert m.database == "nielsen@8x8x16" and m.n == 8
    assert m.open_database().hash("notebook") == m.hashes[m.names.index("notebook")]


def test_project_takes_a_material_of_any_source(tmp_path, capsys):
    from mitsuba_manifold.apps.cli import fit_manifold, project

    fit_manifold.main(["nielsen@8x8x16", "--out", str(tmp_path / "m.npz"), "--q", "2"])
    capsys.readouterr()
    project.main(
        [
            "rgl:paper_white",
            "--manifold",
            str(tmp_path / "m.npz"),
            "--json",
            str(tmp_path / "p.json"),
        ]
    )
    result = json.loads((tmp_path / "p.json").read_text())
    assert result["table"] == "rgl:paper_white" and result["nearest"] in Database("nielsen").names
    nets = nbrdf.NetworkSet.load(nbrdf.WEIGHTS_PATH, "nielsen")
    nets.subset(["notebook"]).save(
        tmp_path / "notebook.npz", positions=sources.SET_POSITIONS["nielsen"]
    )
    capsys.readouterr()
    project.main([str(tmp_path / "notebook.npz"), "--manifold", str(tmp_path / "m.npz")])
    out = capsys.readouterr().out
    assert "nearest training material notebook" in out and "weights: notebook:1," in out
    with pytest.raises(SystemExit):
        project.main(["rgl:paper_whyte", "--manifold", str(tmp_path / "m.npz")])
    assert "did you mean 'paper_white'" in capsys.readouterr().err


@pytest.mark.render  # the pipeline imports the rendering subsystem
def test_the_main_job_runs_on_the_measured_merl_set_and_refuses_unknown_databases(tmp_path):
    from mitsuba_manifold.apps.pipeline import MainJob

    assert MainJob(str(tmp_path / "out")).database == "merl"
    MainJob(str(tmp_path / "out"), database="rgl", res=8).check()
    with pytest.raises(
        InputError, match=r"`database` nope:.*does not exist.*built-in databases: merl, rgl"
    ):
        MainJob(str(tmp_path / "out"), database="nope").check()
    assert not (tmp_path / "out").exists()


def test_a_truncated_measured_file_is_refused_by_its_size(tmp_path, capsys, measured_files):
    """A ``.bsdf`` cut short is refused by the sizes its header gives, before Mitsuba reads it:
    as a material, in a database folder and by ``make_database.py``, which writes nothing."""
    from mitsuba_manifold.apps.cli import make_database

    data = open(measured_files["paper_blue"], "rb").read()
    folder = tmp_path / "half"
    folder.mkdir()
    (folder / "half_rgb.bsdf").write_bytes(data[: len(data) // 2])
    message = rf"half_rgb\.bsdf: file is truncated \({len(data) // 2} bytes; its header needs {len(data)}\)"
    with pytest.raises(FormatError, match=message):
        sources.material_source(str(folder / "half_rgb.bsdf"))
    with pytest.raises(FormatError, match=message):
        Database(folder)
    with pytest.raises(SystemExit) as exit_:
        make_database.main(["--from", str(folder), "--out", str(tmp_path / "db")])
    assert exit_.value.code == 2 and "file is truncated" in capsys.readouterr().err
    assert not (tmp_path / "db").exists()


def test_project_and_add_take_a_material_as_the_tools_do(tmp_path, measured_files):
    """``Manifold.project`` / ``Manifold.add`` take ``SET:NAME`` and any material file, as the
    tools do; a ``.bsdf`` without Mitsuba's reader (a fresh process that did not import the
    rendering subsystem) is refused with the fix, never read as a MERL file."""
    import subprocess
    import sys

    from mitsuba_manifold import Manifold

    m = Manifold.fit("nielsen@8x8x16", q=2)
    table = sources.material_source("rgl:paper_white").table(m.dims)
    np.testing.assert_array_equal(m.project("rgl:paper_white").x, m.project(table).x)
    with pytest.raises(UnknownMaterialError, match="did you mean 'paper_white'"):
        m.project("rgl:paper_whyte")
    m.save(tmp_path / "m.npz")
    info = m.add("rgl:paper_white")
    assert info.name == "paper_white" and m.added[-1].origin == "rgl:paper_white"
    code = (
        "import sys; from mitsuba_manifold import Manifold\n"
        "from mitsuba_manifold.errors import UnavailableError\n"
        f"m = Manifold.load({str(tmp_path / 'm.npz')!r})\n"
        "for call in (m.project, m.add):\n"
        "    try: call(sys.argv[1])\n"
        "    except UnavailableError as e: print(e)\n"
        "assert 'mitsuba' not in sys.modules\n"
    )
    root = os.path.join(os.path.dirname(__file__), "..", "..")
    r = subprocess.run(
        [sys.executable, "-c", code, measured_files["paper_blue"]],
        capture_output=True,
        text=True,
        cwd=root,
        check=False,
    )
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert len(lines) == 2 and all("import mitsuba_manifold.render first" in ln for ln in lines)


def test_stack_reads_the_half_precision_cache_straight_into_its_rows(tmp_path):
    """The stack of a built-in set: its tables as made, then as read back from the float16
    cache into the rows, then with a damaged cache file made again."""
    names = ["bluebook", "glossyredpaper", "greencloth"]
    db = Database("nielsen@8x8x16")
    cold = db.stack(names)  # made into the cache
    ref = np.stack([db.reflectance(n).reshape(-1) for n in names])
    assert cold.dtype == np.float32 and cold.shape == (3, 3 * 8 * 8 * 16)
    assert cold.flags.c_contiguous and cold.flags.writeable
    warm = Database("nielsen@8x8x16").stack(names)  # read from the cache
    assert np.array_equal(cold, ref) and np.array_equal(warm, ref)
    path = tmp_path / "cache" / "builtin" / (db.hash("glossyredpaper") + ".refl16.npy")
    path.write_bytes(path.read_bytes()[:-100])  # cut short: made again
    assert np.array_equal(Database("nielsen@8x8x16").stack(names), ref)
    assert np.array_equal(np.load(path).astype(np.float32).reshape(-1), ref[1])


def test_a_folder_given_as_a_material_file_says_it_is_a_folder(tmp_path, capsys):
    """A folder where a material file is expected: one line saying it is a folder and what to
    give, from the reader and from a tool (``fit_manifold.py --add``), not "no such file"."""
    from mitsuba_manifold.apps.cli import fit_manifold

    folder = tmp_path / "tables.binary"
    folder.mkdir()
    with pytest.raises(InputError) as info:
        sources.material_source(str(folder))
    message = str(info.value)
    assert f"material {folder} is a folder, not a file" in message and ".bsdf" in message
    assert "\n" not in message and "no such file" not in message
    with pytest.raises(SystemExit) as exit_:
        fit_manifold.main(
            ["nielsen@8x8x16", "--add", str(folder), "--out", str(tmp_path / "m.npz")]
        )
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and f"--add {folder}: material {folder} is a folder" in err
    assert not (tmp_path / "m.npz").exists()


def _damage(path, change, reseal=False):
    """Rewrite the array of a cache file in place, its header and checksum trailer kept (what a
    bad disk or an editor leaves: a valid ``.npy`` of the right shape); ``reseal``: with a
    checksum of the new bytes (what a writer of bad values would leave)."""
    from mitsuba_manifold._util import cache

    data = bytearray(open(path, "rb").read())
    value = np.load(path)
    start = len(data) - cache.TRAILER_SIZE - value.nbytes
    data[start : start + value.nbytes] = change(value).astype(value.dtype).tobytes()
    if reseal:
        data = data[: -cache.TRAILER_SIZE]
    open(path, "wb").write(bytes(data))
    if reseal:
        cache.seal(path)


@pytest.mark.parametrize("damage", ["doubled", "nan"])
def test_a_damaged_table_cache_is_found_made_again_and_named(tmp_path, caplog, damage):
    """A cached table whose values changed on disk (doubled: a valid float16 array of the right
    shape; or NaN) is never used: every reader (the whole table, the rows of a stack) makes it
    again, and one line names the file."""
    names = ["bluebook", "glossyredpaper"]
    db = Database("nielsen@8x8x16")
    ref = db.stack(names).copy()
    path = tmp_path / "cache" / "builtin" / (db.hash("glossyredpaper") + ".refl16.npy")
    change = (lambda v: 2 * v) if damage == "doubled" else (lambda v: np.where(v > 0, np.nan, v))
    readers = [lambda d: np.stack([d.reflectance(n) for n in names])]
    if damage == "doubled":  # the rows of a stack check the checksum alone
        readers.append(lambda d: d.stack(names))
    for read in readers:
        _damage(path, change, reseal=damage == "nan")
        caplog.clear()
        with caplog.at_level("WARNING", logger="mitsuba_manifold"):
            got = read(Database("nielsen@8x8x16"))
        assert np.array_equal(got.reshape(ref.shape), ref)
        lines = [r.getMessage() for r in caplog.records]
        assert len(lines) == 1 and str(path) in lines[0], lines
        assert ("checksum" if damage == "doubled" else "NaN") in lines[0]
        assert np.array_equal(np.load(path).astype(np.float32).reshape(-1), ref[1])


def test_a_source_whose_table_is_not_finite_is_refused_naming_the_material(tmp_path, monkeypatch):
    db = Database("nielsen@8x8x16")
    source = db.sources["bluebook"]
    monkeypatch.setattr(
        type(source), "table", lambda self, dims: np.full((3,) + tuple(dims), np.nan, np.float32)
    )
    with pytest.raises(FormatError) as info:
        db.reflectance("bluebook")
    message = str(info.value)
    assert "'bluebook'" in message and "NaN" in message and "\n" not in message
    assert not os.listdir(tmp_path / "cache" / "builtin")  # nothing cached from it


def test_a_folder_named_like_a_builtin_set_is_never_silently_replaced_by_it(
    tmp_path, monkeypatch, capsys
):
    """``rgl`` in a folder holding ``rgl/``: refused, naming both and how to say each (``./rgl``,
    ``builtin:rgl``), by the library and by the tools; a manifold recorded on the set still opens
    its set there (what it recorded is no user's name)."""
    from mitsuba_manifold.apps.cli import fit_manifold
    from mitsuba_manifold.manifold.model import Manifold

    work = tmp_path / "work"
    (work / "rgl").mkdir(parents=True)
    merl.write_binary(work / "rgl" / "mine.binary", np.full((3, 8, 8, 16), 0.01))
    monkeypatch.chdir(work)
    for spec in ("rgl", "rgl@8x8x16"):
        with pytest.raises(InputError) as info:
            Database(spec)
        message = str(info.value)
        assert "ambiguous" in message and str(work / "rgl") in message, message
        assert "./rgl" in message and "builtin:rgl" in message and "\n" not in message
    assert Database("./rgl").names == ["mine"]
    assert Database(str(work / "rgl")).names == ["mine"]
    assert len(Database("builtin:rgl@8x8x16").names) == 51
    assert Database("builtin:rgl@8x8x16").folder == "rgl@8x8x16"  # recorded as the set's name
    with pytest.raises(InputError, match="no built-in set 'merl2'"):
        Database("builtin:merl2")
    (work / "nielsen@8x8x16").mkdir()  # named like a set at a resolution: ambiguous too
    with pytest.raises(InputError, match="ambiguous") as info:
        Database("nielsen@8x8x16")
    assert "./nielsen@8x8x16" in str(info.value) and "builtin:nielsen@8x8x16" in str(info.value)
    with pytest.raises(FormatError, match="holds no tables"):
        Database("./nielsen@8x8x16")
    os.rmdir(work / "nielsen@8x8x16")
    with pytest.raises(InputError, match="ambiguous"):
        write_database(tmp_path / "out", ["rgl", "nielsen"])
    with pytest.raises(SystemExit):
        fit_manifold.main(["rgl@8x8x16", "--out", str(tmp_path / "m.npz")])
    err = capsys.readouterr().err
    assert "ambiguous" in err and "builtin:rgl" in err and not (tmp_path / "m.npz").exists()
    from mitsuba_manifold.apps.cli import make_database

    (work / "sgd").mkdir()  # the noisy copies of the SGD set are made from the set only
    with pytest.raises(SystemExit):
        make_database.main(["--out", str(tmp_path / "noisy"), "--from", "sgd", "--noise", "0.1"])
    assert "ambiguous" in capsys.readouterr().err and not (tmp_path / "noisy").exists()

    monkeypatch.chdir(tmp_path)
    m = Manifold.fit(
        "nielsen@8x8x16", q=2, stress=0.0, method="hooke-jeeves", preset="paper"
    )  # recorded "nielsen@8x8x16"
    m.save(tmp_path / "n.npz")
    (work / "nielsen").mkdir()
    monkeypatch.chdir(work)
    m = Manifold.load(tmp_path / "n.npz")
    assert m.database == "nielsen@8x8x16"
    assert m.tables().shape[0] == 8 and m.open_database().names == m.names
    assert m.combine(np.full(8, 1 / 8), prune=0.0)[0].shape == (3, 8, 8, 16)


def test_a_cache_variable_naming_a_file_says_which_variable(tmp_path, monkeypatch):
    blocker = tmp_path / "afile"
    blocker.write_text("not a folder")
    monkeypatch.setenv("MITSUBA_MANIFOLD_CACHE", str(blocker))
    with pytest.raises(OSError) as info:
        Database("nielsen@8x8x16").reflectance("bluebook")
    assert "$MITSUBA_MANIFOLD_CACHE" in str(info.value) and str(blocker) in str(info.value)


#: A ``sources.json`` as every release so far wrote it (format version 1), byte for byte.
SOURCES_V1 = """{
 "format": "mitsuba-manifold-sources",
 "version": 1,
 "from": [
  "nielsen"
 ],
 "dims": [
  8,
  8,
  16
 ]
}
"""


def test_a_source_list_written_before_opens_the_same_and_writes_back_byte_for_byte(tmp_path):
    from mitsuba_manifold.data.database import SOURCES_NAME, SourceList, open_spec

    folder = tmp_path / "db"
    folder.mkdir()
    (folder / SOURCES_NAME).write_text(SOURCES_V1)
    record = SourceList.read(str(folder / SOURCES_NAME))
    assert (record.version, record.sets, record.dims) == (1, ("nielsen",), (8, 8, 16))
    spec = open_spec(str(folder))
    assert spec.dims == (8, 8, 16) and spec.key == str(folder)  # the list's resolution is natural
    assert [s.name for s in spec.sources] == [s.name for s in sources.builtin("nielsen")]
    record.write(str(tmp_path / "again.json"))
    assert (tmp_path / "again.json").read_text() == SOURCES_V1
    unversioned = json.loads(SOURCES_V1)
    del unversioned["version"]  # no release wrote one without it; it reads as version 1
    (folder / SOURCES_NAME).write_text(json.dumps(unversioned))
    assert SourceList.read(str(folder / SOURCES_NAME)) == record


@pytest.mark.parametrize(
    "change, words",
    [
        ({"format": "other"}, "its format field must be 'mitsuba-manifold-sources'"),
        (
            {"version": 2},
            "its version field is 2, newer than this package reads (1 to 1); update mitsuba-manifold to read it, or remake it",
        ),
        ({"from": ["tables"]}, "its from field at 0 names the source 'tables', neither a built-in"),
        ({"from": "merl"}, "its from field must be a list of built-in set names"),
        ({"dims": [8, "8", 16]}, "its dims field at 1 must be the tables' resolution"),
        ({"dims": [8, 8, 0]}, "its dims field at 2 must be the tables' resolution"),
    ],
)
def test_a_bad_source_list_is_one_error_naming_the_file_and_the_field(tmp_path, change, words):
    from mitsuba_manifold.data.database import open_spec

    folder = tmp_path / "db"
    folder.mkdir()
    (folder / "sources.json").write_text(json.dumps(dict(json.loads(SOURCES_V1), **change)))
    with pytest.raises(FormatError) as e:
        open_spec(str(folder))
    message = str(e.value)
    assert message.startswith(str(folder / "sources.json")) and words in message, message
    assert "\n" not in message
    assert message.endswith(" remake it with tools/make_database.py")
