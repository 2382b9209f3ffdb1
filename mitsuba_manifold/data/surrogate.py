"""The SGD surrogate of the 100 MERL materials: the model, its fits and its tabulation on the MERL grid.

The real MERL files cannot be shipped, so the package tabulates the Shifted Gamma
Distribution (SGD) fits of the 100 MERL materials (Bagher et al. 2012, parameters in
``data/merl_sgd_fits.json``, model in ``data/SGD_MODEL.md``) on the MERL grid;
:func:`~mitsuba_manifold.data.database.make_database` writes them as MERL ``.binary`` files.
NumPy only, no files written here.
"""

from __future__ import annotations

import functools
import json
import os
from typing import TYPE_CHECKING

import numpy as np

from ..errors import FormatError, NumericalError, UnknownMaterialError
from . import merl

if TYPE_CHECKING:
    from typing import Any


FITS_PATH = os.path.join(os.path.dirname(os.path.abspath(__file__)), "merl_sgd_fits.json")
SGD_FIELDS = ("rho_d", "rho_s", "alpha", "p", "f0", "f1", "kap", "lambda", "c", "k", "theta0")


def load_sgd_fits(path=None) -> dict[Any, dict[str, np.ndarray]]:
    """SGD parameters per material: ``{name: {field: float64 array (3,)}}``, in file order."""
    path = path or FITS_PATH
    with open(path) as f:
        data = json.load(f)
    fits = {}
    for m in data["materials"]:
        params = {k: np.asarray(m[k], dtype=np.float64) for k in SGD_FIELDS}
        bad = [k for k, v in params.items() if v.shape != (3,) or not np.isfinite(v).all()]
        if bad:
            raise FormatError(f"{path}: material {m.get('name')!r} has invalid fields {bad}")
        fits[m["name"]] = params
    return fits


def _shadowing(theta, params):
    """SGD shadowing G1 for elevations ``theta`` (..., 1), per channel, overflow-safe.

    G1 = clamp(1 + lambda (1 - exp(c t^k)), 0, 1) with t = max(0, theta - theta0),
    evaluated as 1 + lambda - exp(log(lambda) + c t^k) so that huge exponents saturate
    to the intended limit instead of producing inf * 0.
    """
    t = np.maximum(theta - params["theta0"], 0.0)
    with np.errstate(divide="ignore", over="ignore"):
        log_ctk = np.log(params["c"]) + params["k"] * np.log(t)  # -inf where t == 0
        expo = np.exp(np.minimum(log_ctk, 700.0))  # c t^k, 0 where t == 0
        big = np.exp(np.minimum(np.log(params["lambda"]) + expo, 700.0))  # lambda exp(c t^k)
    return np.clip(1.0 + params["lambda"] - big, 0.0, 1.0)


def sgd_reflectance(params, wi, wo) -> np.ndarray:
    """SGD BRDF values (1/sr) for direction pairs.

    Parameters
    ----------
    params : dict
        One material's SGD fields, each of shape (3,).
    wi, wo : ndarray (..., 3)
        Unit directions in the local frame (normal = +z).

    Returns
    -------
    ndarray (..., 3)
        Reflectance per RGB channel, 0 where either direction is below the horizon.
    """
    return _sgd_values(params, _pair_geometry(wi, wo))


def _pair_geometry(wi, wo) -> dict[str, Any]:
    """The material-independent terms of the SGD model for direction pairs (..., 3)."""
    wi, wo = np.asarray(wi, dtype=np.float64), np.asarray(wo, dtype=np.float64)
    h = wi + wo
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    cos_h = np.clip(h[..., 2:3], 1e-300, 1.0)
    cos_i, cos_o = wi[..., 2:3], wo[..., 2:3]
    valid = (cos_i > 0) & (cos_o > 0)
    g = {
        "valid": valid,
        "cos_d": np.clip(np.sum(wi * h, axis=-1, keepdims=True), 0.0, 1.0),
        "tan2": np.maximum(1.0 - cos_h * cos_h, 0.0) / (cos_h * cos_h),
        "log_cos_h": np.log(cos_h),
        "theta_i": np.arccos(np.clip(cos_i, -1, 1)),
        "theta_o": np.arccos(np.clip(cos_o, -1, 1)),
        "inv_io": 1.0 / (np.where(valid, cos_i, 1.0) * np.where(valid, cos_o, 1.0)),
    }
    for v in g.values():
        v.setflags(write=False)
    return g


def _sgd_values(params, g) -> np.ndarray:
    """SGD values from :func:`_pair_geometry` terms (broadcast over the channels of ``params``)."""
    alpha, p = params["alpha"], params["p"]
    a = alpha + g["tan2"] / alpha
    with np.errstate(divide="ignore", over="ignore"):
        log_d = np.log(params["kap"]) - a - p * np.log(a) - np.log(np.pi) - 4.0 * g["log_cos_h"]
        d = np.exp(np.minimum(log_d, 700.0))
    cos_d = g["cos_d"]
    fresnel = params["f0"] - cos_d * params["f1"] + (1.0 - cos_d) ** 5 * (1.0 - params["f0"])
    shadow = _shadowing(g["theta_i"], params) * _shadowing(g["theta_o"], params)
    spec = params["rho_s"] * fresnel * d * shadow * g["inv_io"]
    f = (params["rho_d"] + spec) / np.pi
    return np.where(g["valid"], f, 0.0)


def tabulate_sgd(params, dims=merl.MERL_DIMS) -> np.ndarray:
    """Stored MERL values of an SGD material at bin centres (``phi_h = 0``).

    Bins whose directions lie below the horizon are marked :data:`merl.NOT_MEASURED`.
    Returns float64 of shape ``(3,) + dims``.
    """
    if isinstance(params, str):
        params = _fit_named(params)
    above, geometry = bin_geometry(tuple(int(v) for v in dims))
    refl = np.zeros((3,) + tuple(dims))
    for c in range(3):  # per channel keeps the temporaries at one bin-count each
        one = {k: v[c : c + 1] for k, v in params.items()}
        refl[c][above] = _sgd_values(one, geometry)[:, 0]
    if not np.isfinite(refl).all():  # guards the model's extreme fits; should never trigger
        raise NumericalError("SGD tabulation produced non-finite values")
    raw = merl.to_stored(refl)
    raw[:, ~above] = merl.NOT_MEASURED
    return raw


@functools.lru_cache(maxsize=2)
def bin_geometry(dims) -> tuple[Any, dict[str, Any]]:
    """The bins above the horizon and the SGD terms of their centres (once per process and resolution)."""
    th, td, pd = merl.bin_centres(dims)
    above = merl.above_horizon(dims)
    above.setflags(write=False)
    return above, _pair_geometry(*merl.directions(th[above], td[above], pd[above]))


def _fit_named(name) -> dict[str, np.ndarray]:
    fits = load_sgd_fits()
    if name not in fits:
        raise UnknownMaterialError(
            f"unknown material {name!r}: the built-in database has {len(fits)} materials "
            f"(e.g. {', '.join(list(fits)[:5])}, ...)"
        )
    return fits[name]
