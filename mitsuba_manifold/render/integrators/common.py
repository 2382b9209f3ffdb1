"""Shared machinery of the package's integrators (as Mitsuba's ``ad/integrators/common.py``).

The paper's Sec. 5.2 splits the light reaching the camera by how many times it
scattered off the material being edited (the *target*, a ``manifold_brdf``):
``L = L1- + L2+``, where ``L1-`` (paths scattering off the target at most once) is
affine in the target's BRDF. This module resolves targets and path classes in a scene
and checks variants; integrators that trace whole wavefronts themselves seed samplers and
make primary rays with Mitsuba's own ``ADIntegrator.prepare`` and ``sample_rays``.
"""

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from ...errors import InputError, VariantError

#: Values of the ``component`` parameter besides ``touch:<id>+<id>...``: the components of the
#: image (the glossary's one vocabulary).
COMPONENTS = ("full", "l1", "base", "touch", "l2+")
#: Former spellings of ``component`` values, still read with a ``DeprecationWarning``.
DEPRECATED_COMPONENTS = {"rest": "l2+"}
#: Most target groups (the number of path classes grows as 2 ** groups).
MAX_GROUPS = 4


def is_manifold_bsdf(bsdf):
    """True when ``bsdf`` is a manifold material: a ``manifold_brdf`` of the active variant
    (an instance of :class:`mitsuba_manifold.render.plugin.bsdf.ManifoldBRDF`).
    """
    from ..plugin import bsdf as manifold_brdf  # the module .plugins made for the active variant

    return isinstance(bsdf, manifold_brdf.ManifoldBRDF)


#: BSDFs that may hold a manifold material and keep its image affine in it, by class name: the
#: ``twosided`` wrapper (the material on both sides; the one-pass renderer mirrors the back side).
TWOSIDED = "TwoSidedBRDF"


def scene_shapes(scene):
    """Every shape of ``scene``: its own, and those inside shape groups (instanced), which
    ``scene.shapes()`` does not list.
    """
    shapes = list(scene.shapes())
    for _, _, node, _ in mi.traverse(scene).properties.values():
        if isinstance(node, mi.Shape) and not any(node is s for s in shapes):
            shapes.append(node)
    return shapes


def _inner(bsdf):
    """The manifold BSDFs a (wrapper) BSDF holds, found through its parameters."""
    found = []
    for _, _, node, _ in mi.traverse(bsdf).properties.values():
        if is_manifold_bsdf(node) and not any(node is b for b in found):
            found.append(node)
    return found


def carriers(scene):
    """``[(carrier, material)]``: every BSDF that a shape of ``scene`` holds (instanced ones too) and
    that is a manifold material or holds one (``twosided``, ...), with that manifold material, in
    the order of the shapes. A ray hitting ``carrier`` scatters off ``material``.
    """
    out = []
    for shape in scene_shapes(scene):
        bsdf = shape.bsdf()
        if bsdf is None or any(bsdf is c for c, _ in out):
            continue
        if is_manifold_bsdf(bsdf):
            out.append((bsdf, bsdf))
        else:
            out += [(bsdf, m) for m in _inner(bsdf)]
    for k, (c, m) in enumerate(out):  # a nested material without an id is named by its holder
        if not m.id():
            m.set_id(c.id() or f"manifold_brdf_{k}")
    return out


def is_plain_twosided(carrier):
    """Whether ``carrier`` is a ``twosided`` wrapper with the one manifold material on both sides."""
    name = carrier.class_name() if hasattr(carrier, "class_name") else type(carrier).__name__
    return (
        name == TWOSIDED
        and len(_inner(carrier)) == 1
        and "brdf_1" not in mi.traverse(carrier).keys()
    )


def manifold_bsdfs(scene):
    """The distinct manifold BSDF instances of ``scene`` (a shape's own BSDF, or held by one such as
    ``twosided``; instanced shapes included), in the order of the shapes.
    """
    found = []
    for _, bsdf in carriers(scene):
        if not any(bsdf is b for b in found):
            found.append(bsdf)
    return found


def nested_manifold_bsdfs(scene):
    """Manifold BSDFs of ``scene`` that no shape's BSDF holds in a way the split can see."""
    own = manifold_bsdfs(scene)
    nested = []
    for _, _, node, _ in mi.traverse(scene).properties.values():
        if is_manifold_bsdf(node) and not any(node is b for b in own + nested):
            nested.append(node)
    return nested


def group_carriers(scene, groups):
    """Per target group (:func:`target_groups`), the BSDFs whose hit is a vertex on it."""
    pairs = carriers(scene)
    return [[c for c, m in pairs if any(m is b for b in bsdfs)] for _, bsdfs in groups]


def target_groups(scene, target="all"):
    """Resolve the ``target`` parameter against ``scene``.

    Parameters
    ----------
    scene : mi.Scene
    target : str
        ``"all"``: every manifold BSDF of the scene counts as one material (one group);
        ``"each"``: one group per manifold BSDF; otherwise a comma-separated list of
        BSDF ids, one group per id.

    Returns
    -------
    list of (str, list of mi.BSDF)
        One ``(name, bsdfs)`` pair per group.

    Raises
    ------
    ValueError
        If the scene holds no manifold BSDF, an id is unknown or not a manifold
        BSDF, an id is repeated, or there are more than :data:`MAX_GROUPS` groups.
    """
    found = manifold_bsdfs(scene)
    if not found and nested_manifold_bsdfs(scene):
        raise InputError(
            "manifold_path: the scene's manifold_brdf is nested where no shape's BSDF holds it; the L1- split "
            'needs it as a shape\'s own BSDF or inside twosided: attach it so, or render with component="full".'
        )
    if not found:
        raise InputError(
            "manifold_path: the scene has no manifold material (no shape uses a "
            "'manifold_brdf' BSDF); the L1- split needs one. Give the material to edit "
            'type="manifold_brdf", or render with component="full".'
        )
    target = str(target).strip()
    if target == "all":
        groups = [("touch", found)]
    elif target == "each":
        groups = [(b.id(), [b]) for b in found]
    else:
        ids = [s.strip() for s in target.split(",") if s.strip()]
        if not ids:
            raise InputError("manifold_path: target is empty; use 'all', 'each' or BSDF ids")
        if len(set(ids)) != len(ids):
            raise InputError(f"manifold_path: target {target!r} names a BSDF twice")
        by_id = {b.id(): b for b in found}
        groups = []
        for i in ids:
            if i not in by_id:
                others = [s.bsdf().id() for s in scene_shapes(scene) if s.bsdf() is not None]
                kind = "is not a manifold_brdf" if i in others else "is not in the scene"
                raise InputError(
                    f"manifold_path: target BSDF {i!r} {kind}; manifold BSDFs of the "
                    f"scene: {sorted(by_id)}"
                )
            groups.append((i, [by_id[i]]))
    if len(groups) > MAX_GROUPS:
        raise InputError(
            f"manifold_path: {len(groups)} target groups, at most {MAX_GROUPS} are "
            "supported; use target='all' or name the BSDFs to edit"
        )
    return groups


def class_names(group_names):
    """Names of the path classes for the given group names.

    Class ``m`` (``0 <= m < 2 ** len(group_names)``) holds the paths that scattered off
    exactly the groups whose bits are set in ``m``, each once: ``"base"`` for ``m = 0``,
    ``"touch"`` for the single group when there is one, ``"touch:a+b"`` otherwise.
    The last class, ``"rest"``, holds the paths that scattered twice or more off a group
    (``L2+``).
    """
    p = len(group_names)
    names = []
    for m in range(1 << p):
        if m == 0:
            names.append("base")
        elif p == 1:
            names.append("touch")
        else:
            names.append("touch:" + "+".join(group_names[g] for g in range(p) if m >> g & 1))
    names.append("rest")
    return names


@dataclass(frozen=True)
class TracePlan:
    """What :meth:`~.path.ManifoldPathIntegrator.trace_paths` traces in one scene: the target
    groups and which path classes (:func:`class_names`: class ``m < 2 ** len(groups)`` the paths
    that scattered once off the groups of the bits of ``m``, class ``2 ** len(groups)`` the
    rest) it sums and records.

    Made by :meth:`~.path.ManifoldPathIntegrator.plan` for a ``component`` and ``target``, and by
    the one-pass renderer (:mod:`.onepass`) for its recorded vertices; checked when made.

    Attributes
    ----------
    groups : list of (str, list)
        The target groups: name and ``manifold_brdf`` instances (:func:`target_groups`).
    select : int
        Bit set over the classes summed into the image.
    keep : int
        Bit set over the classes a path may still be in while it is worth tracing.
    aovs : list of int
        Classes written as AOVs (``split``).
    hits : list of list
        Per group, the BSDFs whose hit is a vertex on it: its manifold materials and the
        ``twosided`` wrappers holding them (:func:`group_carriers`).
    mirror : list
        Those wrappers whose back side the one-pass records mirror.
    names : list of str
        The classes' names (:func:`class_names`; empty where not needed).
    """

    groups: list
    select: int
    keep: int
    aovs: list
    hits: list
    mirror: list
    names: list = ()

    def __post_init__(self) -> None:
        self.check()

    @property
    def classes(self) -> int:
        """Number of path classes: ``2 ** len(groups)`` single-scattering ones and the rest."""
        return (1 << len(self.groups)) + 1

    def check(self) -> None:
        """Raise an :class:`InputError` naming the field unless the plan is consistent: at most
        :data:`MAX_GROUPS` groups, class bit sets and AOV classes within the classes, one list
        of hits per group, and a name per class where names are given.
        """
        if len(self.groups) > MAX_GROUPS:
            raise InputError(f"trace plan: {len(self.groups)} target groups, at most {MAX_GROUPS}")
        every = (1 << self.classes) - 1
        for name in ("select", "keep"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= every:
                raise InputError(
                    f"trace plan: `{name}` must be a bit set over {self.classes} classes, got {value!r}"
                )
        bad = [c for c in self.aovs if not 0 <= int(c) < self.classes]
        if bad:
            raise InputError(f"trace plan: AOV classes {bad} are not among {self.classes} classes")
        if len(self.hits) != len(self.groups):
            raise InputError(
                f"trace plan: {len(self.hits)} lists of hits for {len(self.groups)} groups"
            )
        if self.names and len(self.names) != self.classes:
            raise InputError(
                f"trace plan: {len(self.names)} class names for {self.classes} classes"
            )


def power_heuristic(pdf_a, pdf_b):
    a2, b2 = dr.square(pdf_a), dr.square(pdf_b)
    w = a2 / (a2 + b2)
    return dr.select(dr.isfinite(w), w, 0)


def check_variant(variant=None):
    """Raise ``RuntimeError`` unless ``variant`` (default: the active one) can run the integrator.

    The integrator traces whole wavefronts with Dr.Jit loops: it needs a JIT variant
    (``llvm_*`` or ``cuda_*``) with RGB spectra, e.g. ``llvm_ad_rgb`` or ``cuda_ad_rgb``.
    """
    variant = variant or mi.variant()
    if variant is None:
        raise VariantError("manifold_path: call mi.set_variant(...) before using the integrator")
    if not (variant.startswith(("llvm_", "cuda_")) and variant.endswith("_rgb")):
        raise VariantError(
            f"manifold_path: variant {variant!r} is not supported; the integrator traces "
            "wavefronts with Dr.Jit and needs an RGB JIT variant such as 'llvm_ad_rgb' "
            "or 'cuda_ad_rgb' (mi.set_variant(...), then mitsuba_manifold.register())"
        )
    return variant


def developed_rgb(film):
    """The linear RGB image a film holds (float32 (H, W, 3), its crop window), whatever its
    ``pixel_format``: the film's raw storage (R, G, B, [A,] [AOVs,] W) divided by the filter
    weights, as ``develop`` does before converting to the pixel format (luminance, XYZ, ...), a
    fixed map of this RGB.
    """
    import numpy as np

    raw = np.array(film.bitmap(raw=True), dtype=np.float64)
    w = raw[..., -1:]
    rgb = raw[..., :3] / np.where(w > 0, w, 1.0)
    return np.where(w > 0, rgb, 0.0).astype(np.float32)
