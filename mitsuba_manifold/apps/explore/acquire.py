"""A material acquired from one photograph of a basis's scene, in the explorer.

A basis of one target already holds what acquisition needs for a photo taken with its camera
and lights: the image of every training material alone (``I_i``) and of everything else
(``base``), so the photo is modelled as ``base + sum_i w_i I_i`` without rendering anything
(:class:`~mitsuba_manifold.basis.inverse.acquisition.LinearPhotos`), and the weights are found by the
acquisition's convex programme (:func:`~mitsuba_manifold.basis.inverse.acquisition.choose`, ``solve``,
``solve_beyond``, ``spread``; the plausibility constraints of
:func:`~mitsuba_manifold.render.inverse.acquire.constraints_of`).

Cross terms: where the basis holds full-GI images, ``I_i`` is material ``i``'s full-GI image
(``touch_i + L2+_i``, exact at every training material); the cross terms ``C_ij`` (second order
in the weights: light scattered off the material twice, by two different materials) are left
out of the solve, which stays convex, and the acquired material is shown as the basis's full
blend at its weights, cross terms included. A basis of L1- images solves on those (exact for an
object that does not see itself).

Then: the latent point whose weights explain the photo best (a search over the latent space of
the same data term, from the measured materials' points); the acquired material is *on the map*
when that point's error is within :data:`LATENT_TOLERANCE` of the acquired weights' (or within
:data:`LATENT_ABSOLUTE`) and its material is plausible (directional albedo in [0, 1]), else it is
named as a combination of measured materials. :class:`Acquisitions` runs one acquisition at a
time in a background thread with its progress.
"""

import base64
import binascii
import io
import os
import tempfile
import threading
import time
import traceback
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..._util.blas import one_thread
from ...basis.blend import blend
from ...basis.folder import BASE
from ...basis.inverse import acquisition as aq
from ...errors import BusyError, InputError, MitsubaManifoldError
from . import encode
from .web.inputs import show

#: Largest upload (bytes of the JSON body: photo and mask, base64).
MAX_UPLOAD = 24 * 1024 * 1024
#: Largest photo (pixels) decoded.
MAX_PIXELS = 4096 * 4096
#: A photo of another size is resized to the basis's when the aspect ratios differ by at most this.
ASPECT_TOLERANCE = 0.01
#: The latent point is the acquired material's place on the map when its relative error is at
#: most ``1 + LATENT_TOLERANCE`` times the acquired weights' (or within ``LATENT_ABSOLUTE``).
LATENT_TOLERANCE = 0.1
LATENT_ABSOLUTE = 0.01
#: ... and when its material is plausible: directional albedo in ``[-ALBEDO_SLACK, 1 + ALBEDO_SLACK]``.
ALBEDO_SLACK = 0.01
#: Starts of the latent search: the measured materials whose own images explain the photo best.
LATENT_STARTS = 4
#: Weights outside the simplex are "beyond the manifold": a weight below ``-SIMPLEX_TOLERANCE``,
#: or weights summing to more than ``SUM_TOLERANCE`` away from 1.
SIMPLEX_TOLERANCE = 1e-3
SUM_TOLERANCE = 0.1
#: Jobs kept (finished ones beyond are forgotten, oldest first).
JOBS_KEPT = 4
#: Smallest tile side of the contact sheet (pixels; small bases are enlarged, nearest pixel).
SHEET_TILE = 256
#: Images of a finished job (``/api/acquire/{id}/{which}.png``).
IMAGES = ("target", "acquired", "single", "mask", "sheet")


# ------------------------------------------------------------------ upload
def decode_data(value, what):
    """Bytes of an upload field: a ``data:...;base64,`` URL or plain base64, or InputError."""
    if not isinstance(value, str) or not value:
        raise InputError(
            f"`{what}` must be a file's content as base64 (a data: URL), got {show(value)}"
        )
    text = value.split(",", 1)[1] if value.startswith("data:") and "," in value else value
    try:
        return base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError):
        raise InputError(f"`{what}` is not valid base64 (send the file as a data: URL)") from None


def _kind(data, what):
    """``".exr"``, ``".png"`` or ``".jpg"`` from the file's first bytes, or InputError."""
    if data[:4] == b"v/1\x01":
        return ".exr"
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return ".png"
    if data[:3] == b"\xff\xd8\xff":
        return ".jpg"
    raise InputError(
        f"{what} is not an OpenEXR, PNG or JPEG file (its first bytes say otherwise); give a "
        "linear EXR or an sRGB PNG/JPEG"
    )


def _size_of(data, kind):
    """``(width, height)`` from the header, before any pixel is decoded."""
    if kind == ".exr":
        return None  # the reader checks the header itself
    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as im:
            return im.size
    except Exception as e:  # Pillow raises many kinds on a broken file
        raise InputError(f"unreadable image ({type(e).__name__}: {e})") from None


def _read(data, what, reader):
    """``reader(path)`` of the uploaded bytes (written to a temporary file), errors in one line."""
    from ...basis.inverse import targets

    kind = _kind(data, what)
    size = _size_of(data, kind)
    if size is not None and size[0] * size[1] > MAX_PIXELS:
        raise InputError(f"{what} is {size[0]}x{size[1]}: at most {MAX_PIXELS} pixels are read")
    fd, path = tempfile.mkstemp(suffix=kind, prefix="explore-acquire-")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        if kind == ".exr":  # its header's size, before any pixel is decoded
            from ...imaging.io import read_exr_header

            head = read_exr_header(path)
            if head.width * head.height > MAX_PIXELS:
                raise InputError(
                    f"{what} is {head.width}x{head.height}: at most {MAX_PIXELS} pixels are read"
                )
        return getattr(targets, reader)(path)
    except MitsubaManifoldError as e:
        raise InputError(f"{what}: {str(e).replace(path, 'the file')}") from None
    except (OSError, ValueError, SyntaxError) as e:
        raise InputError(f"{what}: unreadable ({type(e).__name__}: {e})") from None
    finally:
        os.unlink(path)


def _resize(img, size, what, notes):
    """``img`` ((H, W) or (H, W, 3)) at ``size`` (width, height): box-filtered, with a note
    saying so; InputError when the aspect ratios differ.
    """
    from PIL import Image

    h, w = img.shape[:2]
    if (w, h) == tuple(size):
        return img
    W, H = size
    if abs((w / h) / (W / H) - 1.0) > ASPECT_TOLERANCE:
        raise InputError(
            f"{what} is {w}x{h} and the basis's images {W}x{H}: the aspect ratios differ, so it "
            "cannot be of this basis's camera (crop it to the camera's frame)"
        )
    chans = [img] if img.ndim == 2 else [img[..., c] for c in range(img.shape[2])]
    out = [
        np.asarray(
            Image.fromarray(np.ascontiguousarray(c, np.float32), "F").resize((W, H), Image.BOX)
        )
        for c in chans
    ]
    notes.append(f"{what} resized from {w}x{h} to the basis's {W}x{H}")
    return out[0] if img.ndim == 2 else np.stack(out, axis=-1)


def read_upload(photo, mask, size):
    """The photo (linear float64 (H, W, 3)) and mask ((H, W) in [0, 1] or None) of an upload, at
    the basis's ``size`` (width, height), and notes of what was done (resized, clipped pixels
    left out). PNG/JPEG pixels at their largest code (clipped) are masked out.
    """
    notes = []
    target, clipped = _read(decode_data(photo, "photo"), "the photo", "read_target")
    target = _resize(np.asarray(target, np.float64), size, "the photo", notes)
    if not np.isfinite(target).all():
        raise InputError("the photo has NaN or Inf values")
    if not (target > 0).any():
        raise InputError("the photo is black: nothing to acquire from")
    m = None
    if mask is not None and mask != "":
        m = _read(decode_data(mask, "mask"), "the mask", "read_mask")
        m = np.clip(_resize(np.asarray(m, np.float64), size, "the mask", notes), 0.0, 1.0)
        if not (m > 0).any():
            raise InputError("the mask selects no pixel (all black): nothing to acquire from")
    if clipped is not None and clipped.any():
        keep = _resize(np.asarray(~clipped, np.float64), size, "clipped pixels", []) > 0.999
        if not keep.all():
            notes.append(
                f"{int((~keep).sum())} clipped pixels (at the format's largest value) left out"
            )
            m = (np.ones(target.shape[:2]) if m is None else m) * keep
    return target, m, notes


# ------------------------------------------------------------------ solve
def linear_photos(basis, names, target, mask):
    """``(LinearPhotos, images (N, H, W, 3), base, mask)`` of a photo of ``basis``'s scene: the
    training materials' images (full GI where the basis holds it, else L1-) at the masked pixels
    (default mask: :func:`~mitsuba_manifold.render.inverse.acquire.default_mask`).
    """
    from ...render.inverse.acquire import Rendered, default_mask

    full = "l2+" in basis.components
    keys = basis.material_keys(names)
    lacking = [n for n, k in zip(names, keys) if not basis.has(basis.gi_key(k) if full else k)]
    if lacking:
        raise InputError(
            f"basis {basis.folder} lacks the images of {len(lacking)} training materials "
            f"({', '.join(lacking[:5])}{' ...' if len(lacking) > 5 else ''}): acquisition needs "
            "every material's image (render the basis of all materials)"
        )
    images = np.stack([basis.image(basis.gi_key(k) if full else k) for k in keys])
    base = np.asarray(basis.image(BASE))
    mask = default_mask(Rendered(base, images, 0.0, True)) if mask is None else mask
    sel = mask > 0
    if not sel.any():
        raise InputError("no pixel of the photo shows the material (the mask is empty)")
    ys, xs = np.nonzero(sel)
    blocks = (ys // aq.CV_BLOCK) * 100000 + xs // aq.CV_BLOCK
    photos = aq.LinearPhotos(
        images[:, sel].reshape(len(keys), -1).T.astype(np.float64),
        base[sel].reshape(-1).astype(np.float64),
        np.asarray(target, np.float64)[sel].reshape(-1),
        np.repeat(blocks, 3),
        np.zeros(3 * len(ys), int),
    ).check()
    return photos, images, base, mask


def latent_search(manifold, photos, singles):
    """``(x, relative error)``: the latent point whose weights explain the photos best
    (L-BFGS on the data term ``w(x)^T H w(x) - 2 g^T w(x)``, analytic gradient through
    :meth:`~mitsuba_manifold.manifold.model.Manifold.weights_jacobian`), started from the
    :data:`LATENT_STARTS` measured materials with the smallest ``singles`` errors.
    """
    import scipy.optimize

    H, g, e0 = photos.normal_equations()

    def f(x):
        w = np.asarray(manifold.weights(x)[1], np.float64)
        J = np.asarray(manifold.weights_jacobian(x), np.float64)
        r = H @ w - g
        return float(w @ H @ w - 2 * g @ w + e0), 2.0 * (J.T @ r)

    best = (None, np.inf)
    lat = np.asarray(manifold.latent, np.float64)
    span = lat.max(axis=0) - lat.min(axis=0)
    bounds = list(zip(lat.min(axis=0) - span, lat.max(axis=0) + span))
    for i in np.argsort(singles)[:LATENT_STARTS]:
        res = scipy.optimize.minimize(
            f, lat[i], jac=True, method="L-BFGS-B", bounds=bounds, options={"maxiter": 200}
        )
        if res.fun < best[1]:
            best = (np.asarray(res.x, np.float64), float(res.fun))
    return best[0], float(np.sqrt(max(best[1], 0.0)))


def describe(names, w, top=6):
    """The acquired weights in words: ``"0.62 gold-paint + 0.31 steel"`` (largest first), and
    whether they leave the simplex (a negative weight or a sum away from 1) with why.
    """
    w = np.asarray(w, np.float64)
    order = [i for i in np.argsort(-np.abs(w)) if abs(w[i]) > 5e-3][:top]
    parts = []
    for k, i in enumerate(order):
        sign = "-" if w[i] < 0 else ("" if k == 0 else "+")
        parts.append(
            f"{sign} {abs(w[i]):.2f} {names[i]}".strip() if sign else f"{w[i]:.2f} {names[i]}"
        )
    rest = len([v for v in w if abs(v) > 5e-3]) - len(order)
    text = " ".join(parts) + (f" + {rest} more" if rest > 0 else "")
    why = []
    if (w < -SIMPLEX_TOLERANCE).any():
        why.append(f"{int((w < -SIMPLEX_TOLERANCE).sum())} negative weights")
    if abs(w.sum() - 1.0) > SUM_TOLERANCE:
        why.append(f"weights summing to {w.sum():.3f}")
    return text, why


def _tile(img, side):
    """``img`` enlarged (nearest pixel) to at least ``side`` pixels wide."""
    k = max(1, int(np.ceil(side / img.shape[1])))
    return np.repeat(np.repeat(img, k, axis=0), k, axis=1)


def contact_sheet(target, acquired, single, labels, title=None, exposure=0.0):
    """PNG bytes of ``target | acquired | best single`` with ``labels`` under each and ``title``
    above.
    """
    from ...imaging.io import write_contact_sheet

    fd, path = tempfile.mkstemp(suffix=".png", prefix="explore-sheet-")
    os.close(fd)
    try:
        write_contact_sheet(
            path,
            np.stack(
                [_tile(np.asarray(v, np.float32), SHEET_TILE) for v in (target, acquired, single)]
            ),
            labels=labels,
            columns=3,
            exposure=exposure,
            title=title,
        )
        with open(path, "rb") as f:
            return f.read()
    finally:
        os.unlink(path)


def acquire_photo(explorer, name, target, mask, notes, progress=lambda stage, done: None):
    """Acquire the material of a photo of basis ``name``'s scene: ``(answer, images)``.

    ``answer`` (JSON-ready): the :class:`~mitsuba_manifold.basis.inverse.acquisition.Acquisition`'s dict,
    ``description`` (the combination in words), ``beyond`` (why it leaves the simplex, or []),
    ``latent`` (``x``, its error, ``on_map``), ``snippet`` and ``notes``; ``images``: linear
    target, acquired, best single and the mask.
    """
    from ...render.inverse.acquire import constraints_of, coverage, coverage_warnings

    ex, t0 = explorer, time.perf_counter()
    basis, manifold, names = ex.basis(name), ex.manifold, list(ex.manifold.names)
    opts = aq.AcquireOptions(progress=False)
    progress("reading the basis's images", 0.02)
    photos, images, base, mask = linear_photos(basis, names, target, mask)
    progress("the plausibility constraints of the tables", 0.05)
    cons = constraints_of(manifold, ex.database)
    steps = [0, 2 * len(aq.CV_GRID) + opts.bootstrap + 2]

    def step():
        steps[0] += 1
        progress("solving", 0.1 + 0.7 * min(steps[0] / steps[1], 1.0))

    feasible, lam, scores = aq.choose(photos, cons, opts.method, seed=opts.seed, progress=step)
    db = manifold.open_database(ex.database) if feasible == "beyond" else None
    w, shrink, cons = aq.solve_programme(
        photos, cons, feasible, lam, lambda i: db.reflectance(names[i]), manifold.n
    )
    sp = aq.spread(photos, cons, feasible, lam, w, opts.bootstrap, opts.seed, progress=step)
    singles = [photos.relative_error(np.eye(manifold.n)[i]) for i in range(manifold.n)]
    best = int(np.argmin(singles))
    error = photos.relative_error(w)
    warnings, cov = [], {}
    scene = ex.scenes.get(ex.key(name))
    progress("coverage of the photo's directions", 0.82)
    if scene is not None:
        cov = coverage(scene, ex.manifold_path, basis.resolution, mask, basis.manifest.sensor_index)
        warnings += coverage_warnings([cov])
    else:
        warnings.append(
            "the basis's scene is missing: which directions the photo shows is unknown (start with --scene)"
        )
    warnings += aq.answer_warnings(sp, shrink, "this photo")
    progress("the nearest latent point", 0.86)
    x, x_error = latent_search(manifold, photos, singles)
    albedo = np.asarray(manifold.weights(x)[1], np.float64) @ cons.albedo
    plausible = bool(albedo.min() >= -ALBEDO_SLACK and albedo.max() <= 1 + ALBEDO_SLACK)
    on_map = plausible and x_error <= max(error * (1 + LATENT_TOLERANCE), error + LATENT_ABSOLUTE)
    text, beyond = describe(names, w)
    result = aq.Acquisition(
        names=names,
        w=[float(v) for v in w],
        method=opts.method,
        error=float(error),
        single={"name": names[best], "error": float(singles[best])},
        x=[float(v) for v in x] if on_map else None,
        feasible=feasible,
        regularisation=float(lam),
        cross_validation={k: [list(v) for v in sc] for k, sc in scores.items()},
        coverage={"views": [cov]} if cov else {},
        spread=sp.__dict__,
        warnings=warnings,
        views=[{"scene": scene, "basis": basis.folder, "target": None, "mask": None, "sensor": 0}],
        manifold=ex.manifold_path,
    )
    progress("the acquired material in the scene", 0.9)
    acquired, info = blend(basis, manifold, w=w, prune=0.0)
    single, _ = blend(basis, manifold, w=np.eye(manifold.n)[best], prune=0.0)
    result.time_s = time.perf_counter() - t0
    answer = dict(
        result.to_dict(),
        description=text,
        beyond=beyond,
        latent={
            "x": [float(v) for v in x],
            "error": x_error,
            "on_map": bool(on_map),
            "plausible": plausible,
        },
        snippet=result.snippet(),
        notes=notes,
        model="full GI images (cross terms left out of the solve, in the blend shown)"
        if "l2+" in basis.components
        else "L1- images",
        blend=info.component,
        pixels=int((mask > 0).sum()),
        basis=ex.key(name),
    )
    return answer, {"target": target, "acquired": acquired, "single": single, "mask": mask}


# ------------------------------------------------------------------ jobs
class Job:
    """One acquisition: its state (``queued``, ``running``, ``done``, ``failed``), progress and answer."""

    def __init__(self, job_id, basis):
        self.id, self.basis = job_id, basis
        self.state, self.stage, self.progress, self.message = "queued", "waiting", 0.0, ""
        self.answer, self.images, self.sheet = None, None, None
        self.started = time.time()

    def status(self):
        out = {
            "id": self.id,
            "state": self.state,
            "stage": self.stage,
            "progress": round(self.progress, 3),
            "message": self.message,
            "basis": self.basis,
        }
        if self.state == "done":
            out["result"] = self.answer
        return out


class Acquisitions:
    """The explorer's acquisitions: one runs at a time in a background thread (a second is
    refused with :class:`BusyError` while one waits or runs), the last :data:`JOBS_KEPT` kept.
    """

    def __init__(self):
        self._jobs, self._lock, self._count = {}, threading.Lock(), 0
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="explore-acquire")

    def submit(self, explorer, name, target, mask, notes):
        with self._lock:
            if any(j.state in ("queued", "running") for j in self._jobs.values()):
                raise BusyError("an acquisition is running; wait for it to finish")
            self._count += 1
            job = Job(f"a{self._count}", name)
            self._jobs[job.id] = job
            for old in list(self._jobs)[:-JOBS_KEPT]:
                self._jobs.pop(old)
        self._pool.submit(self._run, job, explorer, name, target, mask, notes)
        return job

    def _run(self, job, explorer, name, target, mask, notes):
        def progress(stage, done):
            job.stage, job.progress = stage, done

        job.state = "running"
        try:
            with one_thread():  # the page's frames keep the other cores
                answer, images = acquire_photo(explorer, name, target, mask, notes, progress)
            labels = [
                "photo",
                f"acquired (rel. error {answer['error']:.3f})",
                f"best single: {answer['single']['name']} ({answer['single']['error']:.3f})",
            ]
            title = "acquired: " + answer["description"]
            if answer["beyond"]:
                title += " (beyond the manifold: " + ", ".join(answer["beyond"]) + ")"
            job.sheet = contact_sheet(
                images["target"], images["acquired"], images["single"], labels, title
            )
            job.answer, job.images = answer, images
            job.stage, job.progress, job.state = "done", 1.0, "done"
        except MitsubaManifoldError as e:
            job.message, job.state = str(e).splitlines()[0], "failed"
        except Exception as e:  # a bug: one line to the page, the traceback to the console
            traceback.print_exc()
            job.message, job.state = (
                f"internal error ({type(e).__name__}: {e})".splitlines()[0],
                "failed",
            )

    def get(self, job_id):
        with self._lock:
            return self._jobs.get(job_id)

    def image(self, job_id, which, exposure=0.0):
        """PNG bytes of image ``which`` (:data:`IMAGES`) of a finished job."""
        job = self.get(job_id)
        if job is None:
            raise InputError(f"unknown acquisition {show(job_id)}")
        if job.state != "done":
            raise InputError(f"acquisition {job_id} is {job.state}, not done")
        if which not in IMAGES:
            raise InputError(f"image must be one of {', '.join(IMAGES)}, got {show(which)}")
        if which == "sheet":
            return job.sheet
        img = job.images[which]
        if which == "mask":
            return encode.png_bytes(np.repeat((255 * img[..., None]).astype(np.uint8), 3, axis=-1))
        return encode.png_bytes(encode.tonemap(np.asarray(img, np.float32), exposure))

    def close(self):
        self._pool.shutdown(wait=False, cancel_futures=True)
