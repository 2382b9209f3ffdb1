"""Scene files: the scenes shipped with the package, and what a scene XML says before it is loaded.

The package ships its test and demo scenes (``scenes/`` in a checkout, ``mitsuba_manifold/scenes``
once installed): :func:`scene_path` accepts one of their names (``"table"``) or a path to any
scene XML. A scene XML takes ``$parameters`` (:func:`scene_parameters`); its ``manifold_brdf``
materials name their manifold files (:func:`scene_manifolds`), which must be the manifold a
basis or a reference renders with (:func:`check_scene_manifolds`), and must not sit inside a BSDF
that hides them (:func:`check_wrappers`).
"""

import os
import re

from ..._util.checks import scene_xml
from ...data.sources import BUILTIN_PREFIX
from ...errors import InputError, MismatchError, MitsubaManifoldError, did_you_mean
from ...manifold.file.identity import manifold_identity
from ...manifold.file.shipped import SHIPPED, ambiguity, resolve_manifold


def _scenes_dir():
    """The shipped scenes: ``scenes/`` at the top of a checkout, installed as the package data
    ``mitsuba_manifold/scenes`` (``pyproject.toml`` maps one to the other).
    """
    package = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    for folder in (
        os.path.join(package, "scenes"),
        os.path.join(os.path.dirname(package), "scenes"),
    ):
        if os.path.isfile(os.path.join(folder, "table.xml")):
            return folder
    return os.path.join(package, "scenes")


#: Folder of the scenes shipped with the package.
SCENES_DIR = _scenes_dir()

_PARAM = re.compile(r"\$([A-Za-z_][A-Za-z0-9_]*)")


def shipped_scenes():
    """Names of the scenes shipped with the package (``table``, ``sphere``, ...)."""
    return sorted(f[:-4] for f in os.listdir(SCENES_DIR) if f.endswith(".xml"))


def scene_path(scene):
    """Path of a scene given as a shipped scene's name (``"table"``) or as a path to an XML file."""
    scene = os.fspath(scene)
    if os.path.isfile(scene):
        scene_xml(scene)  # a scene XML, or an error naming the file
        return os.path.abspath(scene)
    shipped = os.path.join(SCENES_DIR, scene + ".xml")
    if os.sep not in scene and not scene.endswith(".xml") and os.path.isfile(shipped):
        return shipped
    raise MismatchError(
        f"scene {scene} does not exist (nor is it the name of a shipped scene: "
        f"{', '.join(shipped_scenes())})"
    )


def scene_parameters(scene):
    """Names of the ``$parameters`` a scene XML uses, and its ``<default>`` values."""
    root = scene_xml(scene)  # exists, and is a scene XML (not a table or an image)
    defaults = {el.get("name"): el.get("value") for el in root.iter("default")}
    used = {
        name for el in root.iter() for value in el.attrib.values() for name in _PARAM.findall(value)
    }
    return used, defaults


def scene_sample_count(scene, sensor=0):
    """Samples per pixel the sampler of sensor ``sensor`` of a scene XML declares: its
    ``sample_count``, or the ``<default>`` of the ``$parameter`` it takes; None where it
    declares none (or gives no integer).
    """
    root = scene_xml(scene)
    defaults = {el.get("name"): el.get("value") for el in root.iter("default")}
    sensors = root.findall("sensor")
    if not 0 <= int(sensor) < len(sensors):
        return None
    for el in sensors[int(sensor)].iter("integer"):
        if el.get("name") == "sample_count":
            value = _PARAM.sub(lambda m: str(defaults.get(m.group(1), "")), el.get("value") or "")
            try:
                return int(value)
            except ValueError:
                return None
    return None


def scene_manifolds(scene, params=None):
    """``(bsdf id, manifold file)`` of each ``manifold_brdf`` of a scene XML: its ``manifold``
    value with ``$parameters`` taken from ``params``, else the scene's ``<default>``s, and a
    relative path resolved against the scene's folder (as Mitsuba's file resolver does), or
    a shipped manifold's name where no file of that name exists there.
    """
    root = scene_xml(scene)
    values = {**{el.get("name"): el.get("value") for el in root.iter("default")}, **(params or {})}
    folder = os.path.dirname(os.path.abspath(scene))
    found = []
    for bsdf in root.iter("bsdf"):
        named = [el.get("value") for el in bsdf if el.get("name") == "manifold"]
        if bsdf.get("type") != "manifold_brdf" or not named or named[0] is None:
            continue
        value = _PARAM.sub(lambda m: str(values.get(m.group(1), m.group(0))), named[0])
        path = os.path.join(folder, value)
        if value in SHIPPED or value.startswith(BUILTIN_PREFIX):
            if value in SHIPPED and os.path.lexists(path):
                raise ambiguity(value, path)
            path = resolve_manifold(value)
        elif not os.path.exists(path) and os.path.exists(value):
            path = value
        found.append((bsdf.get("id"), os.path.abspath(path)))
    return found


def check_scene_manifolds(scene, manifold_path, params):
    """Raise unless every ``manifold_brdf`` of the scene uses ``manifold_path`` (the file, or
    one of the same content): a scene naming its own manifold is not rendered with another's
    latent points.
    """
    want, identity = os.path.realpath(manifold_path), None
    for bsdf_id, path in scene_manifolds(scene, params):
        if os.path.realpath(path) == want:
            continue
        from ...manifold.model import Manifold

        try:
            identity = identity or manifold_identity(Manifold.load(manifold_path))
            if manifold_identity(Manifold.load(path)) == identity:
                continue
        except (MitsubaManifoldError, OSError):
            pass
        raise MismatchError(other_manifold(scene, bsdf_id, path, manifold_path))


#: BSDFs that hide the BSDF they hold from Mitsuba's scene traversal (the basis cannot find a
#: ``manifold_brdf`` inside them, nor record its vertices in their perturbed frames).
HIDING_WRAPPERS = ("normalmap", "bumpmap")


def check_wrappers(scene):
    """Raise (before loading) if a ``manifold_brdf`` of the scene XML sits inside a
    :data:`HIDING_WRAPPERS` BSDF, naming it and what works instead.
    """
    root = scene_xml(scene)
    ids = {
        b.get("id") for b in root.iter("bsdf") if b.get("type") == "manifold_brdf" and b.get("id")
    }
    for wrapper in root.iter("bsdf"):
        if wrapper.get("type") not in HIDING_WRAPPERS:
            continue
        inner = [
            el
            for el in wrapper.iter()
            if el is not wrapper
            and (
                (el.tag == "bsdf" and el.get("type") == "manifold_brdf")
                or (el.tag == "ref" and el.get("id") in ids)
            )
        ]
        if inner:
            name = wrapper.get("id") or wrapper.get("type")
            raise InputError(
                f"scene {scene}: the manifold_brdf is inside the {wrapper.get('type')} BSDF {name!r}, "
                "which the basis cannot render (it perturbs the shading frame the measured tables are "
                "looked up in, and hides the material from the scene's traversal): give the shape the "
                "manifold_brdf itself (or inside twosided), without the "
                f"{wrapper.get('type')}"
            )


def other_manifold(scene, bsdf_id, path, manifold_path):
    if not os.path.isfile(path):
        return (
            f"scene {scene}: material {bsdf_id!r} names the manifold {path} (which does not exist), not "
            f'{manifold_path}: use value="$manifold" in the scene'
        )
    return (
        f"scene {scene}: material {bsdf_id!r} names the manifold {path}, not {manifold_path}: use "
        f'value="$manifold" in the scene, or pass `manifold_path`={path}'
    )


def check_scene(name, value):
    """A shipped scene's name or a readable scene XML; returns its path. The error names the
    option and the value, and suggests the closest shipped scene names.
    """
    try:
        path = scene_path(value)
        scene_parameters(path)
    except MitsubaManifoldError as e:
        shipped = shipped_scenes()
        hint = did_you_mean(value, shipped) if os.sep not in str(value) else ""
        if os.path.isfile(value):
            raise InputError(f"{name}: {e}") from None
        raise InputError(
            f"{name} {value!r}: no such file nor shipped scene{hint}; shipped scenes: "
            f"{', '.join(shipped)}"
        ) from None
    return path


def count_sensors(scene_path):
    """Sensors (views) declared at the top level of a scene XML."""
    return len(scene_xml(scene_path).findall("sensor"))  # or a MismatchError naming the file
