"""The saved manifold: the ``.npz`` format (:mod:`.io`) and its schema (:mod:`.schema`), the fit's
record stored in it (:mod:`.fit_record`), the identity of what a file computes (:mod:`.identity`)
and the manifolds shipped with the package (:mod:`.shipped`).
"""
