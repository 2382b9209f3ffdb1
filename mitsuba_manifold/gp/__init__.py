"""The Gaussian-process latent variable model (paper Sec. 3-4), GPy style.

* :mod:`.kernel` — :class:`~.kernel.Kernel`, the covariance function of Eq. 5 as an object
  (``K(X)``, the cross-covariance ``k_*`` of Eq. 3, ``dk/dx``, ``dK/dtheta``) and the one
  factorisation of ``K`` (:class:`~.kernel.Factor`);
* :mod:`.likelihood` — :class:`~.likelihood.Likelihood`, the objective L of Eq. 6 and its gradients;
* :mod:`.rank_update` — the rank-one updated inverse of the paper's direct search;
* :mod:`.optimisers` — Hooke-Jeeves and L-BFGS-B, with their options dataclasses;
* :mod:`.gplvm` — the PCA start and :class:`~.gplvm.GPLVM` (``fit(S, d)`` -> :class:`~.gplvm.FitResult`);
* :mod:`.posterior` — the GP conditioned on fitted points (Eq. 1-4: weights, variance, gradients).

NumPy/SciPy only; knows nothing of tables or files (it takes a Gram matrix).
"""
