"""bench.py refuses bad files and values in one line naming the option, before any database is
made and before anything is written (a benchmark, or the database of MERL resolution that it
makes first, runs for minutes)."""

import os

import pytest
from guarantees_helpers import assert_one_error, run_tool, snapshot

from mitsuba_manifold.errors import InputError

#: Material names of the fake databases (more than the 10 folds of the space benchmark).
NAMES = [f"m{i:02d}" for i in range(12)]


@pytest.fixture
def work(tmp_path, monkeypatch):
    """``tmp_path`` as the working folder (where the default database ``out/database`` would go),
    with a text file posing as a manifold and a database folder of ``.binary`` names; making
    the built-in database is recorded (and makes the folder, as the real one would)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "junk.npz").write_text("not a manifold\n")
    db = tmp_path / "db"
    db.mkdir()
    for n in NAMES:
        (db / f"{n}.binary").write_bytes(b"\0" * 16)
    made = []

    def make_database(folder, *args, **kwargs):
        made.append(folder)
        os.makedirs(folder, exist_ok=True)

    from mitsuba_manifold.data import database

    monkeypatch.setattr(database, "make_database", make_database)
    return {"root": tmp_path, "db": str(db), "made": made, "before": snapshot(tmp_path)}


def _refused(work, *args):
    """Run bench.py ``args``: exit 2, one error line (returned), no database made, nothing written."""
    rc, _, err = run_tool("bench", *args, "--json", "b.json")
    line = assert_one_error(rc, err)
    assert not work["made"], line
    assert snapshot(work["root"]) == work["before"], line
    assert sorted(os.listdir(work["root"])) == ["db", "junk.npz"], line
    return line


@pytest.mark.parametrize("which", ["interp", "stability", "prune", "match", "gi", "bsdf"])
def test_a_file_that_is_no_manifold_is_refused_before_the_database_is_made(work, which):
    line = _refused(work, which, "--manifold", "junk.npz")
    assert "--manifold" in line and "junk.npz" in line and "not a manifold" in line


def test_a_missing_manifold_basis_or_database_is_refused_naming_its_option(work):
    assert "--manifold" in _refused(work, "interp", "--manifold", "none.npz")
    line = _refused(work, "match", "--basis", "nobasis")
    assert "--basis" in line and "nobasis" in line
    line = _refused(work, "interp", "--database", "nodb")
    assert "--database" in line and "nodb" in line and "does not exist" in line
    assert "--database" in _refused(work, "fit", "--database", "junk.npz")


@pytest.mark.parametrize("folds", ["11", "10", "0,12"])
def test_space_refuses_folds_beyond_the_ten(work, folds):
    line = _refused(work, "space", "--database", work["db"], "--folds", folds)
    assert "--folds" in line and "0 to 9" in line


def test_space_refuses_a_fold_that_holds_none_of_few_materials(work):
    line = _refused(
        work, "space", "--database", work["db"], "--materials", "m00,m01,m02", "--folds", "5"
    )
    assert "--folds" in line and "3 materials" in line


def test_space_library_refuses_folds_and_configs_before_reading_the_database(work):
    from benchmarks import space

    with pytest.raises(InputError, match="`folds`.*0 to 9"):
        space.run(work["db"], folds=[11], progress=False)
    with pytest.raises(InputError, match="`configs`.*did you mean 'default'"):
        space.run(work["db"], configs=["defualt"], progress=False)
    assert snapshot(work["root"]) == work["before"]


@pytest.mark.parametrize("res", ["-3", "0"])
def test_match_refuses_a_resolution_below_one_before_making_its_folder(work, res):
    line = _refused(work, "match", "--database", work["db"], "--res", res)
    assert "--res" in line and "at least 1" in line
    from benchmarks import match

    with pytest.raises(InputError, match="`res`"):
        match.run(work["db"], res=int(res), progress=False)
    assert snapshot(work["root"]) == work["before"]


@pytest.mark.parametrize(
    "which, name, hint", [("space", "defualt", "default"), ("fig9", "papr", "paper")]
)
def test_unknown_configs_are_refused_with_a_did_you_mean(work, which, name, hint):
    line = _refused(work, which, "--database", work["db"], "--configs", name)
    assert "--configs" in line and f"did you mean '{hint}'" in line


def test_unknown_materials_are_refused_with_a_did_you_mean(work):
    line = _refused(work, "fit", "--database", work["db"], "--materials", "m01,m1O")
    assert "--materials" in line and "did you mean" in line and "m1O" in line
    line = _refused(work, "pca", "--materials", "chrom")  # the built-in database, made later
    assert "--materials" in line and "did you mean 'chrome'" in line


@pytest.mark.parametrize(
    "args, option",
    [
        (["interp", "--res", "64"], "--res"),
        (["fit", "--folds", "1"], "--folds"),
        (["interp", "--basis", "b"], "--basis"),
        (["stability", "--configs", "paper"], "--configs"),
        (["interp", "--materials", "m00"], "--materials"),
    ],
)
def test_options_of_other_benchmarks_are_refused_not_ignored(work, args, option):
    line = _refused(work, *args)
    assert f"takes no {option}" in line


def test_bench_inputs_take_builtin_database_names(tmp_path):
    from benchmarks.inputs import database_names
    from mitsuba_manifold.errors import InputError

    assert len(database_names("rgl")) == 51
    with pytest.raises(InputError, match="does not exist.*built-in databases: merl"):
        database_names(str(tmp_path / "merl_folder"))
