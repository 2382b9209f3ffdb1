"""The match-render benchmark's database: the measured set it is asked for, not the surrogate."""

import numpy as np
import pytest

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


@pytest.mark.render
def test_views_are_sensors_of_the_scene(tmp_path, small_manifold):
    """Each view is a sensor index of one scene, looking from its place in ``VIEWS``."""
    from mitsuba_manifold.render.inverse import match_render as mr
    from mitsuba_manifold.render.scene.scenes import load_scene, use_variant

    mi = use_variant()

    scene_xml = match_render._views_scene(str(tmp_path))
    sensors = match_render._sensors(8)
    targets = [np.zeros((8, 8, 3), np.float32)] * 3
    masks = [np.ones((8, 8))] * 3
    views = mr.check_views(match_render._views(scene_xml, targets, sensors, masks))
    assert [v.sensor for v in views] == [0, 1, 2]
    scene, _, _ = load_scene(scene_xml, small_manifold, 1, (8, 8))
    for k, (origin, sensor) in enumerate(zip(match_render.VIEWS, scene.sensors())):
        seen = sensor.world_transform() @ mi.ScalarPoint3f(0, 0, 0)
        assert np.allclose(np.array(seen).ravel(), origin, atol=1e-5), k
