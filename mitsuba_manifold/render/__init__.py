"""The only subsystem that imports Mitsuba and Dr.Jit: plugin registration, the
``manifold_brdf`` BSDF (paper Eq. 4 in a renderer), table lookups and sampling, the integrators,
scenes, rendering a basis (in chunks, on executors) and the example geometry.

Depends on every NumPy subsystem; nothing below it imports it.
"""
