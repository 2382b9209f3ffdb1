"""Inverse rendering without rendering (the Mitsuba part is :mod:`mitsuba_manifold.render.inverse`):
the latent point whose blend matches a target image (:mod:`.match`), the image errors it minimises
(:mod:`.objectives`), the target and its mask (:mod:`.targets`), the search of the latent space
shared with the render match (:mod:`.search`) and the weights that explain photographs, a convex
programme (:mod:`.acquisition`).

NumPy only.
"""
