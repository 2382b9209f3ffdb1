"""Scenes: the shipped scenes and loading a scene with a manifold material, the variant a render
uses, the integrator a basis is rendered with, reference renders (:mod:`.scenes`) and the example
geometry (:mod:`.geometry`).
"""
