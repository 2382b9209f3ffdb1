"""A path tracer that renders the part of an image that is affine in one material.

The paper's Sec. 5.2 splits the light reaching the camera by how many times it
scattered off the material being edited (the *target*, a ``manifold_brdf``):
``L = L1- + L2+``, where ``L1-`` (paths scattering off the target at most once) is
affine in the target's BRDF. Since a manifold material is an affine combination
``sum_i w_i rho_i`` of measured BRDFs with ``sum_i w_i = 1``, the ``L1-`` image of any
latent point is ``base + sum_i w_i touch_i``: ``base`` holds the paths that never
scatter off the target (the same for every material), ``touch_i`` the paths that
scatter off it exactly once, rendered with training material ``i``.

:func:`register` makes the integrator ``manifold_path`` available to Mitsuba for the
active variant. Its parameters, components and outputs are documented on the class
made by :func:`integrator_class`; its method ``render_onepass`` renders ``base`` and the
touch images of many materials from one set of paths (the material enters a once-touching
path at one vertex only, so that vertex is recorded and every table evaluated there).
"""

import hashlib
import os
import threading

import drjit as dr
import mitsuba as mi
import numpy as np

from . import merl

#: Values of the ``component`` parameter besides ``touch:<id>+<id>...``.
COMPONENTS = ("full", "l1", "base", "touch", "rest")
#: Most target groups (the number of path classes grows as 2 ** groups).
MAX_GROUPS = 4


def is_manifold_bsdf(bsdf):
    """True when ``bsdf`` is a manifold material (an instance flagged ``is_manifold_brdf``)."""
    return bsdf is not None and bool(getattr(bsdf, "is_manifold_brdf", False))


def manifold_bsdfs(scene):
    """The distinct manifold BSDF instances of ``scene``, in the order of ``scene.shapes()``."""
    found = []
    for shape in scene.shapes():
        bsdf = shape.bsdf()
        if is_manifold_bsdf(bsdf) and not any(bsdf is b for b in found):
            found.append(bsdf)
    return found


def target_groups(scene, target="all"):
    """Resolve the ``target`` parameter against ``scene``.

    Parameters
    ----------
    scene : mi.Scene
    target : str
        ``"all"``: every manifold BSDF of the scene counts as one material (one group);
        ``"each"``: one group per manifold BSDF; otherwise a comma-separated list of
        BSDF ids, one group per id.

    Returns
    -------
    list of (str, list of mi.BSDF)
        One ``(name, bsdfs)`` pair per group.

    Raises
    ------
    ValueError
        If the scene holds no manifold BSDF, an id is unknown or not a manifold
        BSDF, an id is repeated, or there are more than :data:`MAX_GROUPS` groups.
    """
    found = manifold_bsdfs(scene)
    if not found:
        raise ValueError(
            "manifold_path: the scene has no manifold material (no shape uses a "
            "'manifold_brdf' BSDF); the L1- split needs one. Give the material to edit "
            "type=\"manifold_brdf\", or render with component=\"full\".")
    target = str(target).strip()
    if target == "all":
        groups = [("touch", found)]
    elif target == "each":
        groups = [(b.id(), [b]) for b in found]
    else:
        ids = [s.strip() for s in target.split(",") if s.strip()]
        if not ids:
            raise ValueError("manifold_path: target is empty; use 'all', 'each' or BSDF ids")
        if len(set(ids)) != len(ids):
            raise ValueError(f"manifold_path: target {target!r} names a BSDF twice")
        by_id = {b.id(): b for b in found}
        groups = []
        for i in ids:
            if i not in by_id:
                others = [s.bsdf().id() for s in scene.shapes() if s.bsdf() is not None]
                kind = ("is not a manifold_brdf" if i in others else "is not in the scene")
                raise ValueError(
                    f"manifold_path: target BSDF {i!r} {kind}; manifold BSDFs of the "
                    f"scene: {sorted(by_id)}")
            groups.append((i, [by_id[i]]))
    if len(groups) > MAX_GROUPS:
        raise ValueError(
            f"manifold_path: {len(groups)} target groups, at most {MAX_GROUPS} are "
            "supported; use target='all' or name the BSDFs to edit")
    return groups


def class_names(group_names):
    """Names of the path classes for the given group names.

    Class ``m`` (``0 <= m < 2 ** len(group_names)``) holds the paths that scattered off
    exactly the groups whose bits are set in ``m``, each once: ``"base"`` for ``m = 0``,
    ``"touch"`` for the single group when there is one, ``"touch:a+b"`` otherwise.
    The last class, ``"rest"``, holds the paths that scattered twice or more off a group
    (``L2+``).
    """
    p = len(group_names)
    names = []
    for m in range(1 << p):
        if m == 0:
            names.append("base")
        elif p == 1:
            names.append("touch")
        else:
            names.append("touch:" + "+".join(group_names[g] for g in range(p) if m >> g & 1))
    names.append("rest")
    return names


def _power_heuristic(pdf_a, pdf_b):
    a2, b2 = dr.square(pdf_a), dr.square(pdf_b)
    w = a2 / (a2 + b2)
    return dr.select(dr.isfinite(w), w, 0)


#: Materials per packet of the table product (Dr.Jit packet gathers of 16 contiguous floats).
_PACKET = 16
#: Most bytes of per-pixel sums one table kernel holds (Expand mode keeps a copy per thread).
_SUM_BYTES = 1 << 28
_NO_BIN = 0xFFFFFFFF


def _prefetch(path, block=1 << 24):
    """Read ``path`` in a background thread, so that it is in the page cache when needed."""
    def run():
        try:
            buf = bytearray(block)
            with open(path, "rb", buffering=0) as f:
                while f.readinto(buf):
                    pass
        except OSError:
            pass
    threading.Thread(target=run, daemon=True).start()


def _mixture_table(db, rows, mix, keep=2):
    """``sum_k mix_k table_k`` from the interleaved tables ``rows``, as ``(bins, 3)`` float32.

    Cached beside ``rows`` (keyed by them and the weights; the ``keep`` newest kept), so
    that a later render need not read every table before it starts tracing.
    """
    key = os.path.basename(rows.filename).split(".")[0]
    digest = hashlib.sha256(np.asarray(mix, dtype=np.float64).tobytes()).hexdigest()[:16]
    path = os.path.join(db.cache_dir, f"{key}.mixture-v1-{digest}.npy")
    shape = (rows.shape[0], 3)
    try:
        table = np.load(path)
        if table.shape == shape and table.dtype == np.float32 and np.isfinite(table).all():
            os.utime(path)
            return table
    except (OSError, ValueError):
        pass
    w = np.zeros(rows.shape[2], dtype=np.float32)
    w[:len(mix)] = mix
    table = (np.asarray(rows).reshape(-1, rows.shape[2]) @ w).reshape(shape)
    merl.atomic_write(path, lambda f: np.save(f, table))
    db.evict(".mixture-v1-", keep)
    return table


def _splat_rows(sums, splats, pixel, rows, row_packets, kb0, kb1):
    """Add ``a * max(rows[bin], 0)`` of every splat to its pixel's sums, for material packets
    ``kb0 .. kb1 - 1``.

    ``splats`` holds ``(bin bits, a.r, a.g, a.b)`` per splat and ``pixel`` its row of
    ``sums`` (laid out ``(pixels, 3, (kb1 - kb0) * _PACKET)``); ``rows`` is the flat
    ``(bins, 3, row_packets * _PACKET)`` table. One lane per splat and packet: a packet
    gather from the table, a packet scatter-add into a per-thread copy of ``sums``.
    """
    nb = kb1 - kb0
    lane = dr.arange(mi.UInt32, dr.width(pixel) * nb)
    s = lane // nb
    kb = lane - s * nb
    data = dr.gather(mi.Vector4f, splats, s)
    b = dr.reinterpret_array(mi.UInt32, data.x)
    q = dr.gather(mi.UInt32, pixel, s)
    threshold = dr.expand_threshold()
    dr.set_expand_threshold(max(threshold, dr.width(sums)))
    try:
        for c in range(3):
            t = dr.gather(mi.ArrayXf, rows, (b * 3 + c) * row_packets + kb0 + kb,
                          shape=(_PACKET, dr.width(lane)))
            dr.scatter_add(sums, dr.maximum(t, 0.0) * data[c + 1], (q * 3 + c) * nb + kb,
                           mode=dr.ReduceMode.Expand)
        dr.eval(sums)
    finally:
        dr.set_expand_threshold(threshold)


class _TableSplats:
    """The splats of :meth:`render_onepass` as per-pixel sums ``sum a * table(bin)`` of every
    material: nearest lookups, box filter (each sample lands in one pixel).

    Sums are kept per chunk of materials, laid out ``(pixels, 3, materials padded to
    _PACKET)``. When a chunk's sums of the whole image, copied once per thread, exceed
    ``_SUM_BYTES``, the splats are processed in tiles of pixels into smaller sums first.
    """

    def __init__(self, block, rows, names, chunks, dims):
        self.block, self.names, self.dims = block, names, dims
        self.n_pad = int(rows.shape[2])
        self.rows = mi.Float(np.asarray(rows).reshape(-1))  # maps the cached file, no copy
        self.pixels = int(dr.prod(block.size()))
        self.packets = [(k0 // _PACKET, -(-k1 // _PACKET)) for k0, k1 in chunks]
        self.chunks = chunks
        self.sums = [dr.zeros(mi.Float, self.pixels * 3 * (b1 - b0) * _PACKET) for b0, b1 in self.packets]
        widest = max(b1 - b0 for b0, b1 in self.packets) * _PACKET
        self.tile = max(1, _SUM_BYTES // (12 * widest * max(1, dr.thread_count())))
        self.tiles = []

    def prepare(self, rec, beta, pos):
        """Turn one pass's records into splats, sorted by bin within tiles of pixels."""
        from .bsdf import merl_angles, merl_bin
        size, offset = self.block.size(), self.block.offset()
        x = mi.Int32(dr.floor(pos.x)) - offset.x
        y = mi.Int32(dr.floor(pos.y)) - offset.y
        pixel = mi.UInt32(y * size.x + x)
        keys, amps = [], []
        for wo, a in ((rec["wo_nee"], rec["e_nee"]), (rec["wo"], rec["g"])):
            a = beta * a * wo.z
            ok = (rec["wi"].z > 0) & (wo.z > 0) & dr.any(a != 0)
            keys.append(dr.select(ok, merl_bin(*merl_angles(rec["wi"], wo), self.dims), _NO_BIN))
            amps.append(a)
        dr.eval(self.block.tensor(), pixel, keys, amps)
        # Both splats of every sample in sample order (so in pixel order), compacted.
        j = dr.arange(mi.UInt32, 2 * dr.width(pixel))
        key = dr.select((j & 1) != 0, dr.gather(mi.UInt32, keys[1], j >> 1),
                        dr.gather(mi.UInt32, keys[0], j >> 1))
        idx = dr.compress(key != _NO_BIN)
        self.tiles = []
        if dr.width(idx) == 0:
            return
        second = (idx & 1) != 0
        amp = dr.select(second, dr.gather(mi.Color3f, amps[1], idx >> 1),
                        dr.gather(mi.Color3f, amps[0], idx >> 1))
        key = dr.gather(mi.UInt32, key, idx)
        pix = dr.gather(mi.UInt32, pixel, idx >> 1)
        dr.eval(key, amp, pix)
        # Sorted by bin within each tile (a stable 16-bit radix sort of the bins' leading
        # bits is enough to read the tables in order).
        shift = max(0, (int(np.prod(self.dims)) - 1).bit_length() - 16)
        short = (key.numpy() >> shift).astype(np.uint16)
        pix_np = pix.numpy()
        starts = np.arange(0, self.pixels, self.tile)
        bounds = np.searchsorted(pix_np, np.append(starts, self.pixels))
        for p0, lo, hi in zip(starts, bounds[:-1], bounds[1:]):
            if hi == lo:
                continue
            order = mi.UInt32(lo + np.argsort(short[lo:hi], kind="stable").astype(np.uint32))
            a = dr.gather(mi.Color3f, amp, order)
            splats = mi.Vector4f(dr.reinterpret_array(mi.Float, dr.gather(mi.UInt32, key, order)),
                                 a.x, a.y, a.z)
            splats = dr.ravel(splats)  # (bin, r, g, b) per splat, contiguous
            local = dr.gather(mi.UInt32, pix, order) - int(p0)
            dr.eval(splats, local)
            self.tiles.append((int(p0), min(self.pixels, int(p0) + self.tile), splats, local))

    def add(self, c):
        """Add the splats of the prepared pass to the sums of chunk ``c``'s materials."""
        kb0, kb1 = self.packets[c]
        width = 3 * (kb1 - kb0) * _PACKET
        for p0, p1, splats, local in self.tiles:
            if p1 - p0 == self.pixels:
                _splat_rows(self.sums[c], splats, local, self.rows, self.n_pad // _PACKET, kb0, kb1)
            else:
                part = dr.zeros(mi.Float, (p1 - p0) * width)
                _splat_rows(part, splats, local, self.rows, self.n_pad // _PACKET, kb0, kb1)
                i = dr.arange(mi.UInt32, dr.width(part))
                dr.scatter_add(self.sums[c], part, i + p0 * width, mode=dr.ReduceMode.NoConflicts)
                dr.eval(self.sums[c])

    def release(self):
        self.tiles = []

    def images(self, film):
        """Each material's sums divided by the filter weights of all samples."""
        block = np.array(self.block.tensor())
        weight = block[..., -1].reshape(-1)
        scale = mi.Float(np.where(weight > 0, 1.0 / np.where(weight > 0, weight, 1.0), 0.0))
        shape = block.shape[:2] + (3,)
        images = {}
        for (k0, k1), (kb0, kb1), sums in zip(self.chunks, self.packets, self.sums):
            # (pixels, 3, packets) -> (materials, pixels, 3), scaled
            width = (kb1 - kb0) * _PACKET
            lane = dr.arange(mi.UInt32, (k1 - k0) * self.pixels * 3)
            k = lane // (self.pixels * 3)
            r = lane - k * (self.pixels * 3)
            p = r // 3
            out = dr.gather(mi.Float, sums, r * width + k + (k0 - kb0 * _PACKET)) * dr.gather(mi.Float, scale, p)
            out = out.numpy().reshape((k1 - k0,) + shape)
            for k, name in enumerate(self.names[k0:k1]):
                images[name] = out[k]
        return images


class _FilterSplats:
    """The splats of :meth:`render_onepass` put into image blocks with the film's filter,
    each material evaluated at them (``nearest``: one gather from its table; ``linear``: the
    BSDF's own ``eval``)."""

    def __init__(self, film, block, names, chunks, db, path, options, several_passes):
        self.film, self.block, self.names, self.chunks = film, block, names, chunks
        self.db, self.path, self.options = db, path, options
        self.dims = tuple(int(d) for d in db.dims)
        bins = int(np.prod(self.dims))
        self.nearest = options["interpolation"] == "nearest"
        self.blocks = [mi.ImageBlock(block.size(), block.offset(), 3 * (k1 - k0), film.rfilter(),
                                     border=block.has_border(), normalize=block.normalize(),
                                     coalesce=block.coalesce()) for k0, k1 in chunks]
        self.cache = {}  # chunk index -> tables (nearest) or BSDFs (linear)
        self.keep = several_passes and len(names) * bins * 12 <= (1 << 31)
        if self.nearest:  # planar (RGB, bins) -> interleaved (bins, RGB)
            i = dr.arange(mi.UInt32, 3 * bins)
            self.interleave = (i % 3) * bins + i // 3
        self.splats = []

    def _data(self, c):
        if c in self.cache:
            return self.cache[c]
        k0, k1 = self.chunks[c]
        if self.nearest:  # each table as (bins, RGB), clamped at 0 as the BSDF does
            data = [dr.maximum(dr.gather(mi.Float, mi.Float(np.ascontiguousarray(
                self.db.reflectance(n), np.float32).reshape(-1)), self.interleave), 0.0)
                for n in self.names[k0:k1]]
            dr.eval(data)
        else:
            data = [mi.load_dict({"type": "manifold_brdf", "manifold": self.path, "material": n,
                                  "sampling": "cosine", **self.options}) for n in self.names[k0:k1]]
        if self.keep:
            self.cache[c] = data
        return data

    def prepare(self, rec, beta, pos):
        """Two splat sets (light connection, sampled direction), compacted, sorted by bin."""
        from .bsdf import merl_angles, merl_bin
        dr.eval(self.block.tensor(), beta, rec, pos)
        self.splats = []
        for wo, a in ((rec["wo_nee"], rec["e_nee"]), (rec["wo"], rec["g"])):
            a = beta * a * wo.z
            ok = (rec["wi"].z > 0) & (wo.z > 0) & dr.any(a != 0)
            key = merl_bin(*merl_angles(rec["wi"], wo), self.dims)
            key = np.array(dr.select(ok, key, _NO_BIN), dtype=np.uint32)
            order = np.argsort(key, kind="stable")[:int(np.count_nonzero(key != _NO_BIN))]
            if order.size == 0:
                continue
            idx = mi.UInt32(order.astype(np.uint32))
            pick = lambda v: dr.gather(type(v), v, idx)  # noqa: E731
            splat = dict(pos=pick(pos), a=pick(a), bin=mi.UInt32(key[order]))
            if not self.nearest:  # the BSDF's own lookup; eval returns f cos: undo cos
                splat["si"] = dr.zeros(mi.SurfaceInteraction3f, order.size)
                splat["si"].wi = pick(rec["wi"])
                splat["wo"] = pick(wo)
                splat["a"] = splat["a"] / splat["wo"].z
            dr.eval(splat)
            self.splats.append(splat)

    def add(self, c):
        if not self.splats:
            return
        data, block, ctx = self._data(c), self.blocks[c], mi.BSDFContext()
        for splat in self.splats:
            values = []
            for table in data:
                if self.nearest:
                    v = dr.gather(mi.Color3f, table, splat["bin"]) * splat["a"]
                else:
                    v = table.eval(ctx, splat["si"], splat["wo"]) * splat["a"]
                values += [v.x, v.y, v.z]
            block.put(splat["pos"], values)
            dr.eval(block.tensor())

    def release(self):
        self.splats = []

    def images(self, film):
        """Develop as the film does: the material channels as AOVs of the base block,
        normalised by the filter weights of all samples."""
        head = np.array(self.block.tensor())
        images = {}
        for (k0, k1), block in zip(self.chunks, self.blocks):
            aovs = [f"m{k}.{c}" for k in range(k1 - k0) for c in "RGB"]
            film.prepare(aovs)
            merged = np.concatenate([head, np.array(block.tensor())], axis=-1)
            film.put_block(mi.ImageBlock(mi.TensorXf(merged), self.block.offset(), film.rfilter(),
                                         border=self.block.has_border(),
                                         normalize=self.block.normalize(),
                                         coalesce=self.block.coalesce()))
            img = np.array(film.develop(), dtype=np.float32)
            start = img.shape[-1] - len(aovs)
            for k, name in enumerate(self.names[k0:k1]):
                images[name] = img[..., start + 3 * k:start + 3 * k + 3].copy()
        return images


def _make_class():
    """Build the integrator class for the active variant (its base class depends on it)."""

    class ManifoldPathIntegrator(mi.SamplingIntegrator):
        r"""Path tracer splitting radiance by the number of scatterings off a manifold material.

        Unidirectional path tracing with next-event estimation, multiple importance
        sampling (power heuristic) and Russian roulette, as Mitsuba's ``path``. Each path
        carries the set of target groups it has scattered off. A contribution (emission
        found by a BSDF sample, or a light connection) is sorted into a *class*: the set of
        target groups that the scattering vertices before it lie on, each touched once, or
        ``rest`` as soon as a group was touched twice. In the ``L1-`` components a path
        ends at its second scattering vertex on a group: the emission found there is still
        counted (it belongs to the light connection of the previous vertex under MIS), the
        light connection made there and everything after are not.

        Parameters (plugin properties)
        ------------------------------
        max_depth : int
            Longest path depth, as in ``path`` (-1: unbounded). Default -1.
        rr_depth : int
            Depth at which Russian roulette starts. Default 5.
        hide_emitters : bool
            Hide directly visible emitters. Default false.
        component : str
            What the image holds: ``"full"`` (all paths, as ``path``), ``"l1"`` (paths
            scattering off each target group at most once), ``"base"`` (never),
            ``"touch"`` (exactly once off every group; with one group: exactly once),
            ``"touch:id1+id2"`` (exactly once off the named groups, never off the others;
            several groups only), ``"rest"`` (``L2+``: twice or more off some group).
            Default ``"l1"``.
        target : str
            Which manifold BSDFs are "the material": ``"all"`` (default, every
            ``manifold_brdf`` of the scene, as one group), ``"each"`` (one group each, for
            multilinear blends) or comma-separated BSDF ids (one group each).
        split : bool
            Also return every class as an AOV (``base.R`` ... ``touch.R`` ..., and
            ``rest.*`` when the component is ``full``), all from the same paths. Class
            names with ``:`` become ``_`` in channel names. Default false.

        Rendering a scene without a manifold BSDF raises ``ValueError``, except with
        ``component="full"`` and ``split`` false (``render`` raises it directly;
        ``mi.render`` wraps it). :meth:`render_onepass` renders the base image and the
        touch images of many materials of one target from one set of paths.
        """

        def __init__(self, props):
            super().__init__(props)
            max_depth = props.get("max_depth", -1)
            if max_depth < -1:
                raise ValueError(f"manifold_path: max_depth must be -1 (unbounded) or >= 0, got {max_depth}")
            self.max_depth = max_depth if max_depth != -1 else 0xFFFFFFFF
            self.rr_depth = props.get("rr_depth", 5)
            if self.rr_depth <= 0:
                raise ValueError(f"manifold_path: rr_depth must be > 0, got {self.rr_depth}")
            self.component = str(props.get("component", "l1")).strip()
            if self.component not in COMPONENTS and not self.component.startswith("touch:"):
                raise ValueError(
                    f"manifold_path: unknown component {self.component!r}; expected one of "
                    f"{', '.join(COMPONENTS)} or 'touch:<id>+<id>'")
            self.target = str(props.get("target", "all"))
            self.split = bool(props.get("split", False))
            self._names = None  # class names of the last scene rendered (for aov_names)

        # ------------------------------------------------------------ set-up

        def needs_targets(self):
            """Whether rendering needs the scene's manifold BSDFs."""
            return self.component != "full" or self.split

        def plan(self, scene):
            """Resolve targets and component for ``scene``.

            Returns
            -------
            dict
                ``groups`` (list of ``(name, bsdfs)``), ``names`` (class names),
                ``select`` (bit set over classes summed into the image), ``keep``
                (bit set over classes a path may still be in while worth tracing),
                ``aovs`` (class indices written as AOVs).
            """
            groups = target_groups(scene, self.target) if self.needs_targets() else []
            names = class_names([g[0] for g in groups])
            n_sub = 1 << len(groups)
            rest = n_sub
            comp = self.component
            if comp == "full":
                select = (1 << (n_sub + 1)) - 1
            elif comp == "l1":
                select = (1 << n_sub) - 1
            elif comp == "base":
                select = 1
            elif comp == "rest":
                select = 1 << rest
            elif comp == "touch":
                select = 1 << (n_sub - 1)
            else:
                if len(groups) < 2:
                    raise ValueError(
                        f"manifold_path: component {comp!r} names groups, but the target "
                        f"{self.target!r} makes one group; use component='touch'")
                wanted = [s.strip() for s in comp[len("touch:"):].split("+")]
                gnames = [g[0] for g in groups]
                bad = [w for w in wanted if w not in gnames]
                if bad or len(set(wanted)) != len(wanted) or not wanted:
                    raise ValueError(
                        f"manifold_path: component {comp!r} must name distinct target "
                        f"groups among {gnames}")
                select = 1 << sum(1 << gnames.index(w) for w in wanted)
            aovs = []
            if self.split:
                aovs = list(range(n_sub)) + ([rest] if comp == "full" else [])
            need = select
            for c in aovs:
                need |= 1 << c
            keep = 0
            for c in range(n_sub):  # class c can still reach any superset of c, or rest
                if any(need >> d & 1 for d in range(n_sub) if d & c == c) or need >> rest & 1:
                    keep |= 1 << c
            if need >> rest & 1:
                keep |= 1 << rest
            return dict(groups=groups, names=names, select=select, keep=keep, aovs=aovs)

        def aov_names(self):
            if not self.split:
                return []
            if self._names is None:
                raise RuntimeError(
                    "manifold_path: the AOV names of split=true depend on the scene; call "
                    "integrator.prepare_scene(scene) (or render once) before asking for them")
            out = []
            for c in self._aov_classes:
                base = self._names[c].replace(":", "_")
                out += [base + ".R", base + ".G", base + ".B"]
            return out

        def prepare_scene(self, scene):
            """Resolve the targets of ``scene`` now (raises on a scene it cannot split)."""
            plan = self.plan(scene)
            self._names = plan["names"]
            self._aov_classes = plan["aovs"]
            return plan

        def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
            # The film's channels come from aov_names(), which needs the scene: resolve first.
            self.prepare_scene(scene)
            return super().render(scene, sensor, seed, spp, develop, evaluate)

        # ------------------------------------------------------------ tracing

        def sample(self, scene, sampler, ray, medium=None, active=True):
            plan = self.prepare_scene(scene)
            L, valid, parts, _ = self._trace(scene, sampler, ray, active, plan, False)
            aovs = []
            for part in parts:
                aovs += [part.x, part.y, part.z]
            return L, valid, aovs

        @dr.syntax
        def _trace(self, scene, sampler, ray, active, plan, record, proxy=None):
            """Trace paths; return the selected radiance, validity, AOV parts and records.

            With ``record`` (one target group, for :meth:`render_onepass`), the image holds
            the ``base`` class only, and the path's single vertex on the target is recorded
            instead of evaluated (there the BSDF ``proxy`` is sampled in place of the
            target's, with pdf ``q``): the throughput before it (``beta``), the local
            incident direction (``wi``), the light connection made there (direction
            ``wo_nee``; ``e_nee`` = emitted radiance / light pdf, visibility and the MIS
            weight against ``q`` included), and the sampled direction ``wo`` with ``g`` =
            (radiance that came back along it, MIS-weighted emission included) / ``q``.
            A material whose ``eval`` (``f cos``) is ``f`` then adds
            ``beta * (f(wi, wo_nee) e_nee + f(wi, wo) g)``: the same estimator as
            rendering it alone, except that directions come from ``q``.
            """
            groups, select, keep = plan["groups"], plan["select"], plan["keep"]
            n_sub = 1 << len(groups)
            rest = mi.UInt32(n_sub)
            track = len(groups) > 0
            aov_classes = plan["aovs"]

            bsdf_ctx = mi.BSDFContext()
            ray = mi.Ray3f(ray)
            depth = mi.UInt32(0)
            beta = mi.Spectrum(1)
            eta = mi.Float(1)
            active = mi.Bool(active)
            L = mi.Spectrum(0)
            parts = [mi.Spectrum(0) for _ in aov_classes]
            # Class of the scattering vertices so far: bit g set = group g touched once;
            # the value n_sub = rest (some group touched twice).
            cls = mi.UInt32(0)
            prev_si = dr.zeros(mi.SurfaceInteraction3f)
            prev_bsdf_pdf = mi.Float(1)
            prev_bsdf_delta = mi.Bool(True)
            # Records of the touch vertex (record mode): after it, beta is the throughput
            # relative to the sampled direction, and rr_scale the throughput up to there.
            rec_beta = mi.Spectrum(0) if record else None
            rec_wi = mi.Vector3f(0, 0, 1) if record else None
            rec_wo_nee = mi.Vector3f(0, 0, 1) if record else None
            rec_e_nee = mi.Spectrum(0) if record else None
            rec_wo = mi.Vector3f(0, 0, 1) if record else None
            rec_inv_pdf = mi.Float(0) if record else None
            L_after = mi.Spectrum(0) if record else None
            rr_scale = mi.Float(1) if record else None

            if dr.hint(self.hide_emitters, mode="scalar"):
                # As Mitsuba's path tracers: camera rays pass through area emitters.
                skip = mi.Bool(active)
                while dr.hint(skip, label="manifold_path_skip_emitters"):
                    si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.Minimal,
                                             coherent=True, active=skip)
                    skip &= si.is_valid() & (si.shape.emitter() != None)  # noqa: E711
                    ray[skip] = si.spawn_ray(ray.d)

            while dr.hint(active, label="manifold_path"):
                si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All,
                                         coherent=(depth == 0), active=active)
                bsdf = si.bsdf(ray)

                # --- Emission found by the previous BSDF sample (class of the vertices before)
                ds = mi.DirectionSample3f(scene, si=si, ref=prev_si)
                em_pdf = scene.pdf_emitter_direction(prev_si, ds, ~prev_bsdf_delta)
                mis_bsdf = _power_heuristic(prev_bsdf_pdf, em_pdf)
                visible = mi.Bool(active)
                if dr.hint(self.hide_emitters, mode="scalar"):
                    visible &= depth > 0
                Le = beta * mis_bsdf * ds.emitter.eval(si, visible)
                L += dr.select((mi.UInt32(select) >> cls) & 1 != 0, Le, 0)
                for k in range(len(aov_classes)):
                    parts[k] += dr.select(cls == aov_classes[k], Le, 0)
                if dr.hint(record, mode="scalar"):
                    L_after += dr.select(cls == 1, Le, 0)

                # --- Class after scattering here
                cls_before = mi.UInt32(cls)
                if dr.hint(track, mode="scalar"):
                    hit = mi.UInt32(0)
                    for g in range(len(groups)):
                        for b in groups[g][1]:
                            hit |= dr.select(bsdf == mi.BSDFPtr(b), mi.UInt32(1 << g), 0)
                    again = (hit & cls) != 0
                    cls = dr.select((cls == rest) | again, rest, cls | hit)
                if dr.hint(record, mode="scalar"):
                    # On the target, sample (and weigh the light connection) with the
                    # density that covers every material.
                    bsdf = dr.select(hit != 0, mi.BSDFPtr(proxy), bsdf)

                active_next = (active & si.is_valid() & (depth + 1 < self.max_depth)
                               & ((mi.UInt32(keep) >> cls) & 1 != 0))

                # --- Light connection (next-event estimation)
                active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
                ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), True, active_em)
                active_em &= ds.pdf != 0
                wo = si.to_local(ds.d)
                bsdf_val, bsdf_pdf = bsdf.eval_pdf(bsdf_ctx, si, wo, active_em)
                mis_em = dr.select(ds.delta, 1, _power_heuristic(ds.pdf, bsdf_pdf))
                Lr = dr.select(active_em, beta * mis_em * bsdf_val * em_weight, 0)
                L += dr.select((mi.UInt32(select) >> cls) & 1 != 0, Lr, 0)
                for k in range(len(aov_classes)):
                    parts[k] += dr.select(cls == aov_classes[k], Lr, 0)
                if dr.hint(record, mode="scalar"):
                    first = active & (cls_before == 0) & (cls == 1)
                    L_after += dr.select((cls == 1) & ~first, Lr, 0)
                    rec_beta = dr.select(first, beta, rec_beta)
                    rec_wi = dr.select(first, si.wi, rec_wi)
                    rec_wo_nee = dr.select(first, wo, rec_wo_nee)
                    rec_e_nee = dr.select(first & active_em, mis_em * em_weight, rec_e_nee)

                # --- BSDF sampling
                bs, bsdf_weight = bsdf.sample(bsdf_ctx, si, sampler.next_1d(),
                                              sampler.next_2d(), active_next)
                ray = si.spawn_ray(si.to_world(bs.wo))
                eta *= bs.eta
                beta_full = beta * bsdf_weight
                if dr.hint(record, mode="scalar"):
                    ok = first & active_next & (bs.pdf > 0)
                    rec_wo = dr.select(first, bs.wo, rec_wo)
                    rec_inv_pdf = dr.select(ok, dr.rcp(bs.pdf), rec_inv_pdf)
                    rr_scale = dr.select(first, dr.max(mi.unpolarized_spectrum(beta_full)), rr_scale)
                    beta = dr.select(first, dr.select(ok, 1.0, 0.0), beta_full)
                else:
                    beta = beta_full
                prev_si = dr.detach(si, True)
                prev_bsdf_pdf = bs.pdf
                prev_bsdf_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)

                # --- Russian roulette
                beta_max = dr.max(mi.unpolarized_spectrum(beta))
                active_next &= beta_max != 0
                if dr.hint(record, mode="scalar"):
                    beta_max = dr.select(cls == 1, beta_max * rr_scale, beta_max)
                rr_prob = dr.minimum(beta_max * dr.square(eta), 0.95)
                rr_active = depth >= self.rr_depth
                beta[rr_active] *= dr.rcp(rr_prob)
                active_next &= ~rr_active | (sampler.next_1d() < rr_prob)

                depth[si.is_valid()] += 1
                active = active_next

            records = None
            if dr.hint(record, mode="scalar"):
                records = dict(beta=rec_beta, wi=rec_wi, wo_nee=rec_wo_nee, e_nee=rec_e_nee,
                               wo=rec_wo, g=L_after * rec_inv_pdf)
            return L, depth != 0, parts, records

        # ------------------------------------------------------------ one pass

        def render_onepass(self, scene, materials=None, spp=0, seed=0, sensor=0, chunk=None,
                           max_samples=1 << 22, spp_per_pass=None, progress=None):
            """Render the base image and every material's touch image from one set of paths.

            For paths scattering once off the target, the material enters only at that
            vertex (issue 5). The paths are traced once; on the target they sample a density
            ``q`` that covers every material (the ``manifold_brdf`` sampling density of the
            mixture ``sum_i P_i / |P_i|`` of the per-material densities, plus its cosine
            fraction), and that vertex is recorded (:meth:`_trace`). Its two directions (the
            light connection, the sampled one) become two *splats* per sample, kept where
            they carry light: a pixel, a MERL bin, an RGB amplitude ``a``. A material adds
            ``a * table(bin)`` to the pixel, so the images are a sparse product
            ``(pixels x bins) @ (bins x materials)``.

            With ``nearest`` lookups and a box filter (the usual case), that product is
            computed directly: the tables, interleaved by bin (``Database.material_rows``,
            cached beside the database), give all materials' values at a bin in one
            contiguous read; the splats are sorted by bin, so the tables are read in order;
            one Dr.Jit kernel per group of ``chunk`` materials adds ``a * row`` into
            per-pixel sums (scatter-adds into per-thread copies, ``ReduceMode.Expand``),
            over tiles of pixels small enough to bound that memory. Otherwise (``linear``
            lookups, other filters) each material is evaluated at the splats sorted by bin
            (one gather from its table, or the BSDF's own ``eval``) and splatted with the
            film's filter. Either way the images are normalised by the filter weights of all
            samples, as the film does. Samples are processed in passes of at most
            ``max_samples`` paths to bound memory. Each image is an unbiased estimate of
            what ``component="touch"`` renders with that material alone; the images are
            correlated (the same paths).

            Parameters
            ----------
            scene : mi.Scene
                Its target (``target`` parameter) must be one group of ``manifold_brdf``
                BSDFs on one manifold. The scene's materials are not modified.
            materials : list of str, optional
                Training materials of the manifold to render (default: all).
            spp, seed, sensor :
                As :meth:`render` (``spp=0``: the sensor's sample count).
            chunk : int, optional
                Materials per kernel (default: all of them with the table product, 16
                otherwise).
            max_samples : int
                Most paths traced at once (passes of whole samples per pixel).
            spp_per_pass : int, optional
                Samples per pixel per pass, instead of the most that ``max_samples`` allows.
            progress : callable, optional
                Called as ``progress(done, total)`` in work units (one per pass and chunk).

            Returns
            -------
            base : ndarray float32 (H, W, 3)
                The paths that never scatter off the target.
            images : dict of str -> ndarray float32 (H, W, 3)
                The touch image of each material, in the order of ``materials``.
            """
            from mitsuba.ad.integrators.common import ADIntegrator

            from . import bsdf as manifold_bsdf

            groups = target_groups(scene, self.target)
            if len(groups) != 1:
                raise ValueError(
                    f"manifold_path: one-pass rendering handles one target group, the target "
                    f"{self.target!r} gives {len(groups)} ({[g[0] for g in groups]}); render "
                    "several targets material by material")
            targets = groups[0][1]
            for b in targets:
                if not hasattr(b, "manifold") or not hasattr(b, "manifold_path"):
                    raise ValueError(f"manifold_path: target BSDF {b.id()!r} is not a "
                                     "manifold_brdf (one-pass rendering reads its tables)")
            first = targets[0]
            manifold, path = first.manifold, first.manifold_path
            interpolation = getattr(first, "_interpolation", "nearest")
            database = getattr(first, "_database", None)
            sampling = getattr(first, "_sampling", "cdf")
            for b in targets[1:]:
                same = (os.path.samefile(b.manifold_path, path)
                        and getattr(b, "_interpolation", "nearest") == interpolation
                        and getattr(b, "_database", None) == database)
                if not same:
                    raise ValueError(
                        f"manifold_path: target BSDFs {first.id()!r} and {b.id()!r} differ in "
                        "manifold, database or interpolation; one-pass rendering needs them alike")
            names = list(manifold.names) if materials is None else [str(n) for n in materials]
            unknown = [n for n in names if n not in manifold.names]
            if unknown or not names or len(set(names)) != len(names):
                raise ValueError(
                    f"manifold_path: materials must be distinct names of the manifold {path}; "
                    f"unknown: {unknown or 'none'} (it has {', '.join(manifold.names[:8])}, ...)")
            if spp_per_pass is not None and int(spp_per_pass) < 1:
                raise ValueError(f"manifold_path: spp_per_pass must be >= 1, got {spp_per_pass}")
            if chunk is not None and int(chunk) < 1:
                raise ValueError(f"manifold_path: chunk must be >= 1, got {chunk}")

            if isinstance(sensor, int):
                sensor = scene.sensors()[sensor]
            film = sensor.film()
            db = manifold.open_database(database, names)
            dims = tuple(int(d) for d in db.dims)
            bins = int(np.prod(dims))
            # The table product needs nearest lookups, a box filter (one pixel per sample)
            # and tables addressable with 32-bit indices.
            n_pad = -(-len(names) // _PACKET) * _PACKET
            rows = None
            if (interpolation == "nearest" and film.rfilter().is_box_filter()
                    and bins * 3 * n_pad < 1 << 32):
                rows = db.material_rows(names, pad=_PACKET)
                _prefetch(rows.filename)  # read while the paths are traced

            # The sampling density on the target: every material's density, normalised.
            mass = np.array([manifold_bsdf.material_density(db, n).sum() for n in names], float)
            top = mass.max()
            mix = 1.0 / np.maximum(mass, 1e-3 * top) if top > 0 else np.ones(len(names))
            mix /= mix.sum()
            options = {"interpolation": interpolation}
            if database is not None:
                options["database"] = database
            spec = {"type": "manifold_brdf", "manifold": path, "prune": 0.0, "sampling": sampling,
                    **options}
            if rows is None:
                proxy = mi.load_dict({**spec, "weights": ", ".join(
                    f"{n}:{float(w)!r}" for n, w in zip(names, mix))})
            else:  # the mixture's table from the interleaved tables (cached)
                table = _mixture_table(db, rows, mix).T.reshape((3,) + dims)
                proxy = mi.load_dict({**spec, "material": names[0]})
                proxy.set_weights(dict(zip(names, mix)), table=table)

            spp = int(spp) or sensor.sampler().sample_count()
            size = film.crop_size()
            if film.sample_border():
                size += 2 * film.rfilter().border_size()
            pixels = int(size[0]) * int(size[1])
            pass_spp = int(spp_per_pass) if spp_per_pass else int(max_samples) // max(pixels, 1)
            pass_spp = max(1, min(spp, pass_spp))
            passes = [pass_spp] * (spp // pass_spp) + ([spp % pass_spp] if spp % pass_spp else [])
            chunk = int(chunk) if chunk else (len(names) if rows is not None else 16)
            chunks = [(i, min(len(names), i + chunk)) for i in range(0, len(names), chunk)]
            alpha = mi.has_flag(film.flags(), mi.FilmFlags.Alpha)
            plan = dict(groups=groups, names=class_names([groups[0][0]]), select=1, keep=3, aovs=[])

            film.prepare([])
            base_block = film.create_block()
            base_block.set_coalesce(base_block.coalesce() and spp >= 4)
            if rows is None:
                splat = _FilterSplats(film, base_block, names, chunks, db, path, options,
                                      len(passes) > 1)
            else:
                splat = _TableSplats(base_block, rows, names, chunks, dims)

            done, total = 0, len(passes) * len(chunks)
            with dr.suspend_grad():
                for p, n_spp in enumerate(passes):
                    sampler, _ = ADIntegrator.prepare(self, sensor, seed * len(passes) + p, n_spp, [])
                    ray, weight, pos = ADIntegrator.sample_rays(self, scene, sensor, sampler)
                    L, valid, _, rec = self._trace(scene, sampler, ray, mi.Bool(True), plan, True,
                                                   proxy)
                    L = L * weight
                    head = [L.x, L.y, L.z] + ([dr.select(valid, 1.0, 0.0)] if alpha else [])
                    base_block.put(pos, head + [mi.Float(1.0)])
                    splat.prepare(rec, rec["beta"] * weight, pos)
                    del sampler, ray, L, valid, rec, head
                    for c in range(len(chunks)):
                        splat.add(c)
                        done += 1
                        if progress is not None:
                            progress(done, total)
                    splat.release()
            film.prepare([])
            film.put_block(base_block)
            base = np.array(film.develop(), dtype=np.float32)[..., :3].copy()
            return base, splat.images(film)

        def to_string(self):
            return (f"ManifoldPathIntegrator[max_depth={self.max_depth}, rr_depth="
                    f"{self.rr_depth}, component={self.component!r}, target={self.target!r}, "
                    f"split={self.split}]")

    return ManifoldPathIntegrator


_CLASSES = {}


def check_variant(variant=None):
    """Raise ``RuntimeError`` unless ``variant`` (default: the active one) can run the integrator.

    The integrator traces whole wavefronts with Dr.Jit loops: it needs a JIT variant
    (``llvm_*`` or ``cuda_*``) with RGB spectra, e.g. ``llvm_ad_rgb`` or ``cuda_ad_rgb``.
    """
    variant = variant or mi.variant()
    if variant is None:
        raise RuntimeError("manifold_path: call mi.set_variant(...) before using the integrator")
    if not (variant.startswith(("llvm_", "cuda_")) and variant.endswith("_rgb")):
        raise RuntimeError(
            f"manifold_path: variant {variant!r} is not supported; the integrator traces "
            "wavefronts with Dr.Jit and needs an RGB JIT variant such as 'llvm_ad_rgb' "
            "or 'cuda_ad_rgb' (mi.set_variant(...), then mitsuba_manifold.register())")
    return variant


def integrator_class():
    """The integrator class for the active Mitsuba variant (built once per variant)."""
    variant = check_variant()
    if variant not in _CLASSES:
        _CLASSES[variant] = _make_class()
    return _CLASSES[variant]


def _unsupported(variant):
    def construct(props):
        check_variant(variant)
    return construct


def register():
    """Register ``manifold_path`` with Mitsuba for the active variant.

    In variants the integrator cannot run in (scalar, spectral, mono), the name is
    registered all the same, and creating the integrator raises a ``RuntimeError`` that
    says which variants work.
    """
    variant = mi.variant()
    try:
        cls = integrator_class()
    except RuntimeError:
        if variant is None:
            raise
        mi.register_integrator("manifold_path", _unsupported(variant))
        return
    mi.register_integrator("manifold_path", lambda props: cls(props))
