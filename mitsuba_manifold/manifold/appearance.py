"""How far a path between two materials strays from them in colour: the path-stray measure.

An artist reads a morph from blue to white that passes through brown as wrong even when
every step is small. The measure here looks at what a viewer sees first, the colour of the
material under light from a few incidences: the directional albedo (linear RGB,
:class:`plausibility.DirectionalAlbedo`) at :data:`INCIDENCES`, each in CIELAB (D65). A
material is the concatenation of those Lab triples; a path's *stray* is the largest
distance of its points from the segment between its two ends in that space (so a path
that only lightens or darkens between the ends' colours strays 0), in CIELAB units
(``Delta E``, averaged over the incidences by root mean square) and as a share of the ends'
own distance. Directional albedo is linear in the tables, so along a path it is the
weights times each material's albedos: no table is combined.
"""

from __future__ import annotations

import numpy as np

from .plausibility import DirectionalAlbedo

#: Incidences (degrees) of the colour descriptor.
INCIDENCES = (10.0, 45.0, 75.0)
#: Linear sRGB (Rec. 709 primaries) to CIE XYZ, D65 white.
RGB_TO_XYZ = np.array(
    [
        [0.4124564, 0.3575761, 0.1804375],
        [0.2126729, 0.7151522, 0.0721750],
        [0.0193339, 0.1191920, 0.9503041],
    ]
)
WHITE = RGB_TO_XYZ.sum(axis=1)


def lab(rgb) -> np.ndarray:
    """CIELAB of linear RGB reflectances ``(..., 3)`` (1 = a perfect white)."""
    xyz = np.asarray(rgb, dtype=np.float64) @ RGB_TO_XYZ.T / WHITE
    xyz = np.maximum(xyz, 0.0)
    e = 216 / 24389
    f = np.where(xyz > e, np.cbrt(xyz), (24389 / 27 * xyz + 16) / 116)
    return np.stack(
        [116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]), 200 * (f[..., 1] - f[..., 2])], -1
    )


def material_albedos(tables, dims, incidences=INCIDENCES) -> np.ndarray:
    """Directional albedos ``(N, n_incidence, 3)`` of flat RGB tables ``(N, d)``."""
    da = DirectionalAlbedo(dims, theta_i=np.radians(incidences))
    return np.transpose(da.of(tables), (0, 2, 1))


def descriptor(albedos) -> np.ndarray:
    """Lab triples of directional albedos ``(..., n_incidence, 3)``, flattened to ``(..., 3 n_incidence)``."""
    L = lab(albedos)
    return L.reshape(L.shape[:-2] + (-1,))


def distance_to_segment(P, a, b) -> np.ndarray:
    """Euclidean distance of the rows of ``P`` from the segment ``[a, b]``."""
    ab = b - a
    t = np.clip((P - a) @ ab / max(float(ab @ ab), 1e-300), 0.0, 1.0)
    return np.linalg.norm(P - (a + t[:, None] * ab), axis=1)


def stray(weights, albedos) -> dict:
    """Path stray of a path whose points have weights ``weights`` ``(K, N)`` (first and last: the ends).

    ``albedos``: :func:`material_albedos` of the N materials. Returns a dict: ``delta_e`` (the
    largest RMS-over-incidences CIELAB distance of a point from the ends' segment), ``share``
    (that over the ends' own distance), ``at`` (the point's index) and ``lab`` (each point's
    Lab at the middle incidence, for plots).
    """
    alb = np.einsum("kn,nic->kic", np.asarray(weights, dtype=np.float64), albedos)
    D = descriptor(alb)
    n_inc = albedos.shape[1]
    dist = distance_to_segment(D, D[0], D[-1]) / np.sqrt(n_inc)
    ends = float(np.linalg.norm(D[-1] - D[0]) / np.sqrt(n_inc))
    k = int(np.argmax(dist))
    return {
        "delta_e": float(dist[k]),
        "share": float(dist[k] / max(ends, 1e-12)),
        "at": k,
        "ends_delta_e": ends,
        "lab": lab(alb[:, n_inc // 2]).tolist(),
    }
