"""What :meth:`Manifold.fit <mitsuba_manifold.manifold.model.Manifold.fit>` did: a small typed record.

:class:`FitRecord` holds the fit's settings (preset, method, latent dimension), the size of the
data (``d`` values per material at resolution ``dims``), the outcome (final log-likelihood of
Eq. 6, its history, evaluations; whether the optimiser's convergence test was met, after how
many iterations, the final gradient norm and why it stopped) and the :class:`Timings`. In a saved manifold it is the
``info`` entry of the ``.npz`` metadata plus the ``history`` array (:mod:`.io`);
:meth:`FitRecord.from_info` reads that layout (also files of format version 1, and
entries this version does not know, which are kept in :attr:`FitRecord.extra` and written
back) and :meth:`FitRecord.as_info` writes it.
"""

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Timings:
    """Wall times of the fit's stages, seconds (None: not measured): reading the tables, the
    Gram matrices (with the stress term's distances when it is on) and the optimisation.
    """

    load_s: float = None
    gram_s: float = None
    fit_s: float = None


@dataclass
class FitRecord:
    """Settings, outcome and timings of a manifold's fit (all optional: a manifold made by hand has none).

    Attributes
    ----------
    method : str
        Optimiser (``"newton"``, ``"lbfgs"`` or ``"hooke-jeeves"``).
    preset : str
        Preset the settings came from (``"default"``, ``"paper"``; ``"custom"`` if unknown).
    q, d : int
        Latent dimension; values per material.
    dims : tuple of int
        Table resolution ``(n_theta_h, n_theta_d, n_phi_d)``.
    log_likelihood : float
        Final L (Eq. 6).
    n_evaluations : int
        Objective evaluations of the optimiser.
    converged : bool or None
        Whether the optimiser's convergence test was met (None: not recorded, a file saved
        before the test was).
    n_iterations : int
        Optimiser iterations (sweeps for Hooke-Jeeves).
    grad_norm : float
        The objective's gradient norm at the saved points relative to ``d N / 2``
        (:func:`~mitsuba_manifold.gp.optimisers.gradient_norm`).
    stop : str
        Why the optimiser stopped.
    history : ndarray
        L per optimiser iteration.
    timings : Timings
    extra : dict
        Entries of a saved ``info`` that are none of the above (kept and written back).
    """

    method: str = None
    preset: str = None
    q: int = None
    d: int = None
    dims: tuple = None
    log_likelihood: float = None
    n_evaluations: int = None
    converged: bool = None
    n_iterations: int = None
    grad_norm: float = None
    stop: str = None
    history: np.ndarray = field(default_factory=lambda: np.zeros(0))
    timings: Timings = field(default_factory=Timings)
    extra: dict = field(default_factory=dict)

    #: The entries of the saved ``info`` dict, in their order (the timings are ``time_*_s``).
    INFO = (
        "method",
        "d",
        "dims",
        "q",
        "preset",
        "log_likelihood",
        "time_load_s",
        "time_gram_s",
        "time_fit_s",
        "n_evaluations",
        "converged",
        "n_iterations",
        "grad_norm",
        "stop",
    )

    def __post_init__(self):
        self.history = np.asarray(self.history, dtype=np.float64)
        if self.dims is not None:
            self.dims = tuple(self.dims)

    @classmethod
    def from_info(cls, info=None, history=()):
        """The record of a saved ``info`` dict and ``history`` array."""
        info = dict(info or {})
        times = Timings(*(info.pop(f"time_{k}_s", None) for k in ("load", "gram", "fit")))
        known = {k: info.pop(k) for k in cls.INFO if k in info}
        return cls(**known, history=history, timings=times, extra=info)

    def convergence(self):
        """One line on the optimiser's convergence: met or not, iterations, gradient norm;
        ``unknown`` for a record without it.
        """
        if self.converged is None:
            return "convergence unknown (not recorded: saved before fits recorded it; refit)"
        parts = [f"{self.n_iterations} iterations" if self.n_iterations is not None else None]
        if self.grad_norm is not None:
            parts.append(f"gradient norm {self.grad_norm:.3g}")
        detail = ", ".join(p for p in parts if p)
        if self.converged:
            return f"converged ({detail})"
        return f"NOT CONVERGED ({detail}): {self.stop or 'stopped early'}"

    def as_info(self):
        """The ``info`` dict of the saved layout (entries that are None left out)."""
        out = {}
        for key in self.INFO:
            value = (
                getattr(self.timings, key[5:]) if key.startswith("time_") else getattr(self, key)
            )
            if value is not None:
                out[key] = list(value) if key == "dims" else value
        out.update(self.extra)
        return out
