"""``tools/explore.py``: the manifold as a live page (paper Sec. 5.1 and 5.2, interactively).

An artist drags a point over the latent map and sees at once the scene with the
interpolated material (a blend of a basis of per-material renders, Eq. 13, computed and
encoded on the server), the material itself on a sphere shaded in the browser from the
interpolated table (WebGL 2, MERL's half/diff lookup in the fragment shader) and what the
manifold says about it: weights, albedo, GP variance (Eq. 2), negative bins, neighbours
and a BRDF slice. A full-GI reference render runs in the background on request, and a photo of
the basis's scene gives back the material in it (acquisition from the basis's own images).

Modules: :mod:`.service` (the state and every answer, no HTTP), :mod:`.encode` (tonemap and
image encoding), :mod:`.material`, :mod:`.latentmap`, :mod:`.reference`, :mod:`.bases` (basis
names and scenes), :mod:`.walks` (paths of ``Manifold.path`` and the distance to the closest
measured material), :mod:`.thumbs` (the materials' thumbnails), :mod:`.hdri` (the sphere's
environment), :mod:`.acquire` (a material from a photo of a basis's scene), :mod:`.render_job`
(a reference render in its own process); the web layer in :mod:`.web`: :mod:`.web.server`
(Starlette app), :mod:`.web.guard` (who may talk to the server, size limits),
:mod:`.web.inputs` (request values), :mod:`.web.session` (one tab's websocket),
:mod:`.web.serving` (deadlines and a cap on connections, a quiet console) and
:mod:`.web.launch`; ``static/`` holds the page (no build step, no network access).
"""

from ..._util.moved import alias as _alias
from ...errors import InputError
from .service import Explorer


def create_app(explorer, allow=None, **kwargs):
    """The web app of an :class:`Explorer` (imports Starlette only when called); ``allow``: the
    :class:`~.web.guard.AllowList` of hosts and origins it answers to (see :func:`.web.server.create_app`).
    """
    from .web.server import create_app as _create

    return _create(explorer, allow, **kwargs)


__all__ = ["Explorer", "InputError", "create_app"]

#: Modules that moved into sub-packages: their old names import the new modules, deprecated.
_MOVED = {
    "server": ".web.server",
    "serving": ".web.serving",
    "session": ".web.session",
    "guard": ".web.guard",
    "inputs": ".web.inputs",
    "launch": ".web.launch",
}
_alias(__name__, _MOVED)
