"""What ``add`` and ``save`` refuse so that a manifold file always reads back: tables that
reflect nothing or are not finite, names no tool could select, a manifold whose file would not
read. On a built-in set (the package's own networks), at a low resolution."""

import os

import numpy as np
import pytest

from mitsuba_manifold.errors import InputError
from mitsuba_manifold.manifold.model import Manifold

DB = "nielsen@8x8x16"


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("MITSUBA_MANIFOLD_CACHE", str(tmp_path / "cache"))


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    cache = tmp_path_factory.mktemp("cache")
    old = os.environ.get("MITSUBA_MANIFOLD_CACHE")
    os.environ["MITSUBA_MANIFOLD_CACHE"] = str(cache)
    try:
        return Manifold.fit(DB, q=2, stress=0.0, method="hooke-jeeves", preset="paper")
    finally:
        if old is None:
            os.environ.pop("MITSUBA_MANIFOLD_CACHE")
        else:
            os.environ["MITSUBA_MANIFOLD_CACHE"] = old


def _saved(m, tmp_path):
    path = tmp_path / "base.npz"
    m.save(path)
    return path


def _white(tmp_path, dims):
    from mitsuba_manifold.data import merl

    path = tmp_path / "white.binary"
    merl.write_binary(path, merl.to_stored(np.full((3,) + tuple(dims), 0.2)))
    return str(path)


def test_a_material_that_reflects_nothing_is_refused_and_the_manifold_file_kept(
    base, tmp_path, capsys
):
    """An all-zero table (a black ``.binary`` file, or an array) is refused by ``add`` and by
    ``fit_manifold.py M.npz --add black.binary --out M.npz``: M.npz keeps its bytes and reads."""
    from mitsuba_manifold.apps.cli import fit_manifold
    from mitsuba_manifold.data import merl

    saved = _saved(base, tmp_path)
    before = saved.read_bytes()
    black = tmp_path / "black.binary"
    merl.write_binary(black, np.zeros((3,) + tuple(base.dims)))
    with pytest.raises(SystemExit) as exit_:
        fit_manifold.main([str(saved), "--add", str(black), "--out", str(saved), "--force"])
    err = capsys.readouterr().err
    assert exit_.value.code != 0 and "reflects nothing" in err and str(black) in err
    assert saved.read_bytes() == before and Manifold.load(saved).n == base.n
    m = Manifold.load(saved)
    with pytest.raises(InputError, match="reflects nothing"):
        m.add(np.zeros(3 * int(np.prod(base.dims)), np.float32), name="zeros")
    with pytest.raises(InputError, match="NaN, Inf"):
        m.add(np.full(3 * int(np.prod(base.dims)), np.inf, np.float32), name="inf")
    assert m.n == base.n


def test_save_never_replaces_a_readable_manifold_with_an_unreadable_one(base, tmp_path):
    from mitsuba_manifold.errors import FormatError

    saved = _saved(base, tmp_path)
    before = saved.read_bytes()
    m = Manifold.load(saved)
    broken = np.array(m.table_gram)
    broken[1, 1] = 0.0  # what a table that reflects nothing gives
    m.table_gram = broken
    with pytest.raises(FormatError) as info:
        m.save(saved)
    message = str(info.value)
    assert f"manifold not saved to {saved}" in message and "table_gram" in message
    assert "unchanged" in message and ".tmp" not in message
    assert saved.read_bytes() == before and sorted(
        f for f in os.listdir(tmp_path) if f.endswith(".npz")
    ) == ["base.npz"]
    with pytest.raises(FormatError, match="nothing written"):
        m.save(tmp_path / "new.npz")
    assert not (tmp_path / "new.npz").exists()


@pytest.mark.parametrize("name", [".hidden", " padded", "tab\tname"])
def test_add_refuses_a_name_the_tools_could_never_select(base, tmp_path, name):
    m = Manifold.load(_saved(base, tmp_path))
    with pytest.raises(InputError, match="cannot be selected"):
        m.add(_white(tmp_path, base.dims), name=name)
    assert m.n == base.n
    m.add(_white(tmp_path, base.dims), name="white")  # the same table under a plain name
    assert m.names[-1] == "white"
