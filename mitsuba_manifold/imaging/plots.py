"""Figures of a fitted manifold: the latent map over an albedo heat map, the fit's convergence."""

from __future__ import annotations

import os

import numpy as np

from .._util.atomic import atomic_write


def subplots(nrows=1, ncols=1, squeeze=True, layout=None, **figure_kw) -> tuple:
    """A new figure and its axes (as ``pyplot.subplots``), drawn by Agg.

    The figure is made without ``pyplot``: no backend is switched (a caller's interactive
    backend stays as it is) and no figure is registered anywhere, so nothing needs closing.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(layout=layout, **figure_kw)
    FigureCanvasAgg(fig)
    return fig, fig.subplots(nrows, ncols, squeeze=squeeze)


def save(fig, path) -> None:
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=110))


def finish(fig, axes, path) -> str:
    """Grid and legend on every axis of ``axes``, then save ``fig`` to ``path`` and close it; returns ``path``."""
    for ax in np.ravel(axes):
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    fig.tight_layout()
    save(fig, path)
    return path


def slice_points(manifold, dims=(0, 1), resolution=160, margin=0.15) -> tuple:
    """Grid over a 2D slice of the latent space: ``(xs, ys, points (ny * nx, q))``.

    The slice spans latent coordinates ``dims``; the other coordinates are fixed at the
    mean of the latent points.
    """
    lo = manifold.latent[:, dims].min(axis=0)
    hi = manifold.latent[:, dims].max(axis=0)
    pad = margin * np.maximum(hi - lo, 1e-9)
    xs = np.linspace(lo[0] - pad[0], hi[0] + pad[0], resolution)
    ys = np.linspace(lo[1] - pad[1], hi[1] + pad[1], resolution)
    gx, gy = np.meshgrid(xs, ys)
    pts = np.tile(manifold.latent.mean(axis=0), (gx.size, 1))
    pts[:, dims[0]] = gx.ravel()
    pts[:, dims[1]] = gy.ravel()
    return xs, ys, pts


def albedo_grid(manifold, dims=(0, 1), resolution=160, margin=0.15) -> tuple:
    """Albedo (mean of RGB) of the interpolated material over a 2D slice (:func:`slice_points`).

    Returns ``(xs, ys, albedo[ny, nx])``.
    """
    xs, ys, pts = slice_points(manifold, dims, resolution, margin)
    return xs, ys, manifold.albedo(pts).mean(axis=1).reshape(len(ys), len(xs))


def data_distance(manifold, pts) -> tuple:
    """Distance (in units of l) from each point to the nearest latent point, and the reach of the data.

    The reach is twice the median nearest-neighbour spacing of the latent points: closer than
    that to a material, a point is among the data; farther, it extrapolates.
    """
    d2 = ((pts[:, None, :] - manifold.latent[None]) ** 2).sum(-1)
    reach = 2.0 * float(np.median(_isolation(manifold.latent)))
    return np.sqrt(d2.min(axis=1)) / manifold.length_scale, reach / manifold.length_scale


def latent_map(manifold, path, dims=(0, 1), resolution=160, title=None) -> str:
    """PNG of the latent points with their names over the albedo heat map and iso-lines.

    Paper Fig. 7 and 10. Where any RGB albedo channel leaves [0, 1] the map is hatched; a
    dashed line encloses where the data lives (:func:`data_distance`). For ``q > 2`` the map
    is a slice through ``dims`` at the mean of the other coordinates; materials far from the
    slice are drawn hollow. Every material is a point; names go to as many as fit without
    overlapping (:func:`label_points`), dark on a light halo so they read on any colour.
    """
    xs, ys, pts = slice_points(manifold, dims, resolution)
    rgb = manifold.albedo(pts)
    shape = (len(ys), len(xs))
    alb = rgb.mean(axis=1).reshape(shape)
    outside = ((rgb < 0) | (rgb > 1)).any(axis=1).reshape(shape)
    dist, reach = data_distance(manifold, pts)
    fig, ax = subplots(figsize=(11, 9), layout="constrained")
    im = ax.imshow(
        alb, origin="lower", extent=(xs[0], xs[-1], ys[0], ys[-1]), cmap="viridis", aspect="auto"
    )
    cs = ax.contour(xs, ys, alb, levels=12, colors="white", linewidths=0.6, alpha=0.8)
    ax.clabel(cs, fontsize=6, fmt="%.2f")
    fig.colorbar(im, ax=ax, label="albedo of the interpolated material (mean RGB)")
    if outside.any():
        ax.contourf(
            xs, ys, outside.astype(float), levels=[0.5, 1.5], colors="none", hatches=["////"]
        )
        ax.contour(xs, ys, outside.astype(float), levels=[0.5], colors="red", linewidths=0.8)
    ax.contour(
        xs,
        ys,
        dist.reshape(shape),
        levels=[reach],
        colors="orange",
        linewidths=1.0,
        linestyles="--",
    )
    pts_d = manifold.latent[:, dims]
    others = [k for k in range(manifold.q) if k not in dims]
    off = (
        np.abs(manifold.latent[:, others] - manifold.latent[:, others].mean(0)).max(axis=1)
        if others
        else np.zeros(manifold.n)
    )
    near = off <= reach
    ax.scatter(
        pts_d[near, 0], pts_d[near, 1], s=14, c="red", edgecolors="black", linewidths=0.4, zorder=5
    )
    ax.scatter(
        pts_d[~near, 0],
        pts_d[~near, 1],
        s=14,
        facecolors="none",
        edgecolors="red",
        linewidths=0.6,
        zorder=5,
    )
    lo, hi = rgb.min(), rgb.max()
    note = (
        f"hatched: {outside.mean():.1%} of the map has albedo outside [0, 1] ({lo:.2f} to {hi:.2f})"
        if outside.any()
        else f"albedo within [0, 1] everywhere ({lo:.2f} to {hi:.2f})"
    )
    slice_note = f", slice through x[{dims[0]}], x[{dims[1]}]" + (
        " (hollow: off the slice)" if others else ""
    )
    ax.set_xlabel(f"x[{dims[0]}]")
    ax.set_ylabel(f"x[{dims[1]}]")

    def heading(named):
        return title or (
            f"Latent space (q={manifold.q}{slice_note}); {named} of {manifold.n} materials named"
            + ("" if named == manifold.n else " (no room for the others)")
            + f"\n{note}; dashed: within {reach:.2g} l of a material (the data)"
        )

    ax.set_title(heading(0), fontsize=9)  # as many lines as the final title, for the layout
    fig.canvas.draw()  # the layout settles; names go on the final axes
    fig.set_layout_engine("none")
    order = np.lexsort(
        (-_isolation(pts_d), ~near)
    )  # on the slice first, then the most isolated first
    ax.set_title(heading(label_points(ax, pts_d, manifold.names, order=order)), fontsize=9)
    save(fig, path)
    return path


def _isolation(xy):
    """Distance from each point to its nearest neighbour (inf for a single point)."""
    d2 = ((xy[:, None] - xy[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    return np.sqrt(d2.min(axis=1))


#: Where a label may sit beside its point: (dx, dy) in points, horizontal and vertical alignment.
_LABEL_SPOTS = (
    (4, 2, "left", "bottom"),
    (-4, 2, "right", "bottom"),
    (4, -2, "left", "top"),
    (-4, -2, "right", "top"),
    (6, 0, "left", "center"),
    (-6, 0, "right", "center"),
    (0, 5, "center", "bottom"),
    (0, -5, "center", "top"),
)


def label_points(ax, xy, names, order=None, fontsize=7, marker_px=4) -> int:
    """Name the points ``xy`` (data coordinates of ``ax``) where a name fits: inside the
    axes, over no other name and no other point. Tries each spot of :data:`_LABEL_SPOTS`
    in turn; points whose every spot is taken stay unnamed. ``order``: who is placed first
    (default: as given). Call once the figure's layout is final. Returns how many are named.
    """
    import matplotlib.patheffects as pe
    from matplotlib.transforms import Bbox

    renderer = ax.figure.canvas.get_renderer()
    frame = ax.get_window_extent(renderer)
    disp = ax.transData.transform(np.asarray(xy, dtype=float))
    marks = [
        Bbox.from_extents(x - marker_px, y - marker_px, x + marker_px, y + marker_px)
        for x, y in disp
    ]
    halo = [pe.withStroke(linewidth=2.5, foreground="white")]
    taken: list
    taken, named = [], 0
    for i in range(len(names)) if order is None else order:
        for dx, dy, ha, va in _LABEL_SPOTS:
            text = ax.annotate(
                names[i],
                xy[i],
                xytext=(dx, dy),
                textcoords="offset points",
                ha=ha,
                va=va,
                fontsize=fontsize,
                color="black",
                path_effects=halo,
                zorder=4,
            )
            box = text.get_window_extent(renderer).padded(1.5)
            inside = (
                frame.x0 <= box.x0
                and box.x1 <= frame.x1
                and frame.y0 <= box.y0
                and box.y1 <= frame.y1
            )
            if (
                inside
                and not any(box.overlaps(b) for b in taken)
                and not any(box.overlaps(m) for j, m in enumerate(marks) if j != i)
            ):
                taken.append(box)
                named += 1
                break
            text.remove()
    return named


def latent_line(manifold, path, resolution=400, margin=0.15) -> str:
    """PNG of a one-dimensional latent space (q = 1): the albedo of the interpolated material
    along ``x`` with the materials at their latent points (the ``q = 1`` analogue of
    :func:`latent_map`).
    """
    x = manifold.latent[:, 0]
    pad = margin * max(x.max() - x.min(), 1e-9)
    xs = np.linspace(x.min() - pad, x.max() + pad, resolution)
    fig, ax = subplots(figsize=(11, 5))
    ax.plot(xs, manifold.albedo(xs[:, None]).mean(axis=1), color="0.3", lw=1)
    mine = manifold.albedo(x[:, None]).mean(axis=1)
    ax.scatter(x, mine, s=14, c="red", edgecolors="black", linewidths=0.4, zorder=3)
    for px, py, name in zip(x, mine, manifold.names):
        ax.annotate(
            name, (px, py), fontsize=7, rotation=60, xytext=(2, 2), textcoords="offset points"
        )
    ax.set_title("Latent space (q=1): albedo of the interpolated material along x", fontsize=9)
    ax.set_xlabel("x[0]")
    ax.set_ylabel("albedo (mean RGB)")
    save(fig, path)
    return path


def convergence(history, path, label="Hooke-Jeeves", others=None) -> str:
    """PNG of the log-likelihood per iteration (paper Fig. 5); ``others``: {label: history}."""
    fig, ax = subplots(figsize=(6, 4))
    for lab, h in [(label, history)] + list((others or {}).items()):
        h = np.asarray(h)
        ax.plot(np.arange(len(h)), h, marker=".", label=lab)
    ax.set_xlabel("iteration")
    ax.set_ylabel("log-likelihood L")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    save(fig, path)
    return path


def slice_plot_name(dims) -> str:
    """File name of the latent map of ``dims`` (0-based, as its axes are labelled ``x[i]``)."""
    return "latent_map.png" if tuple(dims) == (0, 1) else f"latent_map_dims{dims[0]}{dims[1]}.png"


def second_slice(q) -> tuple[int, int]:
    """The latent dimensions of the second map :func:`write_fit_plots` draws (for q > 2)."""
    return (2, 3) if q > 3 else (1, 2)


#: Files :func:`write_fit_plots` may write: the map of x[0], x[1] (a line for q = 1), a second
#: slice for q = 3 (x[1], x[2]) or q > 3 (x[2], x[3]), the convergence plot when there is a history.
FIT_PLOTS = (
    "latent_map.png",
    slice_plot_name((1, 2)),
    slice_plot_name((2, 3)),
    "log_likelihood.png",
)


def write_fit_plots(manifold, folder) -> list:
    """Latent map(s) (a line for q = 1) and convergence plot into ``folder``; returns the paths."""
    os.makedirs(folder, exist_ok=True)
    first = os.path.join(folder, FIT_PLOTS[0])
    paths = [latent_line(manifold, first) if manifold.q == 1 else latent_map(manifold, first)]
    if manifold.q > 2:
        dims = second_slice(manifold.q)
        paths.append(latent_map(manifold, os.path.join(folder, slice_plot_name(dims)), dims=dims))
    if len(manifold.history):
        paths.append(
            convergence(
                manifold.history,
                os.path.join(folder, FIT_PLOTS[-1]),
                label=manifold.record.method or "fit",
            )
        )
    return paths


#: Markers of :func:`gi_error_vs_time`, one per way of making the image: (marker, filled, label).
GI_MARKERS = {
    "direct": ("o", True, "direct render ({spp} spp)"),
    "blend": ("*", True, "the blend (default)"),
    "blend_summed": ("^", False, "full-GI blend, L2+ as summed"),
    "blend_l1": ("x", True, "L1- blend"),
    "refined": ("D", True, "refined (--refine)"),
    "blend_denoised": ("P", False, "blend, whole image denoised"),
    "direct_denoised": ("s", False, "direct {top} spp, denoised"),
}


def _gi_points(row) -> dict[str, tuple[list, list]]:
    """``{marker kind: ([times], [rel MSEs])}`` of one point of a GI report row."""
    b, d = row["blend"], row["direct"]
    out = {
        "direct": ([r["time_s"] for r in d], [r["rel_mse"] for r in d]),
        "blend": ([b["time_s"]], [b["rel_mse"]]),
    }
    if "blend_summed" in row:
        out["blend_summed"] = ([row["blend_summed"]["time_s"]], [row["blend_summed"]["rel_mse"]])
    if "blend_l1" in row:  # the L1- blend of the same basis costs what the summed full one does
        t = row.get("blend_summed", b)["time_s"]
        out["blend_l1"] = ([t], [row["blend_l1"]["rel_mse"]])
    if "refined" in row:
        out["refined"] = ([row["refined"]["time_s"]], [row["refined"]["rel_mse"]])
    if "denoised" in b:  # denoised figures beside (never instead of) the raw ones
        out["blend_denoised"] = ([b["denoised"]["time_s"]], [b["denoised"]["rel_mse"]])
        top = [r["denoised"] for r in d if "denoised" in r]
        out["direct_denoised"] = ([r["time_s"] for r in top], [r["rel_mse"] for r in top])
    return out


def gi_error_vs_time(report, path) -> str:
    """Log-log plot of relative MSE against time per image (Fig. 13 in spirit): per scene, each
    point's direct renders and blends; colour: the latent point, marker: how the image was made.
    """
    from matplotlib.lines import Line2D

    names, drawn = list(report["scenes"]), set()
    fig, axes = subplots(
        1, len(names), figsize=(6.5 * len(names) + 1.5, 6.6), squeeze=False, layout="constrained"
    )
    for ax, name in zip(axes[0], names):
        sc = report["scenes"][name]
        for k, row in enumerate(sc["points"]):
            for kind, (ts, es) in _gi_points(row).items():
                drawn.add(kind)
                marker, filled, _ = GI_MARKERS[kind]
                ax.loglog(
                    ts,
                    es,
                    marker + ("-" if kind == "direct" else ""),
                    ms=12 if marker == "*" else 8,
                    color=f"C{k}",
                    mfc=None if filled else "none",
                )
        ax.set_title(
            f"{name}.xml: basis rendered once in {sc['basis_time_s']:.0f} s "
            f"({report['basis_spp']} spp)",
            fontsize=9,
        )
        ax.set_xlabel("time per image (s)")
        ax.set_ylabel(f"relative MSE vs {report['reference_spp']} spp full GI")
        ax.grid(alpha=0.3, which="both")
    points = [
        Line2D([], [], color=f"C{k}", lw=6, label=f"{r['point']}: {r['x_is']}")
        for k, r in enumerate(report["scenes"][names[0]]["points"])
    ]
    spps = sorted(
        {
            r["spp"]
            for sc in report["scenes"].values()
            for row in sc["points"]
            for r in row["direct"]
        }
    )
    spp = ", ".join(str(v) for v in spps) if len(spps) < 3 else f"{spps[0]} to {spps[-1]}"
    kinds = [
        Line2D(
            [],
            [],
            color="0.3",
            ls="",
            marker=mk,
            mfc=None if filled else "none",
            ms=8,
            label=label.format(spp=spp, top=spps[-1] if spps else ""),
        )
        for kind, (mk, filled, label) in GI_MARKERS.items()
        if kind in drawn
    ]
    # below the axes, so that long point names do not squeeze the plot
    fig.legend(
        handles=points + kinds, fontsize=7.5, loc="outside lower center", ncols=2, frameon=False
    )
    save(fig, path)
    return path
