"""Plans passed between modules are dataclasses checked when made: what a scene's integrator
renders (as a basis manifest records it), and what the package's path tracer traces."""

import json

import pytest

from mitsuba_manifold.errors import FormatError, InputError

pytestmark = [pytest.mark.render, pytest.mark.usefixtures("variant")]


def _integrator(**change):
    from mitsuba_manifold.render.scene.integrator import SceneIntegrator

    fields = dict(kind="path", max_depth=3, rr_depth=5, hide_emitters=True, source="scene")
    return SceneIntegrator(**{**fields, **change})


def test_the_scene_integrator_reads_back_what_a_manifest_records():
    from mitsuba_manifold.render.scene.integrator import SceneIntegrator

    plan = _integrator()
    entry = json.loads(json.dumps(plan.to_manifest()))  # as a manifest.json holds it
    assert SceneIntegrator.from_manifest(entry) == plan
    assert SceneIntegrator.from_manifest({**entry, "later": 1}) == plan  # unknown keys ignored
    assert SceneIntegrator.from_manifest(None) is None  # a basis that recorded none


@pytest.mark.parametrize(
    "change, field",
    [
        (dict(kind="bdpt"), "kind"),
        (dict(max_depth=-2), "max_depth"),
        (dict(rr_depth=0), "rr_depth"),
        (dict(max_depth=2.5), "max_depth"),
        (dict(hide_emitters="yes"), "hide_emitters"),
        (dict(source="guess"), "source"),
    ],
)
def test_a_scene_integrator_that_cannot_be_rendered_is_refused_naming_the_field(change, field):
    from mitsuba_manifold.render.scene.integrator import SceneIntegrator

    with pytest.raises(InputError, match=f"`{field}`"):
        _integrator(**change)
    entry = {**_integrator().to_manifest(), **change}
    with pytest.raises(FormatError, match=rf"b/manifest\.json: .*`{field}`"):
        SceneIntegrator.from_manifest(entry, "b/manifest.json")


def test_a_manifest_entry_lacking_settings_is_refused():
    from mitsuba_manifold.render.scene.integrator import SceneIntegrator

    with pytest.raises(FormatError, match="lacks rr_depth"):
        SceneIntegrator.from_manifest(
            {"kind": "path", "max_depth": 3, "hide_emitters": False, "source": "scene"}
        )
    with pytest.raises(FormatError, match="must be an object"):
        SceneIntegrator.from_manifest(["path", 3])


def test_the_trace_plan_of_the_path_tracer_is_checked(small_manifold):
    import mitsuba as mi

    from mitsuba_manifold.render.integrators import TracePlan
    from mitsuba_manifold.render.scene.files import scene_path
    from mitsuba_manifold.render.scene.loading import load_scene

    # one manifold material: one group, 3 classes (base, touch, rest)
    scene = load_scene(scene_path("sphere"), small_manifold, spp=1, resolution=8).scene
    plan = mi.load_dict({"type": "manifold_path", "component": "touch", "split": True}).plan(scene)
    assert isinstance(plan, TracePlan) and plan.classes == 3
    assert plan.names == ["base", "touch", "rest"] and plan.select == 0b010
    groups, hits = plan.groups, plan.hits
    with pytest.raises(InputError, match="`select`"):
        TracePlan(groups, 1 << 3, 7, [], hits, [])
    with pytest.raises(InputError, match="AOV classes"):
        TracePlan(groups, 1, 7, [3], hits, [])
    with pytest.raises(InputError, match="lists of hits"):
        TracePlan(groups, 1, 7, [], [], [])
    with pytest.raises(InputError, match="class names"):
        TracePlan(groups, 1, 7, [], hits, [], names=["base"])
