"""The run report: one self-contained HTML page, checked in headless Chromium (Debian's, via Playwright)."""

import re
import subprocess
import sys

import pytest
from conftest import cli_env, run_cli

ARGS = [
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
REQUIRED_FIGURES = [  # issue 8: one per paper figure or pipeline step
    "track_train · contact_sheet",
    "aam · shape_modes",
    "edit · interpolation_strip",
    "edit · style_over_time",
    "keymorphs · contact_sheet",
    "keyshapes · weights",
    "blend · weights",
    "pitch_test · pitch_segments",
    "trellis · trellis",
    "motion_blend · head_angles",
    "export · preview",
]


def open_in_chromium(chromium, path, screenshot):
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, args=ARGS)
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        errors = []
        page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda e: errors.append(str(e)))
        requests = []
        page.on("request", lambda r: requests.append(r.url) if not r.url.startswith(("file:", "data:")) else None)
        page.goto(path.as_uri())
        page.wait_for_load_state("load")
        images = page.evaluate(
            "Array.from(document.images).map(i => [i.alt, i.complete, i.naturalWidth, i.naturalHeight])"
        )
        durations = page.evaluate("""async () => Promise.all(Array.from(document.querySelectorAll('video')).map(v =>
            new Promise(done => { if (v.readyState >= 1) done(v.duration);
              v.addEventListener('loadedmetadata', () => done(v.duration)); v.addEventListener('error', () => done(-1));
              setTimeout(() => done(-2), 10000); })))""")
        height = page.evaluate("document.documentElement.scrollHeight")
        # the page's first 4000 px: the whole page is ~77,000 px tall (~100 Mpx), slow to render and decode
        page.screenshot(
            path=str(screenshot), full_page=True, clip={"x": 0, "y": 0, "width": 1280, "height": min(height, 4000)}
        )
        browser.close()
    return errors, images, durations, requests, height


@pytest.fixture(scope="module")
def report(default_run, tmp_path_factory):
    proj, _ = default_run
    out = tmp_path_factory.mktemp("report") / "report.html"
    first = run_cli(proj, "report", "-o", out)
    assert first.returncode == 0, first.stderr
    return proj, out, first


def test_report_is_self_contained_and_renders_in_chromium(report, chromium, tmp_path):
    proj, out, _ = report
    page = out.read_text()
    assert "http://" not in page.replace("http://www.w3.org/2000/svg", "") and "https://" not in page
    for caption in REQUIRED_FIGURES:
        assert caption in page, caption
    errors, images, durations, requests, height = open_in_chromium(chromium, out, tmp_path / "shot.png")
    assert errors == []
    assert requests == []  # nothing fetched from the network
    assert len(images) >= len(REQUIRED_FIGURES) - 1
    assert all(complete and w > 0 and h > 0 for _, complete, w, h in images), images
    assert durations and all(d > 0.5 for d in durations), durations
    import numpy as np
    from PIL import Image

    shot = np.asarray(Image.open(tmp_path / "shot.png").convert("L"), dtype=float)
    assert height > 3000 and shot.shape[0] == 4000 and shot.std() > 20  # a long page with content, not a blank one


def test_report_shows_graph_states_params_keys_and_metrics(report, default_run):
    _, out, _ = report
    _, result = default_run
    page = out.read_text()
    assert page.count("<rect") >= len(result.states)  # one box per stage in the graph
    assert result.key("aam")[:16] in page and "shape_variance: 0.98" in page
    assert re.search(r"<td>blend</td><td>clipped_fraction</td>", page)


def test_second_report_renders_nothing(report, tmp_path):
    proj, _, first = report
    again = run_cli(proj, "report", "-o", tmp_path / "again.html")
    assert again.returncode == 0
    assert re.search(r"\(\d+\.\d MB, (\d+) figures, 0 rendered\)", again.stderr), again.stderr
    assert "0 rendered" not in first.stderr


def test_report_of_a_failed_run_colours_the_failure(numproject, tmp_path):
    (numproject / "broken.yaml").write_text(
        "version: 1\nstages:\n  ok:\n    uses: numstages.basic:Source\n"
        "  broken:\n    uses: numstages.basic:Broken\n    params: {mode: crash}\n"
    )
    assert run_cli(numproject, "run", "broken.yaml", "-q").returncode == 1
    out = tmp_path / "failed.html"
    assert run_cli(numproject, "report", "-f", "broken.yaml", "-o", out).returncode == 0
    page = out.read_text()
    assert "<h2>Failures</h2>" in page and "RuntimeError: boom" in page and "#fb6a4a" in page


@pytest.fixture
def long_params_report(numproject, tmp_path):
    """The report of a run whose stage has a params value far wider than the page (one unbroken word)."""
    (numproject / "long.yaml").write_text(
        "version: 1\nstages:\n  broken:\n    uses: numstages.basic:Broken\n"
        f"    params: {{mode: {'crash' + 'x' * 600}}}\n"
    )
    assert run_cli(numproject, "run", "long.yaml", "-q").returncode == 1
    out = tmp_path / "long.html"
    assert run_cli(numproject, "report", "-f", "long.yaml", "-o", out).returncode == 0
    return out


def test_the_params_column_wraps_long_values(long_params_report):
    page = long_params_report.read_text()
    assert "td.params pre{white-space:pre-wrap;overflow-wrap:anywhere}" in page
    assert "<td class='params'><pre>mode: &quot;crashxxx" in page


def test_long_params_keep_the_page_within_the_window(long_params_report, chromium):
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, args=ARGS)
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        page.goto(long_params_report.as_uri())
        width = page.evaluate("document.documentElement.scrollWidth")
        browser.close()
    assert width <= 1280


def test_sweep_report_has_table_and_metric_plots(numproject, chromium, tmp_path):
    result = run_cli(numproject, "sweep", "-S", "src.n=3,4,5", "-q")
    assert result.returncode == 0
    sweep_id = re.search(r"sweep (\S+):", result.stderr).group(1)
    out = tmp_path / "sweep.html"
    made = run_cli(numproject, "report", sweep_id, "-o", out, "--metric", "total.total")
    assert made.returncode == 0, made.stderr
    page = out.read_text()
    assert "<th>src.n</th>" in page and "total.total vs src.n" in page
    errors, images, _, _, _ = open_in_chromium(chromium, out, tmp_path / "sweep.png")
    assert errors == [] and len(images) == 1 and images[0][2] > 0


def test_a_sweep_report_of_a_metric_the_sweep_has_not_is_a_user_error(numproject, tmp_path):
    result = run_cli(numproject, "sweep", "-S", "src.n=3,4", "-q")
    sweep_id = re.search(r"sweep (\S+):", result.stderr).group(1)
    made = run_cli(numproject, "report", sweep_id, "-o", tmp_path / "s.html", "--metric", "total.nope")
    assert made.returncode == 2 and "no metric 'total.nope'" in made.stderr and "total.total" in made.stderr
    assert not (tmp_path / "s.html").exists()


def test_a_report_writes_nothing_outside_the_project(numproject, tmp_path):
    """matplotlib would make its configuration folder and font list in the home folder on first use; the report
    points it into the store's cache folder instead (a user's own MPLCONFIGDIR is kept)."""
    home = tmp_path / "home"
    home.mkdir()
    unset = ("XDG_CONFIG_HOME", "XDG_CACHE_HOME", "MPLCONFIGDIR")
    env = {**{k: v for k, v in cli_env().items() if k not in unset}, "HOME": str(home)}

    def msflow(*args):
        command = [sys.executable, "-m", "msflow.cli", *map(str, args)]
        return subprocess.run(command, cwd=numproject, env=env, capture_output=True, text=True, timeout=120)

    swept = msflow("sweep", "-S", "src.n=3,4", "-q")
    made = msflow("report", re.search(r"sweep (\S+):", swept.stderr).group(1), "-o", tmp_path / "sweep.html")
    assert made.returncode == 0, made.stderr
    assert list(home.rglob("*")) == []
    assert list((numproject / ".msflow" / "cache" / "matplotlib").glob("fontlist*.json"))


def test_report_before_any_run_is_a_user_error(numproject, tmp_path):
    result = run_cli(numproject, "report", "-o", tmp_path / "r.html")
    assert result.returncode == 2 and "no run of this pipeline yet" in result.stderr


def test_a_report_that_cannot_be_written_is_a_user_error(numproject, tmp_path):
    assert run_cli(numproject, "run", "-q").returncode == 0
    (tmp_path / "a file").write_text("not a folder")
    for out, message in ((tmp_path, "is a folder"), (tmp_path / "a file" / "r.html", "cannot write")):
        result = run_cli(numproject, "report", "-o", out)
        assert result.returncode == 2 and message in result.stderr and "--out" in result.stderr, result.stderr
        assert "Traceback" not in result.stderr
