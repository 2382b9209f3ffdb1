"""The ``manifold_brdf`` plugin: the BSDF (paper Eq. 4 in a renderer, :mod:`.bsdf`), its table
lookups (:mod:`.lookups`) and importance sampling (:mod:`.sampling`), the material it renders
(:mod:`.material`), the differentiable latent point (:mod:`.ad`), per-scene table overrides
(:mod:`.overrides`), the reader of Mitsuba ``measured`` files (:mod:`.measured`), the choice of
libLLVM (:mod:`.llvm`) and the registration of the plugins for every variant (:mod:`.plugins`).
"""
