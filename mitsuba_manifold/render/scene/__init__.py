"""Scenes, one concept a module: scene files (the shipped scenes, a scene XML's ``$parameters``
and manifold materials, :mod:`.files`), the variant a render runs in (:mod:`.variants`), what the
scene's integrator renders (:mod:`.integrator`), loading a scene with its materials at latent
points (:mod:`.loading`), reference renders (:mod:`.references`) and the example geometry
(:mod:`.geometry`). :mod:`.scenes` gathers the first five under one name.
"""
