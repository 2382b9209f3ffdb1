"""Image error metrics against a reference, and error images.

Definitions (``a``: the image tested, ``r``: the reference, both linear RGB (H, W, 3);
means run over every pixel and channel):

- ``mse      = mean((a - r)^2)``
- ``rel_mse  = mean((a - r)^2 / (r^2 + eps))``, ``eps = 0.01``: the per-pixel, per-channel
  relative MSE common in rendering papers; ``eps`` keeps black pixels from dominating.
- ``psnr     = 10 log10(peak^2 / mse)`` dB with ``peak = max(r)`` (the reference's brightest
  value; 1 if the reference is all zero or negative); ``inf`` for identical images.
- ``max_abs  = max |a - r|``, ``mean_abs = mean |a - r|``.

A Monte Carlo reference has noise of its own: :func:`pass_standard_error` estimates it per pixel
from the images of independent passes, and :func:`noise_agreement` asks whether an image differs
from the reference by more than that noise.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import InputError
from .io import write_png

#: Default regulariser of :func:`rel_mse`.
REL_EPS = 0.01


def _pair(a, ref) -> tuple:
    a = np.asarray(a, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    if a.shape != ref.shape:
        raise InputError(f"image has shape {a.shape}, reference {ref.shape}: they must match")
    if a.size == 0:
        raise InputError("cannot compare empty images")
    for img, what in ((a, "image"), (ref, "reference")):
        if not np.isfinite(img).all():
            raise InputError(f"{what} contains NaN or Inf values")
    return a, ref


def mse(a, ref) -> float:
    """Mean squared error over pixels and channels."""
    a, ref = _pair(a, ref)
    return float(np.mean(np.square(a - ref)))


def rel_mse(a, ref, eps=REL_EPS) -> float:
    """Relative MSE ``mean((a - r)^2 / (r^2 + eps))`` (per pixel and channel)."""
    a, ref = _pair(a, ref)
    return float(np.mean(np.square(a - ref) / (np.square(ref) + eps)))


def psnr_peak(ref) -> float:
    """The PSNR peak: ``max(ref)``, or 1 when the reference has no positive value."""
    m = float(np.max(ref))
    return m if m > 0 else 1.0


def psnr(a, ref, peak=None) -> float:
    """PSNR in dB, ``10 log10(peak^2 / mse)``; ``peak`` defaults to :func:`psnr_peak`."""
    a, ref = _pair(a, ref)
    peak = psnr_peak(ref) if peak is None else float(peak)
    err = np.mean(np.square(a - ref))
    return float("inf") if err == 0 else float(10.0 * np.log10(peak * peak / err))


def max_abs(a, ref) -> float:
    """Largest absolute difference over pixels and channels."""
    a, ref = _pair(a, ref)
    return float(np.max(np.abs(a - ref)))


def pass_standard_error(weighted_sum, weighted_squares, samples, passes) -> np.ndarray:
    """Per-pixel standard error of the mean of independent render passes.

    Pass ``k`` renders ``n_k`` samples per pixel into the image ``I_k``; the mean is
    ``m = sum_k n_k I_k / N`` with ``N = sum_k n_k``. A pass's variance is ``s^2 / n_k`` with
    ``s^2`` a sample's variance, estimated without bias by
    ``s^2 = sum_k n_k (I_k - m)^2 / (P - 1) = (sum_k n_k I_k^2 - N m^2) / (P - 1)``; the mean's
    standard error is ``sqrt(s^2 / N)``.

    Parameters
    ----------
    weighted_sum, weighted_squares : ndarray
        ``sum_k n_k I_k`` and ``sum_k n_k I_k^2``.
    samples : int
        ``N``.
    passes : int
        ``P``; with fewer than 2 the error is unknown (NaN).
    """
    total = np.asarray(weighted_sum, np.float64)
    if passes < 2:
        return np.full_like(total, np.nan)
    mean = total / samples
    var = np.maximum(np.asarray(weighted_squares, np.float64) - samples * mean * mean, 0.0)
    return np.sqrt(var / ((passes - 1) * samples))


class _Fields(Mapping):
    """A frozen answer that reads as the mapping of its fields too (``r["psnr"]``, ``"psnr" in r``,
    ``r.get``, ``r.items()``, ``{**r}``, ``dict(r)``), as the dicts these answers replace did.
    """

    def as_dict(self) -> dict[str, Any]:
        """The JSON object of the answer (its field names as keys)."""
        return dataclasses.asdict(self)

    def __getitem__(self, key: str) -> Any:
        return self.as_dict()[key]

    def __iter__(self) -> Iterator[str]:
        return iter(f.name for f in dataclasses.fields(self))

    def __len__(self) -> int:
        return len(dataclasses.fields(self))


@dataclass(frozen=True)
class NoiseAgreement(_Fields):
    """:func:`noise_agreement`'s answer (each None where the reference has no noise estimate: a
    reference of one pass). Reads as the mapping it replaces too (``r["agrees"]``, ``{**r}``);
    ``as_dict()`` is its JSON object.
    """

    rel_mse: float | None
    noise_rel_mse: float | None
    excess_rel_mse: float | None
    agrees: bool | None


def noise_agreement(a, ref, ref_se, eps=REL_EPS, scale=None) -> NoiseAgreement:
    """Whether ``a`` equals a noisy reference within the reference's own noise.

    Relative to ``s = scale`` (default the reference ``r``): ``rel_mse = mean((a - r)^2 /
    (s^2 + eps))``, and ``noise_rel_mse = mean(se^2 / (s^2 + eps))``, the relative MSE that an
    exact, noise-free ``a`` would show against ``r`` (on average); ``agrees`` when ``rel_mse`` is
    at most twice that. ``excess_rel_mse`` is the part of the error the reference's noise does
    not explain (``max(rel_mse - noise_rel_mse, 0)``): the bias of ``a`` and the noise ``a`` has
    of its own (a blend of Monte Carlo renders has some).

    Returns
    -------
    NoiseAgreement
        ``rel_mse``, ``noise_rel_mse``, ``excess_rel_mse``, ``agrees`` (all None where ``ref_se``
        is NaN: a reference of one pass).
    """
    a, ref = _pair(a, ref)
    se = np.asarray(ref_se, np.float64)
    if se.shape != ref.shape:
        raise InputError(
            f"reference error has shape {se.shape}, reference {ref.shape}: they must match"
        )
    if not np.isfinite(se).all():
        return NoiseAgreement(None, None, None, None)
    denominator = np.square(ref if scale is None else np.asarray(scale, np.float64)) + eps
    noise = float(np.mean(se * se / denominator))
    err = float(np.mean(np.square(a - ref) / denominator))
    return NoiseAgreement(
        rel_mse=err,
        noise_rel_mse=noise,
        excess_rel_mse=max(err - noise, 0.0),
        agrees=bool(err <= 2.0 * noise),
    )


def negative_pixels(image) -> int:
    """Pixels of ``image`` (H, W, 3) with a value below 0 in any channel (a sum of noisy
    signed terms, such as the cross terms of a full-GI blend, can go below 0).
    """
    return int((np.asarray(image) < 0).any(axis=-1).sum())


def error_image(a, ref) -> np.ndarray:
    """Per-pixel, per-channel absolute difference ``|a - r|`` as float32 (H, W, 3)."""
    a, ref = _pair(a, ref)
    return np.abs(a - ref).astype(np.float32)


@dataclass(frozen=True)
class Comparison(_Fields):
    """:func:`compare`'s metrics of an image against a reference (definitions in the module's
    docstring). Reads as the mapping it replaces too (``c["psnr"]``, ``{**c}``); ``as_dict()``
    is its JSON object.
    """

    rel_mse: float
    mse: float
    psnr: float  # dB; inf for identical images
    peak: float
    max_abs: float
    mean_abs: float
    eps: float


def compare(a, ref, eps=REL_EPS, peak=None) -> Comparison:
    """All metrics of ``a`` against ``ref``.

    Returns
    -------
    Comparison
        ``rel_mse``, ``mse``, ``psnr`` (dB), ``peak``, ``max_abs``, ``mean_abs``, ``eps``.
    """
    a, ref = _pair(a, ref)
    d = a - ref
    sq = np.square(d)
    err = float(sq.mean())
    peak = psnr_peak(ref) if peak is None else float(peak)
    return Comparison(
        rel_mse=float(np.mean(sq / (np.square(ref) + eps))),
        mse=err,
        psnr=float("inf") if err == 0 else float(10.0 * np.log10(peak * peak / err)),
        peak=peak,
        max_abs=float(np.abs(d).max()),
        mean_abs=float(np.abs(d).mean()),
        eps=float(eps),
    )


def false_colour(error, vmax=None, cmap="inferno") -> tuple[np.ndarray, Any]:
    """Map a scalar error per pixel to 8-bit RGB with a matplotlib colour map.

    Parameters
    ----------
    error : array_like (H, W) or (H, W, 3)
        Colour images are reduced to their mean over channels.
    vmax : float, optional
        Value mapped to the top of the colour map (default: the largest error).

    Returns
    -------
    rgb : ndarray uint8 (H, W, 3)
    vmax : float
    """
    from matplotlib import colormaps

    e = np.asarray(error, dtype=np.float64)
    if e.ndim == 3:
        e = e.mean(axis=-1)
    if e.ndim != 2:
        raise InputError(f"error image must be (H, W) or (H, W, 3), got {np.shape(error)}")
    vmax = float(e.max()) if vmax is None else float(vmax)
    scaled = e / vmax if vmax > 0 else np.zeros_like(e)
    rgba = colormaps[cmap](np.clip(scaled, 0.0, 1.0), bytes=True)
    return np.ascontiguousarray(rgba[..., :3]), vmax


#: Percentile of the per-pixel error at the top of an error PNG's colour scale: a few
#: fireflies do not darken the rest of the image (they are drawn at the top colour).
ERROR_PERCENTILE = 99.0


def robust_scale(error, percentile=ERROR_PERCENTILE) -> float:
    """The ``percentile`` of a per-pixel error (mean over channels); its maximum if that is 0."""
    e = np.asarray(error, dtype=np.float64)
    e = e.mean(axis=-1) if e.ndim == 3 else e
    v = float(np.percentile(e, percentile))
    return v if v > 0 else float(e.max())


def write_error_png(
    path, a, ref, vmax=None, cmap="inferno", percentile=ERROR_PERCENTILE, scale_note=None
) -> float:
    """False-colour PNG of ``|a - r|`` (mean over channels) with its colour bar, written atomically.

    The scale runs from 0 to ``vmax`` (default: the ``percentile`` of the error,
    :func:`robust_scale`); errors above it take the top colour and the legend says how many
    pixels do. The scale is drawn under the image and also stored in the PNG's text chunks.
    ``scale_note`` says where a given ``vmax`` comes from (e.g. another image's scale).
    Returns ``vmax``.
    """
    from matplotlib import colormaps

    from .io import with_colour_bar

    err = error_image(a, ref).mean(axis=-1)
    how = f"{percentile:g}th percentile" if vmax is None else (scale_note or "a fixed scale")
    vmax = robust_scale(err, percentile) if vmax is None else float(vmax)
    rgb, vmax = false_colour(err, vmax, cmap)
    above = float((err > vmax).mean())
    ramp = colormaps[cmap](np.linspace(0, 1, 256), bytes=True)[:, :3]
    ticks = [(0.0, "0"), (0.5, f"{vmax / 2:.3g}"), (1.0, f"{vmax:.3g}" + ("+" if above else ""))]
    caption = (
        f"|image - reference|, mean of RGB; scale 0 to {vmax:.3g} ({how}); "
        f"{above:.1%} of pixels above it, at the top colour"
    )
    write_png(
        path,
        with_colour_bar(rgb, ramp, ticks, caption),
        text={"error-scale": f"0 .. {vmax:.6g} ({cmap}, mean |a - ref| over RGB)"},
    )
    return vmax
