"""The fit benchmark on a small database: every run reported, the default converged and the same."""

import pytest

from benchmarks import fit


def test_fit_bench_compares_the_runs_and_measures_sameness(small_db):
    r = fit.run(small_db)
    assert [row["run"] for row in r["runs"]] == [name for name, *_ in fit.RUNS]
    assert r["default_converged"] and r["best_run"] in {row["run"] for row in r["runs"]}
    assert set(r["sameness"]) >= {"last_bits_0", "material_order", "manifold_1_thread"}
    assert r["meets_sameness_target"] and r["manifold_info"]["converged"] is True
    text = fit.report({"database": "db", "result": r})
    assert f"| {fit.DEFAULT_RUN} (default) |" in text and "largest point difference" in text
    default = next(row for row in r["runs"] if row["run"] == fit.DEFAULT_RUN)
    assert len(default["stages"]) == 1  # no continuation by default
    continued = next(row for row in r["runs"] if row["run"] == fit.CONTINUATION_RUN)
    assert [mu for mu, _ in continued["stages"]] == [*fit.CONTINUATION, 1e-4]
    assert set(r["continuation_sameness"]) == {
        f"continuation_last_bits_{k}" for k in range(fit.LAST_BITS)
    }
    objectives = r["last_bits_objectives"]
    for k in range(fit.LAST_BITS):  # the same points: the same maximum of the objective
        assert objectives[f"last_bits_{k}"] == pytest.approx(objectives["default"], rel=1e-9)
    assert "through the noise continuation" in text
