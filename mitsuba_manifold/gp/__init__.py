"""The Gaussian-process latent variable model (paper Sec. 3-4): the kernel (Eq. 1), the
likelihood objective (Eq. 2-3), rank-one updates and optimisers, and the GPLVM fit.

NumPy/SciPy only; knows nothing of tables or files (it takes a Gram matrix).
"""
