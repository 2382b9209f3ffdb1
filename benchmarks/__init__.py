"""Benchmarks behind ``tools/bench.py NAME``, outside the installed package (their reports go
to ``benchmarks/results/``): one module per benchmark, each with
``run(folder, ...)`` returning a JSON-ready dict of measurements.

Timings are wall-clock medians over repeats on the machine that runs them
(:func:`common.machine` records which one). Targets are reported beside the numbers
(``*_target`` and ``meets_*`` fields), never asserted. Benchmarks use the library (and
:mod:`mitsuba_manifold.apps.pipeline`); nothing in the library uses them.
"""

#: Benchmark names, in the order ``tools/bench.py`` lists them.
NAMES = (
    "fit",
    "interp",
    "pca",
    "bsdf",
    "gi",
    "gi-targets",
    "stability",
    "basis",
    "match",
    "match-render",
    "scaling",
    "explore",
    "space",
    "prune",
    "fig9",
    "paths",
    "measured-space",
    "measured",
    "acquire",
)


def module_name(name):
    """The module of benchmark ``name`` (``match-render``: ``match_render``)."""
    return f"{__name__}.{name.replace('-', '_')}"


def run(name, folder, **kwargs):
    """Run benchmark ``name`` on the database ``folder`` (``explore``: a basis folder); returns its
    measurements.
    """
    import importlib

    if name not in NAMES:
        from mitsuba_manifold.errors import InputError

        raise InputError(f"unknown benchmark {name!r}; choose one of {', '.join(NAMES)}")
    return importlib.import_module(module_name(name)).run(folder, **kwargs)
