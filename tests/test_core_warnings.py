"""Stage warnings: kept in the artifact and the run record, printed by run (also for a reused result), shown by
show and the report, and covered by the artifact's content hash."""

import json

from conftest import run_cli


def _record(project):
    return json.loads(sorted((project / ".msflow" / "runs").glob("*.json"))[-1].read_text())


def test_warnings_are_printed_recorded_and_shown(numproject):
    first = run_cli(numproject, "run", "warnings.yaml", "-q")
    assert first.returncode == 0, first.stderr
    assert "warning: careful: stopped at the iteration limit (3) before converging" in first.stderr
    assert "warning: careful: input looks constant" in first.stderr
    assert "numeric detail" not in first.stderr
    assert _record(numproject)["stages"]["careful"]["warnings"] == [
        "stopped at the iteration limit (3) before converging",
        "input looks constant",
    ]
    again = run_cli(numproject, "run", "warnings.yaml", "-q")
    assert "warning: careful (cached result): input looks constant" in again.stderr
    shown = run_cli(numproject, "show", "careful", "-f", "warnings.yaml")
    assert "warnings:\n  stopped at the iteration limit (3)" in shown.stdout
    assert run_cli(numproject, "verify").returncode == 0
    converged = run_cli(numproject, "run", "warnings.yaml", "-q", "-S", "careful.limit=20")
    assert "iteration limit" not in converged.stderr and "input looks constant" in converged.stderr


def test_tampered_warnings_fail_verification(numproject):
    assert run_cli(numproject, "run", "warnings.yaml", "-q").returncode == 0
    manifest_file = next((numproject / ".msflow").rglob("zarr.json"))
    for path in (numproject / ".msflow").rglob("zarr.json"):
        doc = json.loads(path.read_text())
        if doc.get("attributes", {}).get("msflow", {}).get("warnings"):
            manifest_file = path
    doc = json.loads(manifest_file.read_text())
    doc["attributes"]["msflow"]["warnings"] = []
    manifest_file.write_text(json.dumps(doc))
    assert run_cli(numproject, "verify").returncode != 0


def test_report_lists_warnings(numproject, tmp_path):
    assert run_cli(numproject, "run", "warnings.yaml", "-q").returncode == 0
    out = tmp_path / "r.html"
    made = run_cli(numproject, "report", "-f", "warnings.yaml", "-o", out)
    assert made.returncode == 0, made.stderr
    page = out.read_text()
    assert "<h2>Warnings</h2>" in page and "input looks constant" in page


GAPS_WARNINGS = [
    "output 'nan' is all NaN (4 values)",
    "output 'nan_inf' is all NaN or Inf (3 values)",
    "output 'streamed_nan' is all NaN (24 values)",
]


def test_an_output_without_a_finite_value_is_a_warning_and_is_stored(numproject):
    result = run_cli(numproject, "run", "gaps.yaml", "-q")
    assert result.returncode == 0, result.stderr
    # one_finite, empty, streamed_late (its one finite value in its last block) and the integers: no warning
    assert result.stderr.splitlines() == [f"warning: gaps: {w}" for w in GAPS_WARNINGS]
    assert _record(numproject)["stages"]["gaps"]["warnings"] == GAPS_WARNINGS
    shown = run_cli(numproject, "show", "gaps.streamed_nan", "gaps.yaml")
    assert shown.returncode == 0 and "non-finite 24" in shown.stdout


def test_run_stage_warns_of_outputs_without_a_finite_value_too(numproject, monkeypatch):
    import sys

    from msflow.testing import run_stage

    monkeypatch.syspath_prepend(str(numproject))
    monkeypatch.delitem(sys.modules, "numstages.basic", raising=False)
    from numstages.basic import Gaps

    out = run_stage(Gaps, {"blocks": 2, "rows": 5})  # sinks kept in memory, not streamed to a store
    assert out.warnings == [
        "output 'nan' is all NaN (5 values)",
        "output 'nan_inf' is all NaN or Inf (3 values)",
        "output 'streamed_nan' is all NaN (20 values)",
    ]


def test_a_sink_stops_looking_at_its_values_once_one_is_finite(monkeypatch):
    import numpy as np

    from msflow.sinks import OutputSink

    looked_at = []
    isfinite = np.isfinite
    monkeypatch.setattr(np, "isfinite", lambda x: looked_at.append(np.size(x)) or isfinite(x))
    sink = OutputSink("y", np.float64)
    sink.append(np.full(1000, np.nan))  # no finite value yet: its first element, then the whole block
    sink.append(np.arange(1000.0))  # its first element is finite
    sink.append(np.full(1000, np.nan))  # not looked at: the output has a finite value
    assert looked_at == [1, 1000, 1]
    assert sink.nonfinite_warning() is None
