"""Thumbnails of the measured materials: each one rendered once with the plugin on the shipped
sphere scene at a small size, cached, shown as one sprite sheet.

The renders are a basis (:func:`~mitsuba_manifold.render.jobs.render_basis.render_basis`, one
pass for every material, with its albedo and normal guides ``aovs.npz``) of
``scenes/sphere.xml`` at :data:`SUPERSAMPLE` times :data:`SIZE` pixels, written by
``render_basis.py`` in a subprocess at low priority (the page stays usable meanwhile; a
server stopping ends it; a half-finished basis resumes on the next start) into
``<cache>/thumbs-<key>``, named by the content hashes of the manifold file and the scene and
by the render settings. Each thumbnail is the blend of its material alone (weight 1,
:func:`~mitsuba_manifold.basis.blend.blend`), denoised with OIDN guided by that material's
albedo and the normals (:func:`~mitsuba_manifold.basis.denoise.denoise`; without pyoidn, as
rendered), averaged over ``SUPERSAMPLE x SUPERSAMPLE`` pixels and tonemapped at 0 EV; the
sheet is ``columns`` tiles wide, material ``i`` at tile ``i`` (row-major). Its cost and why
these settings: ``docs/benchmarks.md``, "Measurements behind choices in the code".
"""

import math
import os
import subprocess
import sys
import threading

import numpy as np

from . import encode

SIZE = 48
SPP = 64
SUPERSAMPLE = 2
VERSION = "explore-thumbs-v2"
#: ``render_basis.py``'s main in the subprocess (the CLI module runs nothing on import).
RUN = "import sys; from mitsuba_manifold.apps.cli.render_basis import main; sys.exit(main())"


class Thumbnails:
    """The thumbnail sheet of a manifold's materials, made in the background.

    ``state``: ``"rendering"``, ``"ready"`` or ``"unavailable"`` (``message`` says why);
    :meth:`sheet` the PNG once ready. ``after``: called before rendering (the explorer passes its
    tables' ``wait``, so that a first start loads the tables before the thumbnails take the cores).
    """

    def __init__(self, manifold_path, manifold, cache_dir, size=SIZE, spp=SPP, after=None):
        from ..._util.cache import file_hash, key_hash
        from ...render.scene import scenes

        self.manifold_path, self.manifold, self.size, self.spp = (
            manifold_path,
            manifold,
            int(size),
            int(spp),
        )
        self.scene = scenes.scene_path("sphere")
        key = key_hash(
            VERSION,
            file_hash(manifold_path),
            file_hash(self.scene),
            str(self.size),
            str(self.spp),
            str(SUPERSAMPLE),
            length=16,
        )
        self.folder = os.path.join(cache_dir, f"thumbs-{key}")
        self.columns = max(1, math.ceil(math.sqrt(manifold.n)))
        self.state, self.message, self._png, self._proc, self._closed = (
            "rendering",
            "rendering thumbnails",
            None,
            None,
            False,
        )
        self._after = after  # called before rendering: the material tables load first (start-up)
        self._thread = threading.Thread(target=self._make, name="explore-thumbs", daemon=True)
        self._thread.start()

    def info(self):
        return {
            "state": self.state,
            "message": self.message,
            "size": self.size,
            "columns": self.columns,
        }

    def sheet(self):
        """PNG bytes of the sheet (raises InputError until it is ready)."""
        from ...errors import InputError

        if self.state != "ready":
            raise InputError(f"thumbnails are {self.state}: {self.message}")
        return self._png

    def wait(self, timeout=None):
        self._thread.join(timeout)
        return self.state

    def close(self):
        """Stop a render still running (the basis folder resumes next time)."""
        self._closed = True
        proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.terminate()

    def _make(self):
        try:
            if not self._complete():
                if self._after is not None:
                    self._after()
                self._render()
            if self._closed:
                return
            self._png = self._cached_sheet()
            self.state, self.message = "ready", f"{self.manifold.n} thumbnails ({self.size} px)"
        except Exception as e:  # no thumbnails: the page shows names only
            self.state, self.message = "unavailable", f"thumbnails unavailable: {str(e)[:200]}"

    def _complete(self):
        from ...basis.denoise import AOV_FILE
        from ...basis.folder import Basis

        try:
            basis = Basis.load(self.folder)
            return all(
                basis.has(k) for k in basis.material_keys(self.manifold.names)
            ) and os.path.isfile(os.path.join(self.folder, AOV_FILE))
        except Exception:
            return False

    def _render(self):
        cmd = [
            "nice",
            "-n",
            "10",
            sys.executable,
            "-c",
            RUN,
            self.scene,
            "--manifold",
            self.manifold_path,
            "--spp",
            str(self.spp),
            "--res",
            str(self.size * SUPERSAMPLE),
            "--mode",
            "onepass",
            "--aovs",
            "--out",
            self.folder,
        ]
        env = dict(os.environ, DRJIT_NUM_THREADS="1")
        root = os.path.dirname(
            os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        )
        env["PYTHONPATH"] = os.pathsep.join([root] + [p for p in [env.get("PYTHONPATH")] if p])
        # its own session: a Ctrl-C at the terminal stops the server, which ends this (close())
        self._proc = subprocess.Popen(
            cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, start_new_session=True
        )
        _, err = self._proc.communicate()
        if self._proc.returncode != 0 and not self._closed:
            lines = [ln for ln in err.decode(errors="replace").splitlines() if ln.strip()]
            raise RuntimeError(
                lines[-1] if lines else f"render_basis exited with {self._proc.returncode}"
            )

    def _cached_sheet(self):
        """The sheet's PNG, composed once (denoising takes seconds) and kept in the folder; one
        composed without a denoiser is kept apart (``sheet-raw.png``), made again once there is one.
        """
        from ..._util.atomic import write_bytes

        path = os.path.join(
            self.folder, "sheet-denoised.png" if _have_denoiser() else "sheet-raw.png"
        )
        if os.path.isfile(path):
            with open(path, "rb") as f:
                return f.read()
        png = encode.png_bytes(self._compose())
        write_bytes(path, png)
        return png

    def _compose(self):
        from ...basis.blend import blend
        from ...basis.folder import Basis

        basis = Basis.load(self.folder)
        n, s, cols = self.manifold.n, self.size, self.columns
        rows = math.ceil(n / cols)
        sheet = np.zeros((rows * s, cols * s, 3), dtype=np.uint8)
        clean = _cleaner(basis)
        for i in range(n):
            w = np.zeros(n)
            w[i] = 1.0
            img, _ = blend(basis, self.manifold, w=w, prune=0.0)
            r, c = divmod(i, cols)
            sheet[r * s : (r + 1) * s, c * s : (c + 1) * s] = encode.tonemap(
                shrink(clean(img, self.manifold.names[i]), s), 0.0
            )
        return sheet


def shrink(img, size):
    """``img`` (H, W, 3) averaged down to ``size`` x ``size`` (H and W multiples of ``size``)."""
    h, w = img.shape[:2]
    return img.reshape(size, h // size, size, w // size, 3).mean(axis=(1, 3)).astype(np.float32)


def _cleaner(basis):
    """``clean(image, name)``: a material's thumbnail render denoised by OIDN, guided by its albedo
    and the normals of the basis's AOVs (unguided without them); the image as it is without pyoidn.
    """
    from ...basis.denoise import basis_aovs, denoise
    from ...errors import MismatchError

    if not _have_denoiser():  # the renders as they are
        return lambda img, name: img
    aovs = basis_aovs(basis)  # None: no AOVs, or another basis's

    def clean(img, name):
        try:
            guides = (aovs.albedo({name: 1.0}), aovs.normal) if aovs else (None, None)
        except MismatchError:  # AOVs older than this material
            guides = (None, None)
        return denoise(img, *guides, quality="high")

    return clean


def _have_denoiser():
    try:
        import pyoidn  # noqa: F401

        return True
    except ImportError:
        return False
