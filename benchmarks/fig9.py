"""The paper's Fig. 9: perceptual distances from both ends along latent paths.

For each preset (``default``, ``paper``) and path kind (:data:`paths.KINDS`): paths of 20
equal steps (21 points) between the paper's three pairs, ten pairs of latent neighbours
(:func:`space.neighbour_pairs`, seed 0: the pairs the path kinds were tuned on) and a held-out
set never looked at while tuning (ten other neighbour pairs, seed 1, and five random pairs,
seed 2). Every path is measured with the [PR12]-style distance (:mod:`data.distance`) on the
full grid of bins (the paths are searched on :data:`paths.SEARCH_STRIDE`):

* ``deviation``: the largest ``|d(A, x_k) / d(A, B) - t_k|`` and ``|d(B, x_k) / d(A, B) - (1 - t_k)|``
  over the path's points (``t_k = k / 20``): how far either curve strays from Fig. 9's diagonal;
* ``largest_step``: the largest step's share of the path's perceptual length;
* ``still``: the share of steps shorter than a quarter of an even step (``L / 80``);
* ``length_ratio``: the path's perceptual length over ``d(A, B)`` (1: the straight chord);
* ``off_ends``: how far the path strays from the two end materials in the same units: the
  largest over its points of the distance to the nearer end, over ``d(A, B)`` (0.5 for a path
  that stays between them: its middle is half-way; a path through a third material far from
  both reads more);
* ``stray``: how far the path's colours stray from the two ends' (:func:`appearance.stray`: the
  largest CIELAB distance of a point's directional-albedo colours from the segment between
  the ends', ``delta_e``, and its share of the ends' own distance): blue -> brown -> white strays.

Targets (default kind on the default preset): median deviation <= 0.10, no step
over 0.10 of its path, median still share <= 5%, pair (a)'s deviation <= 0.25.
"""

from __future__ import annotations

import time

import numpy as np

from mitsuba_manifold._util.blas import one_thread
from mitsuba_manifold.data.distance import gram_distances
from mitsuba_manifold.imaging import plots
from mitsuba_manifold.manifold import appearance, paths, space
from mitsuba_manifold.manifold.model import Manifold

PAPER_PAIRS = (
    ("blue-metallic-paint", "dark-blue-paint"),
    ("teflon", "silver-paint"),
    ("black-oxidized-steel", "color-changing-paint3"),
)
TARGETS = {
    "median_deviation": 0.10,
    "largest_step": 0.10,
    "median_still": 0.05,
    "pair_a_deviation": 0.25,
}
STEPS = 21


def pair_sets(m, n_neighbours=10, n_held_neighbours=10, n_random=5):
    """``{"paper", "neighbours", "held_out"}`` pairs of names (see the module doc)."""
    name = m.names
    paper = [p for p in PAPER_PAIRS if p[0] in name and p[1] in name]
    tuned = [(name[i], name[j]) for i, j in space.neighbour_pairs(m.latent, n_neighbours, seed=0)]
    seen = {frozenset(p) for p in paper + tuned}
    held = [
        (name[i], name[j])
        for i, j in space.neighbour_pairs(m.latent, n_neighbours + n_held_neighbours, seed=1)
        if frozenset((name[i], name[j])) not in seen
    ][:n_held_neighbours]
    rng = np.random.default_rng(2)
    while len(held) < n_held_neighbours + n_random:
        i, j = rng.choice(m.n, 2, replace=False)
        p = (name[i], name[j])
        if frozenset(p) not in seen | {frozenset(h) for h in held}:
            held.append(p)
    return {"paper": paper, "neighbours": tuned, "held_out": held}


def measure(D):
    """Fig. 9's curves and the measures of a path from its distance matrix ``D`` (21 x 21)."""
    K = len(D) - 1
    t = np.linspace(0.0, 1.0, K + 1)
    d_ab = D[0, -1]
    from_a, from_b = D[0] / d_ab, D[-1] / d_ab
    s = np.diag(D, 1)
    length = s.sum()
    return {
        "d_ab": float(d_ab),
        "from_a": from_a.tolist(),
        "from_b": from_b.tolist(),
        "deviation": float(max(np.abs(from_a - t).max(), np.abs(from_b - (1 - t)).max())),
        "largest_step": float(s.max() / length),
        "still": float(np.mean(s < 0.25 * length / K)),
        "length_ratio": float(length / d_ab),
        "off_ends": float(np.minimum(from_a, from_b).max()),
        "steps": (s / length).tolist(),
    }


def summary(rows, pair_a=None):
    dev = [r["deviation"] for r in rows]
    out = {
        "n_pairs": len(rows),
        "median_deviation": float(np.median(dev)),
        "worst_deviation": float(np.max(dev)),
        "median_off_ends": float(np.median([r["off_ends"] for r in rows])),
        "worst_off_ends": float(np.max([r["off_ends"] for r in rows])),
        "median_stray_delta_e": float(np.median([r["stray"]["delta_e"] for r in rows])),
        "worst_stray_delta_e": float(np.max([r["stray"]["delta_e"] for r in rows])),
        "largest_step": float(max(r["largest_step"] for r in rows)),
        "median_still": float(np.median([r["still"] for r in rows])),
        "median_length_ratio": float(np.median([r["length_ratio"] for r in rows])),
    }
    if pair_a is not None:
        out["pair_a_deviation"] = pair_a["deviation"]
    out["meets"] = {k: bool(out[k] <= v) for k, v in TARGETS.items() if k in out}
    return out


def preset_report(m, sets, kinds, progress=True, every=False):
    """Paths of every kind for every pair of ``sets`` on manifold ``m``, measured on the full grid
    (BLAS on one thread, as :func:`paths.path` runs: threads only contend on a busy machine);
    ``every``: also :func:`every_pair_report`, with the same metrics.
    """
    with one_thread():
        return _preset_report(m, sets, kinds, progress, every)


def _preset_report(m, sets, kinds, progress, every):
    full = paths.PathMetric(m, (1, 1, 1))
    search = paths.PathMetric.of(m)
    albedos = appearance.material_albedos(m.tables(), m.dims)  # the stray's colours
    t0 = time.perf_counter()
    search.graph()
    out = {
        "graph_s": time.perf_counter() - t0,
        "graph_nodes": int(len(search.graph().nodes)),
        "kinds": {},
    }
    for kind in kinds:
        rows, times = {}, []
        for group, pairs in sets.items():
            rows[group] = _rows(m, pairs, kind, full, search, times, albedos)
        tuned = rows["paper"] + rows["neighbours"]
        pair_a = (
            rows["paper"][0]
            if rows["paper"] and rows["paper"][0]["pair"] == list(PAPER_PAIRS[0])
            else None
        )
        out["kinds"][kind] = {
            "tuned": summary(tuned, pair_a),
            "held_out": summary(rows["held_out"]),
            "path_s": {"median": float(np.median(times)), "max": float(np.max(times))},
            "rows": rows,
        }
        if progress:
            s, h = out["kinds"][kind]["tuned"], out["kinds"][kind]["held_out"]
            print(
                f"  {m.info.get('preset')} {kind:>9s}: median deviation {s['median_deviation']:.3f} "
                f"(held out {h['median_deviation']:.3f}), largest step {s['largest_step']:.3f} "
                f"({h['largest_step']:.3f}), median still {s['median_still']:.2f} ({h['median_still']:.2f}), "
                f"pair (a) {s.get('pair_a_deviation', float('nan')):.3f}; off the ends median "
                f"{s['median_off_ends']:.2f} (worst {s['worst_off_ends']:.2f}), colour stray median "
                f"{s['median_stray_delta_e']:.1f} dE (worst {s['worst_stray_delta_e']:.1f}); "
                f"{np.median(times):.2f} s a path",
                flush=True,
            )
    if every:
        out["every_neighbour_pair"] = every_pair_report(m, progress, (full, search), albedos)
    return out


def _rows(m, pairs, kind, full, search, times, albedos):
    """Measured paths of ``kind`` between ``pairs``; their search times appended to ``times``
    (``albedos``: :func:`appearance.material_albedos` of ``m``, the stray's colours).
    """
    rows = []
    for a, b in pairs:
        t0 = time.perf_counter()
        X = paths.path(m, a, b, STEPS, kind, metric=search)
        times.append(time.perf_counter() - t0)
        r = measure(full.distances(X))
        stray = appearance.stray(m.weights(X).w, albedos)
        r.update(
            pair=[a, b],
            x=X.tolist(),
            stray={k: stray[k] for k in ("delta_e", "share", "at", "ends_delta_e")},
            search_deviation=measure(gram_distances([(search.features(X),) * 2]))["deviation"],
        )
        rows.append(r)
    return rows


def every_pair_report(m, progress=True, metrics=None, albedos=None):
    """The default kind between every material and its nearest latent neighbour (each pair once,
    :func:`space.all_neighbour_pairs`): the pair set no seed chooses. ``metrics``: the full-grid
    and the search :class:`paths.PathMetric` when the caller has them.
    """
    pairs = [(m.names[i], m.names[j]) for i, j in space.all_neighbour_pairs(m.latent)]
    full, search = metrics or (paths.PathMetric(m, (1, 1, 1)), paths.PathMetric.of(m))
    albedos = appearance.material_albedos(m.tables(), m.dims) if albedos is None else albedos
    with one_thread():
        rows = _rows(m, pairs, paths.DEFAULT_KIND, full, search, [], albedos)
    out = {
        "kind": paths.DEFAULT_KIND,
        **summary(rows),
        "steps_over_target": int(sum(r["largest_step"] > TARGETS["largest_step"] for r in rows)),
        "rows": [
            {k: r[k] for k in ("pair", "deviation", "largest_step", "still", "off_ends", "stray")}
            for r in rows
        ],
    }
    if progress:
        print(
            f"  every neighbour pair ({len(rows)}): median deviation {out['median_deviation']:.3f}, "
            f"largest step {out['largest_step']:.3f}, median still {out['median_still']:.2f}",
            flush=True,
        )
    return out


def plot(report, path, preset):
    """Fig. 9 for one preset: rows = path kinds; columns = the paper's pairs and the neighbour pairs."""
    kinds = list(report["kinds"])
    cols = [("paper", i) for i in range(len(report["kinds"][kinds[0]]["rows"]["paper"]))] + [
        ("neighbours", None),
        ("held_out", None),
    ]
    fig, axes = plots.subplots(
        len(kinds), len(cols), figsize=(3.1 * len(cols), 2.9 * len(kinds)), squeeze=False
    )
    t = np.linspace(0, 1, STEPS)
    for r, kind in enumerate(kinds):
        rows = report["kinds"][kind]["rows"]
        for c, (group, i) in enumerate(cols):
            ax = axes[r, c]
            chosen = [rows[group][i]] if i is not None else rows[group]
            alpha = 1.0 if i is not None else 0.35
            for k, row in enumerate(chosen):
                ax.plot(
                    t,
                    row["from_a"],
                    "o-" if i is not None else "-",
                    color="tab:blue",
                    ms=3,
                    lw=1,
                    alpha=alpha,
                    label="from A" if k == 0 else None,
                )
                ax.plot(
                    t,
                    row["from_b"],
                    "o-" if i is not None else "-",
                    color="tab:red",
                    ms=3,
                    lw=1,
                    alpha=alpha,
                    label="from B" if k == 0 else None,
                )
            ax.plot([0, 1], [0, 1], "--", color="tab:blue", lw=0.8)
            ax.plot([0, 1], [1, 0], "--", color="tab:red", lw=0.8)
            dev = np.median([row["deviation"] for row in chosen])
            title = (
                f"({'abc'[i]}) {chosen[0]['pair'][0]} ->\n{chosen[0]['pair'][1]}"
                if i is not None
                else f"{len(chosen)} {'tuned neighbour' if group == 'neighbours' else 'held-out'} pairs"
            )
            ax.set_title(
                f"{kind}: {title}\n{'' if i is not None else 'median '}deviation {dev:.2f}",
                fontsize=7,
            )
            ax.set_xlabel("step / 20 along the path", fontsize=7)
            ax.set_ylabel("distance / d(A, B)", fontsize=7)
            ax.set_xlim(0, 1)
            ax.set_ylim(
                0,
                max(
                    1.6, min(3.0, max(max(row["from_a"] + row["from_b"]) for row in chosen) * 1.05)
                ),
            )
            ax.tick_params(labelsize=6)
    fig.suptitle(
        f"Fig. 9 on preset {preset}: [PR12]-style distance from A (blue) and B (red) along 20 steps; "
        "dashed: perceptually uniform",
        fontsize=9,
    )
    fig.tight_layout()
    plots.save(fig, path)
    return path


def run(
    folder,
    presets=("default", "paper"),
    kinds=paths.KINDS,
    names=None,
    plot_stem=None,
    progress=True,
):
    """Fig. 9 measures per preset and path kind on the database ``folder`` (module doc).

    ``plot_stem``: write ``<stem>_<preset>.png`` per preset.
    """
    from mitsuba_manifold.manifold.presets import PRESETS

    from .inputs import known

    presets = known("`presets`", presets, list(PRESETS), "preset")
    out = {
        "steps": STEPS - 1,
        "search_stride": list(paths.SEARCH_STRIDE),
        "default_kind": paths.DEFAULT_KIND,
        "targets": TARGETS,
        "presets": {},
    }
    for preset in presets:
        t0 = time.perf_counter()
        m = Manifold.fit(folder, names=names, preset=preset)
        out["n_materials"], out["dims"] = m.n, list(m.info["dims"])
        sets = pair_sets(m)
        if progress:
            print(
                f"{preset}: fitted in {time.perf_counter() - t0:.1f} s; {sum(map(len, sets.values()))} pairs",
                flush=True,
            )
        rep = preset_report(m, sets, kinds, progress, every=preset == "default")
        rep["fit_s"] = m.info["time_fit_s"]
        if plot_stem:
            rep["plot"] = plot(rep, f"{plot_stem}_{preset}.png", preset)
        out["presets"][preset] = rep
        del m
    return out


def report(result: dict) -> str:
    """Markdown section for docs/benchmarks.md: Fig. 9's paper pairs and the path summaries of
    the default preset, straight segments against the default path kind.
    """
    r = result["result"] if "result" in result else result
    dims = "x".join(map(str, r.get("dims", ())))
    lines = [
        f"### Fig. 9 ({r.get('n_materials', '?')} materials, {dims})",
        "",
        f"`tools/bench.py fig9 --configs default --database {result.get('database', 'merl')} "
        "--json benchmarks/results/fig9_default.json`: the deviation of the perceptual "
        "distances from both ends from Fig. 9's diagonal along 20-step paths.",
        "",
        "| preset | path | pair | deviation | target | met |",
        "|---|---|---|---|---|---|",
    ]
    target = TARGETS["pair_a_deviation"]
    for preset, rep in r["presets"].items():
        for kind in ("straight", r["default_kind"]):
            rows = rep["kinds"].get(kind, {}).get("rows", {}).get("paper", [])
            for label, row in zip("abc", rows):
                dev = row["deviation"]
                lines.append(
                    f"| {preset} | {kind} | ({label}) {row['pair'][0]} - {row['pair'][1]} | "
                    f"{dev:.3f} | <= {target:g} | {'yes' if dev <= target else 'no'} |"
                )
    lines += [
        "",
        "| preset | path | set | median deviation | largest step | median still |",
        "|---|---|---|---|---|---|",
    ]
    for preset, rep in r["presets"].items():
        for kind in ("straight", r["default_kind"]):
            k = rep["kinds"].get(kind, {})
            for group in ("tuned", "held_out"):
                s = k.get(group)
                if s:
                    lines.append(
                        f"| {preset} | {kind} | {group} | {s['median_deviation']:.3f} | "
                        f"{s['largest_step']:.3f} | {s['median_still']:.2f} |"
                    )
    lines.append(
        f"\nTargets: median deviation <= {TARGETS['median_deviation']:g}, largest step <= "
        f"{TARGETS['largest_step']:g}, median still <= {TARGETS['median_still']:g}."
    )
    return "\n".join(lines)
