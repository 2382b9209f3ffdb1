"""The match-render benchmark's database: the measured set it is asked for, not the surrogate."""

from benchmarks import match_render
from mitsuba_manifold.data.database import Database


def test_builtin_set_is_used_at_the_small_resolution(tmp_path):
    db = match_render._database("merl", str(tmp_path), 100)
    assert db == "merl@32x32x64"
    assert not any(tmp_path.iterdir())  # no surrogate tables written
    assert Database(db).dims == match_render.SMALL_DIMS
    assert match_render._database("rgl@16x16x32", str(tmp_path), 100) == "rgl@16x16x32"


def test_builtin_subset_of_materials(tmp_path):
    db = match_render._database("merl", str(tmp_path), 3)
    assert match_render._subset(db, 3) == list(match_render.SMALL_MATERIALS[:3])
    names = match_render._subset(db, 12)
    assert len(names) == 12 and set(names) <= set(Database(db).names)
    assert match_render._subset(db, 100) is None
