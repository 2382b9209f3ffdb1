"""What a scene's integrator renders, as the basis and the references reproduce it
(:class:`SceneIntegrator`, read from a loaded scene by :func:`scene_integrator`, stored in a basis's
manifest by :meth:`SceneIntegrator.to_manifest` and read back by :meth:`SceneIntegrator.from_manifest`).
"""

import re
from dataclasses import asdict, dataclass, fields

from ...errors import FormatError, InputError

#: Mitsuba integrators whose image is that of ``path`` (unbiased path tracers, without media),
#: by class name: the basis reproduces them.
PATH_LIKE = {
    "PathIntegrator": "path",
    "PRBIntegrator": "prb",
    "BasicPRBIntegrator": "prb_basic",
    "VolumetricSimplePathIntegrator": "volpath",
    "VolumetricPathIntegrator": "volpath",
    "VolpathMisIntegratorImpl": "volpathmis",
    "PRBVolpathIntegrator": "prbvolpath",
}

#: ... and those whose image is that of ``path`` with ``max_depth`` 2 (direct light, emitters seen).
DIRECT_LIKE = {"DirectIntegrator": "direct"}

#: Mitsuba's default Russian-roulette depth.
RR_DEPTH = 5
#: Where a :class:`SceneIntegrator`'s settings come from.
SOURCES = ("scene", "default", "option")


@dataclass(frozen=True)
class SceneIntegrator:
    """What a scene's integrator renders, as the basis and the references reproduce it.

    ``kind``: the integrator's plugin type (``path``, ``direct``, ...; ``path`` where the scene
    has none, as Mitsuba renders it); ``max_depth`` (-1: unbounded; ``direct`` is ``path`` with
    ``max_depth`` 2: the emitters seen and one scattering vertex lit by next-event estimation and
    MIS, the same image in expectation), ``rr_depth``, ``hide_emitters``; ``source``: ``"scene"``
    (the scene's own), ``"default"`` (the scene has none) or ``"option"`` (``max_depth`` set by
    the caller, overriding the scene's).
    """

    kind: str
    max_depth: int
    rr_depth: int
    hide_emitters: bool
    source: str

    def __post_init__(self) -> None:
        self.check()

    def check(self) -> None:
        """Raise an :class:`InputError` naming the field unless these are settings the basis
        renders: a path-like or direct ``kind``, ``max_depth`` >= -1, ``rr_depth`` >= 1, a
        boolean ``hide_emitters`` and a known ``source``.
        """
        kinds = sorted(set(PATH_LIKE.values()) | set(DIRECT_LIKE.values()))
        if self.kind not in kinds:
            raise InputError(f"integrator `kind` {self.kind!r} is not one of {', '.join(kinds)}")
        for name, low in (("max_depth", -1), ("rr_depth", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise InputError(f"integrator `{name}` must be an integer >= {low}, got {value!r}")
        if not isinstance(self.hide_emitters, bool):
            raise InputError(
                f"integrator `hide_emitters` must be true or false, got {self.hide_emitters!r}"
            )
        if self.source not in SOURCES:
            raise InputError(
                f"integrator `source` {self.source!r} is not one of {', '.join(SOURCES)}"
            )

    @classmethod
    def from_manifest(cls, entry, where="the manifest") -> "SceneIntegrator | None":
        """The settings a basis manifest's ``integrator`` entry records (:meth:`to_manifest`), or
        None where it records none; a :class:`FormatError` naming ``where`` and the field when
        the entry is not such settings. Keys this version does not know are ignored.
        """
        if entry is None:
            return None
        if not isinstance(entry, dict):
            raise FormatError(
                f"{where}: `integrator` must be an object, got {type(entry).__name__}"
            )
        names = [f.name for f in fields(cls)]
        missing = [n for n in names if n not in entry]
        if missing:
            raise FormatError(f"{where}: `integrator` lacks {', '.join(missing)}")
        try:
            return cls(**{n: entry[n] for n in names})
        except InputError as e:
            raise FormatError(f"{where}: {e}") from None

    def path_properties(self):
        """Properties of a ``manifold_path`` (or ``path``) integrator that renders these paths."""
        return {
            "max_depth": int(self.max_depth),
            "rr_depth": int(self.rr_depth),
            "hide_emitters": bool(self.hide_emitters),
        }

    def reference(self, scene):
        """The integrator Mitsuba renders the scene's reference with: the scene's own, or a
        ``path`` of these settings where the depth was overridden or the scene has none.
        """
        import mitsuba as mi

        own = scene.integrator()
        if self.source == "scene" and own is not None:
            return own
        return mi.load_dict({"type": "path", **self.path_properties()})

    def describe(self):
        """One phrase: ``path (max_depth 3, hide_emitters)``, with where it comes from."""
        depth = "unbounded" if self.max_depth < 0 else str(self.max_depth)
        extra = ", hide_emitters" if self.hide_emitters else ""
        where = {
            "scene": "the scene's integrator",
            "default": "no integrator in the scene: Mitsuba's default",
            "option": "max_depth set by the caller",
        }[self.source]
        return f"{self.kind} (max_depth {depth}, rr_depth {self.rr_depth}{extra}; {where})"

    def to_manifest(self) -> dict:
        """The manifest's ``integrator`` entry (read back by :meth:`from_manifest`)."""
        return asdict(self)


def _depth_of(integrator, name, text):
    """An integer property of a Mitsuba integrator: its attribute, else its ``to_string``."""
    value = getattr(integrator, name, None)
    if value is None:
        m = re.search(rf"{name}\s*=\s*(-?\d+)", text)
        value = int(m.group(1)) if m else None
    if value is None:
        return None
    value = int(value)
    return -1 if value >= 0xFFFFFFFF or value < 0 else value


def scene_integrator(scene, scene_path, max_depth=None):
    """The :class:`SceneIntegrator` of a loaded scene, or an :class:`InputError` naming the
    setting the basis cannot reproduce (raised before anything is rendered).

    ``max_depth`` (given by the caller): overrides the scene's depth where it differs (a
    ``direct`` integrator becomes ``path`` of that depth); the scene's ``rr_depth`` and
    ``hide_emitters`` are kept.
    """
    own = scene.integrator()
    if own is None:
        found = SceneIntegrator("path", -1, RR_DEPTH, False, "default")
    else:
        cls = own.class_name() if hasattr(own, "class_name") else type(own).__name__
        cls = (
            type(own).__name__
            if cls
            in (
                "SamplingIntegrator",
                "MonteCarloIntegrator",
                "ADIntegrator",
                "RBIntegrator",
                "PSIntegrator",
            )
            else cls
        )
        text = str(own)
        hide = bool(getattr(own, "hide_emitters", False))
        if cls in DIRECT_LIKE:
            found = SceneIntegrator(DIRECT_LIKE[cls], 2, RR_DEPTH, hide, "scene")
        elif cls in PATH_LIKE:
            if PATH_LIKE[cls].startswith(("volpath", "prbvolpath")) and _has_media(scene):
                raise InputError(
                    f"scene {scene_path}: integrator {PATH_LIKE[cls]!r} with participating media: "
                    "the basis renders surfaces only; remove the media (or render the scene without "
                    "the manifold basis)"
                )
            depth = _depth_of(own, "max_depth", text)
            rr = _depth_of(own, "rr_depth", text)
            found = SceneIntegrator(
                PATH_LIKE[cls],
                -1 if depth is None else depth,
                RR_DEPTH if rr is None or rr < 1 else rr,
                hide,
                "scene",
            )
        else:
            raise InputError(
                f"scene {scene_path}: its integrator ({cls}) renders something the basis cannot "
                "reproduce (the basis renders what `path` and `direct` do): give the scene "
                '<integrator type="path"> (with its max_depth) or type="direct"'
            )
    if max_depth is not None and int(max_depth) != found.max_depth:
        found = SceneIntegrator(
            "path", int(max_depth), found.rr_depth, found.hide_emitters, "option"
        )
    return found


def _has_media(scene):
    """Whether any shape or sensor of ``scene`` bounds or holds a participating medium."""
    for shape in scene.shapes():
        for name in ("interior_medium", "exterior_medium"):
            get = getattr(shape, name, None)
            if get is not None and get() is not None:
                return True
    return any(getattr(s, "medium", lambda: None)() is not None for s in scene.sensors())
