"""How a basis is sampled: the settings a render of one can take, checked before any work.

A basis is rendered with ``spp`` samples per pixel, in ``chunks`` chunks (chunk ``j`` of ``k``
seeded ``seed * k + j``) and, in one-pass mode, in passes of one sample at most (pass ``p`` of
``n`` seeded ``seed * n + p``): every derived seed must fit Mitsuba's 32 bits. NumPy only, so
that a command line is checked before the renderer is imported.
"""

from .._util import checks as validate
from ..errors import InputError

#: Samples per pixel of a basis whose scene declares none and none is given.
DEFAULT_SPP = 64


def check_sampling(spp, chunks=1, mode="onepass", seed=0, res=None, max_depth=None) -> None:
    """Raise :class:`InputError` for settings no render can take, before any folder is made:
    ``spp`` (the most samples per pixel of any basis), ``chunks``, ``res``, ``max_depth`` and
    ``seed``, whose derived seeds must fit Mitsuba's 32 bits (one-pass renders seed pass ``p``
    of ``n`` with ``seed * n + p``, at most one pass per sample; chunk ``j`` of ``k`` has seed
    ``seed * k + j``).
    """
    validate.positive_int("`spp`", spp, "64")
    validate.positive_int("`chunks`", chunks, "4")
    if res is not None and not 1 <= res <= 16384:
        raise InputError(f"`res` must be from 1 to 16384, got {res}")
    if max_depth is not None and max_depth != -1 and max_depth < 2:
        raise InputError(
            f"`max_depth` must be -1 (unbounded) or at least 2, got {max_depth} (depth 1 "
            "reaches only the lights seen directly: no image would show the material)"
        )
    per_chunk = -(-spp // chunks)
    streams = chunks * (per_chunk if mode == "onepass" else 1)
    why = (
        f" with `spp` {spp}, `chunks` {chunks} and `mode` {mode} (the renderer derives up to "
        f"{streams} seeds from it, and Mitsuba's seeds have 32 bits)"
    )
    validate.seed("`seed`", seed, streams, why if streams > 1 else "")
