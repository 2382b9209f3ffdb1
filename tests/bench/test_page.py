"""docs/benchmarks.md is generated from benchmarks/results/*.json (benchmarks/page.py): up to
date, one figure per row, the machine named once, no run log; a benchmark's ``report`` is used
where it defines one."""

import json
import re

from benchmarks import fit, page


def test_the_committed_page_is_up_to_date():
    assert open(page.PAGE, encoding="utf-8").read() == page.page(), (
        "docs/benchmarks.md is out of date: run python3 -m benchmarks.page"
    )


def test_no_run_log_and_the_machine_once():
    text = page.page()
    assert text.count("Machine") == 1 and "Xeon" in text
    assert "load_average" not in text and "load average" not in text
    assert not re.search(r"\b20\d\d-\d\d-\d\d\b", text)  # no dates
    assert not re.search(r"\b[0-9a-f]{7,40}\b", text)  # no commit hashes
    for line in text.splitlines():
        if line.startswith("| ") and not line.startswith("| figure"):
            assert len(line) <= 200, line


def test_a_benchmarks_report_is_used_when_it_defines_one(tmp_path, monkeypatch):
    data = {"benchmark": "fit", "machine": {"cpu_model": "Test CPU", "cpus": 3}, "result": {}}
    (tmp_path / "fit.json").write_text(json.dumps(data))
    (tmp_path / "other.json").write_text(
        json.dumps({"result": {"time_s": 0.12345, "meets_target": True, "folder": "/tmp/x"}})
    )
    monkeypatch.setattr(
        fit, "report", lambda r: "| what | figure |\n|---|---|\n| mine | 1 |", raising=False
    )
    text = page.page(str(tmp_path))
    assert "| mine | 1 |" in text and "Test CPU, 3 CPU cores" in text
    assert "| time_s | 0.123 |" in text and "| meets_target | yes |" in text
    assert "/tmp/x" not in text  # a folder of the run is no figure
