"""Inverse rendering with Mitsuba (the NumPy-only part is :mod:`mitsuba_manifold.basis.inverse`):
matching target images by rendering with full GI (:mod:`.match_render`, started from the cheap
scan of :mod:`.scan`) and acquiring a material from photographs (:mod:`.acquire`).
"""
