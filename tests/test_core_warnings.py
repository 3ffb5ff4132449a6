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
