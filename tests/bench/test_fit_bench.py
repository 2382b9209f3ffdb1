"""The fit benchmark on a small database: every run reported, the default converged and the same."""

from benchmarks import fit


def test_fit_bench_compares_the_runs_and_measures_sameness(small_db):
    r = fit.run(small_db)
    assert [row["run"] for row in r["runs"]] == [name for name, *_ in fit.RUNS]
    assert r["default_converged"] and r["best_run"] in {row["run"] for row in r["runs"]}
    assert set(r["sameness"]) >= {"last_bits_0", "material_order", "manifold_1_thread"}
    assert r["meets_sameness_target"] and r["manifold_info"]["converged"] is True
    text = fit.report({"database": "db", "result": r})
    assert "| newton / mds (default) |" in text and "largest point difference" in text
