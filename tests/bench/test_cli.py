"""tools/bench.py's options: each benchmark gets only the options it uses."""

import importlib
import inspect
import os

import pytest

from benchmarks import cli as bench_cli
from benchmarks import module_name


def test_bench_takes_manifold_only_where_the_benchmark_uses_it(tmp_path, capsys):
    """--manifold goes to the benchmarks whose run() takes one; the others refuse it in one
    line (they fit their own) instead of failing inside with a TypeError."""
    takes = {
        n
        for n in bench_cli.NAMES
        if "manifold" in inspect.signature(importlib.import_module(module_name(n)).run).parameters
    }
    assert set(bench_cli.WITH_MANIFOLD) == takes
    with pytest.raises(SystemExit) as e:
        bench_cli.main(
            ["space", "--json", str(tmp_path / "s.json"), "--manifold", str(tmp_path / "m.npz")]
        )
    err = capsys.readouterr().err
    assert e.value.code == 2 and "space takes no --manifold" in err and "Traceback" not in err
    assert not os.listdir(tmp_path)
