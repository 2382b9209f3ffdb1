"""``tools/explore.py``: the manifold as a live page (paper Sec. 5.1 and 5.2, interactively).

An artist drags a point over the latent map and sees at once the scene with the
interpolated material (a blend of a basis of per-material renders, Eq. 13, computed and
encoded on the server), the material itself on a sphere shaded in the browser from the
interpolated table (WebGL 2, MERL's half/diff lookup in the fragment shader) and what the
manifold says about it: weights, albedo, GP variance (Eq. 2), negative bins, neighbours
and a BRDF slice. A full-GI reference render runs in the background on request, and a photo of
the basis's scene gives back the material in it (acquisition from the basis's own images).

Modules: :mod:`.service` (the state and every answer, no HTTP), :mod:`.server` (Starlette app),
:mod:`.encode` (tonemap and image encoding), :mod:`.material`, :mod:`.latentmap`,
:mod:`.reference`, :mod:`.guard` (who may talk to the server, size limits), :mod:`.inputs` (request
values), :mod:`.bases` (basis names and scenes), :mod:`.session` (one tab's websocket),
:mod:`.walks` (paths of ``Manifold.path`` and the distance to the closest measured material),
:mod:`.thumbs` (the materials' thumbnails), :mod:`.hdri` (the sphere's environment),
:mod:`.serving` (deadlines and a cap on connections, a quiet console), :mod:`.acquire` (a
material from a photo of a basis's scene); ``static/``
holds the page (no build step, no network access).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ...errors import InputError
from .service import Explorer

if TYPE_CHECKING:
    from starlette.applications import Starlette


def create_app(explorer, allow=None, **kwargs) -> Starlette:
    """The web app of an :class:`Explorer` (imports Starlette only when called); ``allow``: the
    :class:`~.guard.AllowList` of hosts and origins it answers to (see :func:`.server.create_app`).
    """
    from .server import create_app as _create

    return _create(explorer, allow, **kwargs)


__all__ = ["Explorer", "InputError", "create_app"]
