"""Measured materials by device: projection beyond the data and added materials (``tools/bench.py measured-space``).

A manifold (the default preset) is fitted on one device's materials and the materials of
another device are placed in it, for each split of :data:`SPLITS` (MERL -> RGL, MERL ->
Nielsen, MERL + Nielsen -> RGL):

* ``projection``: per material, the error (RMS of ``log(1 + rho)`` differences over all
  bins) of the nearest training material, of the latent projection (convex weights) and of
  the best plausible combination beyond the data (``Manifold.project(beyond=True)``), their
  ratios to the nearest's, and the plausibility of that combination: its smallest table value,
  its largest directional albedo over incidences and channels, its negative weight mass;
* ``add``: the first ``n_add`` materials added one by one (``Manifold.add``): seconds each,
  whether the training points stayed where they were and the new one is reproduced exactly.

Target (the projection, per split): median ratio of the plausible combination to the
nearest material at most 0.75, no negative bin, directional albedo at most 1.
:func:`by_device` takes any ``{set name: database folder}``; :func:`run` finds the sets as the
sub-folders ``merl``, ``rgl``, ``nielsen`` of one folder.
"""

from __future__ import annotations

import os
import tempfile
import time

import numpy as np

from mitsuba_manifold.data.database import Database
from mitsuba_manifold.manifold import projection
from mitsuba_manifold.manifold.model import Manifold
from mitsuba_manifold.manifold.plausibility import DirectionalAlbedo

#: (training sets, test set) of the report.
SPLITS = ((("merl",), "rgl"), (("merl",), "nielsen"), (("merl", "nielsen"), "rgl"))
TARGETS = {"median_ratio": 0.75, "max_albedo": 1.0, "min_value": 0.0}


def combined_folder(folders, out):
    """A database folder ``out`` linking the tables of several database ``folders`` (names must differ)."""
    os.makedirs(out, exist_ok=True)
    for folder in folders:
        for name in Database(folder).names:
            link = os.path.join(out, name + ".binary")
            if os.path.lexists(link):
                raise ValueError(f"material {name!r} is in more than one training set")
            os.symlink(os.path.abspath(os.path.join(folder, name + ".binary")), link)
    return out


def project_set(m, db, names=None, progress=True):
    """Rows of the projection of each material of :class:`Database` ``db`` onto ``m`` (module doc)."""
    tables = m.tables()
    da = DirectionalAlbedo(m.dims)
    rows = []
    for name in names or db.names:
        target = np.asarray(db.reflectance(name), dtype=np.float32).reshape(-1)
        t0 = time.perf_counter()
        p = m.project(target)
        p = projection.beyond(p, tables, target, albedo=da)
        b = p.beyond
        rows.append(
            {
                "name": name,
                "nearest": p.nearest,
                "nearest_error": p.nearest_error,
                "convex_error": p.error,
                "beyond_error": b.error,
                "convex_ratio": p.error / p.nearest_error,
                "beyond_ratio": p.best_error / p.nearest_error,
                "min_value": b.min_value,
                "max_albedo": b.max_albedo,
                "shrink": b.shrink,
                "negative_weight": float(-b.weights[b.weights < 0].sum()),
                "target_max_albedo": float(da.of(target).max()),
                "time_s": time.perf_counter() - t0,
            }
        )
        if progress:
            r = rows[-1]
            print(
                f"    {name}: convex {r['convex_ratio']:.3f}, beyond {r['beyond_ratio']:.3f} of the nearest "
                f"({r['nearest']}); max albedo {r['max_albedo']:.3f}, min value {r['min_value']:.2g}",
                flush=True,
            )
    return rows


def add_set(m, db, n_add):
    """Add the first ``n_add`` materials of ``db`` to ``m`` one by one (module doc)."""
    before = m.latent.copy()
    out = []
    for name in db.names[:n_add]:
        info = m.add(db.path(name), name=f"added:{name}")
        table, _keep, _ = m.interpolate(m.latent[-1], prune=0.0)
        out.append(
            {
                "name": name,
                "time_s": info.time_s,
                "nearest": info.nearest,
                "exact": bool(np.array_equal(table.reshape(-1), m.tables()[-1])),
                "others_unchanged": bool(np.array_equal(m.latent[: len(before)], before)),
            }
        )
    return out


def summary(rows):
    ratio = np.array([r["beyond_ratio"] for r in rows])
    convex = np.array([r["convex_ratio"] for r in rows])
    out = {
        "n": len(rows),
        "median_beyond_ratio": float(np.median(ratio)),
        "median_convex_ratio": float(np.median(convex)),
        "worst_beyond_ratio": float(ratio.max()),
        "min_value": float(min(r["min_value"] for r in rows)),
        "max_albedo": float(max(r["max_albedo"] for r in rows)),
        "median_negative_weight": float(np.median([r["negative_weight"] for r in rows])),
    }
    out["meets"] = {
        "median_ratio": out["median_beyond_ratio"] <= TARGETS["median_ratio"],
        "no_negative_bin": out["min_value"] >= TARGETS["min_value"],
        "albedo": out["max_albedo"] <= TARGETS["max_albedo"] + 1e-6,
    }
    return out


def by_device(sets, splits=SPLITS, n_add=5, names=None, progress=True):
    """The report of the module doc for ``sets`` (``{set name: database folder}``); ``names``:
    ``{set name: materials}`` to project only some.
    """
    out = {"splits": {}, "targets": TARGETS}
    with tempfile.TemporaryDirectory() as tmp:
        for train, test in splits:
            if test not in sets or any(s not in sets for s in train):
                continue
            key = f"{'+'.join(train)}->{test}"
            folder = (
                sets[train[0]]
                if len(train) == 1
                else combined_folder([sets[s] for s in train], os.path.join(tmp, key))
            )
            t0 = time.perf_counter()
            m = Manifold.fit(folder)
            if progress:
                print(
                    f"  {key}: fitted {m.n} materials in {time.perf_counter() - t0:.1f} s",
                    flush=True,
                )
            db = Database(sets[test])
            rows = project_set(m, db, (names or {}).get(test), progress)
            added = add_set(m, db, n_add) if n_add else []
            out["splits"][key] = {
                "n_train": m.n - len(added),
                "dims": list(m.dims),
                "summary": summary(rows),
                "rows": rows,
                "add": added,
                "add_s": {
                    "median": float(np.median([a["time_s"] for a in added])) if added else None,
                    "max": float(max(a["time_s"] for a in added)) if added else None,
                },
            }
            if progress:
                s = out["splits"][key]["summary"]
                print(
                    f"  {key}: median ratio beyond {s['median_beyond_ratio']:.3f} (convex "
                    f"{s['median_convex_ratio']:.3f}); max albedo {s['max_albedo']:.3f}, min value "
                    f"{s['min_value']:.2g}",
                    flush=True,
                )
    return out


def run(folder, n_add=5, progress=True):
    """:func:`by_device` on the sub-folders ``merl``, ``rgl`` and ``nielsen`` of ``folder`` that exist."""
    sets = {
        s: os.path.join(folder, s)
        for s in ("merl", "rgl", "nielsen")
        if os.path.isdir(os.path.join(folder, s))
    }
    if "merl" not in sets:
        from mitsuba_manifold.errors import InputError

        raise InputError(
            f"measured-space: {folder} has no 'merl' sub-folder; give a folder holding the "
            "databases merl/, rgl/ and nielsen/"
        )
    return by_device(sets, n_add=n_add, progress=progress)
