"""Denoised blends: Intel Open Image Denoise guided by albedo and normal AOVs that blend too.

A denoiser works best with the albedo and normal of the first visible surface. Both are
available for any latent point from the basis without rendering:

* normals do not depend on the material (one image, shared);
* the albedo where the first hit is *not* the manifold material does not depend on it
  either (``albedo_base``: the mean BSDF sample weight ``f cos / pdf`` there, the
  directional albedo of any BSDF); where it is, the albedo of material ``i`` is its directional
  albedo ``a_i(theta)`` at the viewing angle, and that is linear in the BRDF, so the
  albedo of a blend with weights ``w`` is ``sum_i w_i a_i(theta)``, like Eq. 13.

:func:`~mitsuba_manifold.render.jobs.guides.render_aovs` traces first hits only (the
``manifold_aovs`` integrator, ``spp``
anti-aliased samples): normals, ``albedo_base`` (of other BSDFs) and, on the target, a
per-pixel histogram ``h`` of the viewing angle over :data:`THETA_BINS` bins.
:func:`directional_albedos` tabulates ``a_i`` per material and angle bin from the
measured tables (quadrature over half vectors). The albedo of
weights ``w`` is ``clip(albedo_base + h @ (w @ a), 0, 1)`` (:meth:`BasisAOVs.albedo`).
They are saved beside the basis as ``aovs.npz`` (atomic; checked against the basis
manifest on load). :func:`denoise` calls ``pyoidn`` (OIDN 2.x, CPU). Report the raw
image's error beside the denoised one: the denoiser is biased towards smooth images.
"""

import os
import zipfile
from dataclasses import dataclass

import numpy as np

from .._util.atomic import atomic_write
from ..data import merl
from ..errors import MismatchError
from . import folder as basis_folder
from .composition import compose

AOV_FILE = "aovs.npz"
THETA_BINS = 45  # as integrators.aovs.THETA_BINS (not imported: that module needs Mitsuba)
AOV_VERSION = 1
#: OIDN quality of the L2+ part of full-GI blends (:func:`denoised_l2`): smooth indirect light
#: needs no more (its errors and time against ``high``: ``docs/benchmarks.md``).
L2_QUALITY = "fast"
#: Width (standard deviation, as a fraction of the image's larger side) of the low-pass that puts
#: back the light the denoiser took from the L2+ part (:func:`restore_light`).
RESTORE_WIDTH = 1 / 8


# ------------------------------------------------------------------ directional albedos


def directional_albedos(db, names, bins=THETA_BINS, n_phi=64, refine=2, chunk=16):
    """``a[i, k, c]``: albedo of material ``names[i]`` lit from ``theta`` at the centre of bin ``k``.

    ``a(theta_i) = int f(w_i, w_o) cos(theta_o) dw_o``, integrated over half vectors
    ``h`` (``w_o`` = ``w_i`` reflected about ``h``, ``dw_o = 4 (w_i . h) dw_h``) by the
    midpoint rule on the tables' own ``theta_h`` spacing (``refine`` points per bin,
    so that narrow specular peaks are not missed) and ``n_phi`` azimuths, with the filled
    tables (negative values clamped at 0 as the BSDF does). The tables are read ``chunk``
    materials at a time, and of each only the bins the quadrature visits.
    """
    n_u = refine * int(db.dims[0])
    u = (np.arange(n_u) + 0.5) / n_u
    t_h = u * u * (np.pi / 2)
    dt_h = 2 * u * (np.pi / 2) / n_u
    p_h = (np.arange(n_phi) + 0.5) / n_phi * (2 * np.pi)
    T, P = np.meshgrid(t_h, p_h, indexing="ij")
    h = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
    dwh = (np.sin(T) * dt_h[:, None]).reshape(-1) * (2 * np.pi / n_phi)
    t_i = (np.arange(bins) + 0.5) / bins * (np.pi / 2)
    wi = np.repeat(np.stack([np.sin(t_i), np.zeros(bins), np.cos(t_i)], -1), len(h), 0)
    hh = np.tile(h, (bins, 1))
    cos_d = np.sum(wi * hh, -1)
    wo = 2 * cos_d[:, None] * hh - wi
    weight = np.where((wo[:, 2] > 0) & (cos_d > 0), wo[:, 2] * 4 * cos_d * np.tile(dwh, bins), 0.0)
    idx = merl.flat_index(wi, np.where(weight[:, None] > 0, wo, [0.0, 0.0, 1.0]), tuple(db.dims))
    uniq, inv = np.unique(idx, return_inverse=True)
    weight = weight.reshape(bins, len(h))
    out = np.empty((len(names), bins, 3), np.float32)
    for k0 in range(0, len(names), chunk):
        part = names[k0 : k0 + chunk]
        values = np.stack(
            [np.asarray(db.reflectance(n), np.float32).reshape(3, -1)[:, uniq].T for n in part],
            axis=-1,
        )  # (u, 3, k)
        f = np.maximum(values, 0.0)[inv.reshape(-1)].reshape(bins, len(h), 3, len(part))
        out[k0 : k0 + len(part)] = np.einsum("kocn,ko->nkc", f, weight)
    return out


@dataclass
class BasisAOVs:
    """The denoising guides of a basis (see the module docstring)."""

    normal: np.ndarray  # (H, W, 3)
    albedo_base: np.ndarray  # (H, W, 3)
    hist: np.ndarray  # (H, W, bins): fraction of samples hitting the target per angle bin
    table: np.ndarray  # (N, bins, 3): directional albedo per material
    names: list
    spp: int
    time_s: float = 0.0

    def albedo(self, weights):
        """Albedo image of the material with weights ``{name: w}`` (or (N,) in :attr:`names` order)."""
        if isinstance(weights, dict):
            index = {n: i for i, n in enumerate(self.names)}
            missing = [n for n in weights if n not in index]
            if missing:
                raise MismatchError(f"AOVs have no directional albedo for {missing}")
            w = np.zeros(len(self.names))
            for n, v in weights.items():
                w[index[n]] = v
        else:
            w = np.asarray(weights, dtype=np.float64)
            if w.shape != (len(self.names),):
                raise MismatchError(
                    f"weights must have {len(self.names)} entries, got shape {w.shape}"
                )
        mixed = np.tensordot(w, self.table, axes=1)  # (bins, 3)
        return np.clip(self.albedo_base + self.hist @ mixed.astype(np.float32), 0.0, 1.0)

    def albedo_of_blend(self, plan, version=basis_folder.FORMAT_VERSION):
        """Albedo image of a one-target blend, from its :class:`~.blend.BlendPlan` (image keys and
        weights).
        """
        weights = np.asarray(plan.image_weights, dtype=np.float64)
        return self.albedo(
            {basis_folder.key_materials(k, version)[0]: w for k, w in zip(plan.keys, weights)}
        )

    def save(self, folder, manifest):
        path = os.path.join(os.fspath(folder), AOV_FILE)
        key = _basis_key(manifest)
        import json

        atomic_write(
            path,
            lambda f: np.savez(
                f,
                normal=self.normal,
                albedo_base=self.albedo_base,
                hist=self.hist,
                table=self.table,
                names=np.array(self.names),
                spp=self.spp,
                time_s=self.time_s,
                version=AOV_VERSION,
                basis=json.dumps(key, sort_keys=True),
            ),
        )
        return path

    @classmethod
    def load(cls, folder, manifest=None):
        """Read ``folder/aovs.npz``; with ``manifest``, check it was made for that basis."""
        path = os.path.join(os.fspath(folder), AOV_FILE)
        if not os.path.isfile(path):
            raise MismatchError(f"{folder} has no {AOV_FILE} (render the basis with `aovs`)")
        out, key = cls._read(path)
        if manifest is not None:
            want = _basis_key(manifest)
            if want != key:
                diff = [k for k in want if want[k] != key.get(k)]
                raise MismatchError(
                    f"{path} was made for another basis ({', '.join(diff)} differ); "
                    "render the AOVs again"
                )
        return out

    @classmethod
    def _read(cls, path):
        """``(aovs, the basis key they were made for)`` of the file ``path``; a file that is not one
        (truncated, garbage, another version) raises :class:`MismatchError` naming it.
        """
        import json

        try:
            with np.load(path) as z:
                if int(z["version"]) != AOV_VERSION:
                    raise MismatchError(
                        f"{path}: AOV format version {int(z['version'])}, expected {AOV_VERSION}"
                    )
                out = cls(
                    z["normal"],
                    z["albedo_base"],
                    z["hist"],
                    z["table"],
                    [str(n) for n in z["names"]],
                    int(z["spp"]),
                    float(z["time_s"]),
                )
                return out, _stored_key(json.loads(str(z["basis"])))
        except (
            OSError,
            ValueError,
            KeyError,
            AttributeError,
            TypeError,
            EOFError,
            zipfile.BadZipFile,
        ) as e:
            raise MismatchError(
                f"{path} is not an AOV file written by render_basis with `aovs` ({type(e).__name__}); "
                "delete it and render the AOVs again"
            ) from None


def _basis_key(manifest):
    """What AOVs are made for: the basis's scene, manifold, resolution and sensor (a
    :class:`~.folder.Manifest` or its JSON object).
    """
    m = basis_folder.Manifest.from_json(manifest)
    return {
        "scene_hash": m.scene_hash,
        "manifold_hash": m.manifold_hash,
        "resolution": list(m.resolution),
        "sensor": m.sensor_index,
    }


def _stored_key(key):
    """:func:`_basis_key` as an AOV file stores it (a sensor not recorded is sensor 0)."""
    key = {k: key.get(k) for k in ("scene_hash", "manifold_hash", "resolution", "sensor")}
    key["sensor"] = key["sensor"] or 0
    return key


# ------------------------------------------------------------------ denoising


def denoise(image, albedo=None, normal=None, quality="high"):
    """OIDN (``pyoidn``) on a linear HDR image; ``albedo`` in [0, 1] and ``normal`` guide it."""
    try:
        import pyoidn
    except ImportError:
        raise MismatchError("denoising needs pyoidn (pip install pyoidn)") from None
    img = np.ascontiguousarray(np.maximum(image, 0.0), dtype=np.float32)
    kw = {}
    if albedo is not None:
        kw["albedo"] = np.ascontiguousarray(albedo, dtype=np.float32)
    if normal is not None:
        if albedo is None:
            raise MismatchError("OIDN takes normals only together with an albedo")
        kw["normal"] = np.ascontiguousarray(np.clip(normal, -1.0, 1.0), dtype=np.float32)
    return pyoidn.denoise(img, hdr=True, clean_aux=bool(kw), quality=quality, **kw)


# ------------------------------------------------------------------ the L2+ part of full-GI blends


def denoised_l2(basis, image, plan):
    """``L1- blend + D + restore_light(extra - D)``: the full-GI ``image`` of a one-target blend
    with its part beyond L1- (``extra``) denoised (``D``), guided by the basis's AOVs when it has
    them (:mod:`.denoise`), and the light the denoiser took put back at low frequency
    (:func:`restore_light`); ``plan``: the blend's :class:`~.blend.BlendPlan` (its L1- images,
    :attr:`~.blend.BlendPlan.keys`, and their weights). That part is
    signed (cross terms) and OIDN takes light only, so its positive and negative parts are denoised
    apart, at OIDN's ``fast`` quality (:data:`L2_QUALITY`; its errors against ``high``'s are in
    docs/benchmarks.md).
    """
    l1, _, _ = compose(basis, plan.keys, plan.image_weights, None)
    extra = image - l1
    guides = _guides(basis, plan)
    smooth = np.zeros_like(extra)
    for sign in (1.0, -1.0):  # a part may be empty (no negative cross term, weights >= 0)
        part = np.maximum(sign * extra, 0.0)
        if np.any(part):
            smooth = smooth + sign * denoise(part, *guides, quality=L2_QUALITY)
    return (l1 + smooth + restore_light(extra - smooth)).astype(np.float32)


def restore_light(removed, width=RESTORE_WIDTH):
    """The low-frequency part of what a denoiser ``removed`` (H, W, 3), each channel's total kept.

    OIDN takes fireflies away, and with them the light they carry on average: caustic paths
    through a narrow peak (white-paint's red lobe on the table's bowl) are rare and bright, so the
    denoised L2+ part is darker than its expectation, by about the same amount on every seed. That
    loss is smooth over the surface, so ``removed`` is added back blurred by a kernel of standard
    deviation ``width`` times the image's larger side: the blend then has the summed blend's light
    and keeps the denoiser's detail (figures in docs/benchmarks.md). Three box filters (reflected
    at the edges, so each channel's total is kept) stand for the Gaussian, at a cost independent
    of the width.
    """
    from scipy.ndimage import uniform_filter

    sigma = width * max(removed.shape[:2])
    size = (
        int(round(np.sqrt(4.0 * sigma * sigma + 1.0))) | 1
    )  # three boxes of variance (size^2 - 1) / 12
    out = np.asarray(removed, np.float32)
    for _ in range(3):
        out = uniform_filter(out, (size, size, 1), mode="reflect")
    return out


def basis_aovs(basis):
    """The :class:`BasisAOVs` of ``basis`` (read once per basis object), or None when it has none
    made for it.
    """
    return basis.derived("aovs", _aovs_or_none)


def _aovs_or_none(basis):
    """The basis's AOVs; None when it has none or they were made for another basis (stale: the
    denoiser then runs unguided); an unreadable file raises, naming it.
    """
    path = os.path.join(basis.folder, AOV_FILE)
    if not os.path.isfile(path):
        return None
    aovs, key = BasisAOVs._read(path)
    return aovs if key == _basis_key(basis.manifest) else None


def _guides(basis, plan):
    """``(albedo, normal)`` of a one-target L1- blend from the basis's AOVs, or ``(None, None)``."""
    aovs = basis_aovs(basis)
    if not aovs:
        return None, None
    try:
        return aovs.albedo_of_blend(plan, basis.manifest.version), aovs.normal
    except MismatchError:  # AOVs older than some of the basis's materials: unguided
        return None, None
