"""docs/benchmarks.md, generated from the current results in ``benchmarks/results/*.json``.

One section per result file: a benchmark module's ``report(result) -> str`` when it defines one
(``result``: the JSON file's content), otherwise a generic table of the file's figures (one
figure per row, its targets and whether they are met). The machine is named once, from the
results' ``machine`` entries; nothing else of a run (its date, load, folders) is shown.

``python3 -m benchmarks.page`` rewrites the page; ``--check`` fails when it is out of date
(``tests/bench/test_page.py`` does the same).
"""

import argparse
import importlib
import json
import os
import re
import sys
import textwrap

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(ROOT, "benchmarks", "results")
PAGE = os.path.join(ROOT, "docs", "benchmarks.md")

#: Result files that are not a benchmark of ``tools/bench.py``: their title and command.
OTHER = {
    "main_job_report": ("The main job", "python3 tools/main.py (writes out/gi/report.json)"),
    "gpu_check_h200": ("On a GPU (NVIDIA H200, cuda_ad_rgb)", "tools/gpu_check.sh"),
}
#: Keys never shown: what describes a run rather than what it measured.
RUN_KEYS = re.compile(
    r"(^|_)(load_average\w*|date|started|machine|cpu_s\w*|notes?|code|commit|command|screenshot|"
    r"plot|crops|work|basis|manifold|client|partial|run)$"
)
#: Words of the keys shown first (targets, then the figures a user reads).
FIRST = ("meets", "target", "bias", "error", "rel_mse", "ratio", "_ms", "_s", "peak", "median")
#: Fields that name an entry of a list (its label in the figure's name).
LABELS = ("name", "point", "x_is", "scene", "case", "method", "q")
#: Rows of a generic section at most.
MAX_ROWS = 24
#: Characters of a cell at most.
MAX_CELL = 80


def _number(v) -> str:
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return f"{v:,}" if abs(v) >= 10000 else str(v)
    return f"{v:.3g}"


def _cell(v):
    """A value as a table cell, or None where it is no single figure."""
    if isinstance(v, (bool, int, float)):
        return _number(v)
    if isinstance(v, str):
        if "/" in v or len(v) > MAX_CELL or re.search(r"\b[0-9a-f]{7,40}\b", v):
            return None  # a folder, a sentence of notes, a commit
        return v.replace("|", "/")
    if isinstance(v, list) and 0 < len(v) <= 4 and all(isinstance(x, (int, float, str)) for x in v):
        text = ", ".join(_number(x) if not isinstance(x, str) else x for x in v)
        return text if len(text) <= MAX_CELL and "/" not in text else None
    return None


def _figures(value, key="", depth=0):
    """``[(dotted key, cell)]`` of every single figure in ``value`` (dicts to depth 4)."""
    if isinstance(value, dict):
        if depth > 4:
            return []
        out = []
        for k, v in value.items():
            k = str(k)
            if RUN_KEYS.search(k):
                continue
            out += _figures(v, f"{key}.{k}" if key else k, depth + 1)
        return out
    if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        if depth > 3 or len(value) > 12:
            return []
        out = []
        for i, v in enumerate(value):
            named = [k for k in LABELS if isinstance(v.get(k), (str, int))][:2]
            label = " ".join(f"{k}={v[k]}" if k == "q" else str(v[k]) for k in named) or str(i)
            rest = {k: x for k, x in v.items() if k not in named}
            out += _figures(rest, f"{key}[{label}]", depth + 1)
        return out
    cell = _cell(value)
    return [] if cell is None else [(key, cell)]


def _score(key) -> int:
    return next((i for i, w in enumerate(FIRST) if w in key.rsplit(".", 1)[-1]), len(FIRST))


def generic(name, data) -> str:
    """A section for result ``data`` of benchmark ``name`` without a ``report``."""
    result = data.get("result", data) if isinstance(data, dict) else data
    rows = _figures(result)
    shown = sorted(range(len(rows)), key=lambda i: (_score(rows[i][0]), i))[:MAX_ROWS]
    lines = ["| figure | value |", "|---|---|"]
    lines += [f"| {rows[i][0]} | {rows[i][1]} |" for i in sorted(shown)]
    if len(rows) > len(shown):
        lines.append(f"| (and {len(rows) - len(shown)} more in the JSON) | |")
    return "\n".join(lines)


def main_job(data) -> str:
    """The main job's section: its pair and, at each point, the blend against the reference
    and against a direct render of 256 spp; its peak memory.
    """
    lines = [
        f"Pair: {' and '.join(data['pair'])} (latent neighbours whose colours differ most). "
        f"Basis {data['resolution']}x{data['resolution']} at {data['basis_spp']} spp, references "
        f"at {data['reference_spp']} spp. Peak memory {data['peak_rss_bytes'] / 2**30:.2f} GiB.",
        "",
        "| point | blend | rel. MSE | bias | L1- bias | direct 256 spp rel. MSE |",
        "|---|---|---|---|---|---|",
    ]
    for scene in data["scenes"].values():
        for p in scene["points"]:
            b = p["blend"]
            l1 = p.get("blend_l1", {}).get("relative_bias")
            direct = {d["spp"]: d for d in p.get("direct", [])}.get(256, {})
            summed = p.get("blend_summed", {}).get("time_s")
            lines.append(
                f"| {p['point']} ({p['x_is']}) | {b['time_s'] * 1e3:.0f} ms"
                + (f" ({summed * 1e3:.1f} ms summed)" if summed is not None else "")
                + f" | {b['rel_mse']:.3g} | {b['relative_bias']:+.2%} | "
                + (f"{l1:+.2%}" if l1 is not None else "")
                + f" | {_number(direct['rel_mse']) if direct else ''} |"
            )
    return "\n".join(lines)


def _bench_name(stem, data) -> str:
    name = data.get("benchmark") if isinstance(data, dict) else None
    return str(name) if isinstance(name, str) else stem.replace("_", "-")


def _report(name):
    """The ``report`` function of benchmark ``name``'s module, or None."""
    from . import NAMES, module_name

    if name not in NAMES:
        return None
    return getattr(importlib.import_module(module_name(name)), "report", None)


def machine(results) -> str:
    """The machine of the results, in words (the most common ``machine`` entry)."""
    seen = {}
    for data in results.values():
        m = data.get("machine") if isinstance(data, dict) else None
        if isinstance(m, dict) and "cpu_model" in m:
            text = (
                f"{m['cpu_model']}, {m.get('cpus', '?')} CPU cores, "
                f"{m.get('mem_total_gib', '?')} GiB, no GPU (`llvm_ad_rgb`), Python "
                f"{m.get('python', '?')}, Linux"
            )
            seen[text] = seen.get(text, 0) + 1
    return max(seen, key=seen.get) if seen else "not recorded"


def load(folder=RESULTS):
    """``{stem: content}`` of the result files in ``folder``, sorted by name (hidden files, such
    as the tools' record of the outputs they own, are not results).
    """
    out = {}
    for f in sorted(os.listdir(folder)):
        if f.endswith(".json") and not f.startswith("."):
            with open(os.path.join(folder, f), encoding="utf-8") as fh:
                out[f[:-5]] = json.load(fh)
    return out


def page(folder=RESULTS) -> str:
    """The Markdown of docs/benchmarks.md."""
    from . import NAMES

    results = load(folder)
    lines = [
        "# Benchmarks",
        "",
        "<!-- Generated by `python3 -m benchmarks.page` from benchmarks/results/*.json:",
        "     edit those (or a benchmark's `report`), not this page. -->",
        "",
        *textwrap.wrap(
            "Speed, memory and quality targets are checked by benchmarks, never by timed tests. "
            "Each benchmark writes a JSON report (`python3 tools/bench.py NAME --json FILE`); "
            "this page shows the current one of each, one figure per row, with its targets "
            "(`meets_*`: whether a target is met). Earlier runs are in the repository's history.",
            96,
        ),
        "",
        *textwrap.wrap(
            f"Machine (unless a section says otherwise): {machine(results)}. Timings on a "
            "shared machine vary between runs.",
            96,
        ),
        "",
    ]
    order = {n: i for i, n in enumerate(NAMES)}

    def key(stem):
        name = _bench_name(stem, results[stem])
        return (stem in OTHER, order.get(name, len(order)), stem)

    for stem in sorted(results, key=key):
        data = results[stem]
        name = _bench_name(stem, data)
        if stem in OTHER:
            title, command = OTHER[stem]
        else:
            title = name if stem.replace("_", "-") == name else f"{name} ({stem})"
            command = f"python3 tools/bench.py {name} --json benchmarks/results/{stem}.json"
        report = main_job if stem == "main_job_report" else _report(name)
        body = report(data).strip() if report else generic(name, data)
        lines += [f"## {title}", "", f"`{command}`", "", body, ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="Write docs/benchmarks.md from the results.")
    p.add_argument("--check", action="store_true", help="fail if the page is out of date")
    args = p.parse_args(argv)
    text = page()
    old = open(PAGE, encoding="utf-8").read() if os.path.exists(PAGE) else None
    if args.check:
        if old != text:
            print(f"{PAGE} is out of date: run python3 -m benchmarks.page", file=sys.stderr)
            return 1
        return 0
    if old != text:
        with open(PAGE, "w", encoding="utf-8") as f:
            f.write(text)
    print(PAGE)
    return 0


if __name__ == "__main__":
    sys.exit(main())
