"""Rendering jobs: a basis (:mod:`.render_basis`; with full GI and its cross terms,
:mod:`.gi_basis`), in chunks (:mod:`.chunks`) on executors (:mod:`.executor`), the denoising
guides (:mod:`.guides`), refining a blend into a converged render (:mod:`.refine`) and renders
that stop cleanly when interrupted (:mod:`.interrupt`).
"""
