"""``liris report``: an offline HTML page per run, and its check in a real headless browser."""

from __future__ import annotations

import builtins
import re
import shutil
from importlib.util import find_spec

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli
from test_protocols import two_pass_sequence

from lidar_iris_eval.descriptors import _REGISTRY

needs_plotly = pytest.mark.skipif(find_spec("plotly") is None,
                                  reason="plotly not installed (pip install -e '.[report]')")


@pytest.fixture(autouse=True)
def toys(monkeypatch):
    monkeypatch.setitem(_REGISTRY, "toy", "test_protocols:ToyHist")
    monkeypatch.setitem(_REGISTRY, "toy-asym", "test_protocols:ToyAsym")


@pytest.fixture
def run_dir(tmp_path, capsys):
    seq = two_pass_sequence(tmp_path / "seq", n_per_pass=12)
    code, _, err = run_cli(["eval", seq, "--protocol", "1", "--protocol", "2", "-d",
                            "toy,toy-asym", "--exclude", "5", "--cache-dir", tmp_path / "c",
                            "--out", tmp_path / "run", "-q"], capsys)
    assert code == 0, err
    return tmp_path / "run"


@needs_plotly
def test_report_is_offline_and_embeds_affinity_as_images(run_dir, capsys):
    code, out, err = run_cli(["report", run_dir], capsys)
    assert code == 0, err
    page = (run_dir / "report" / "index.html").read_text()
    js = run_dir / "report" / "plotly.min.js"
    assert js.stat().st_size > 1_000_000  # plotly's bundle, written beside the page
    scripts = re.findall(r"<script[^>]*src=['\"]([^'\"]+)", page)
    assert scripts == ["plotly.min.js"]  # nothing from a CDN
    assert "cdn.plot.ly" not in page
    images = re.findall(r"alt='affinity [^']*' src='data:image/png;base64,", page)
    assert len(images) == 2  # one affinity image per descriptor
    atlas = re.findall(r"alt='failure atlas [^']*' src='data:image/png;base64,", page)
    assert len(atlas) == 2  # and one failure atlas figure per descriptor
    # the affinity matrices are images only: no plotly figure (JSON) in their section
    section = page.split("<div id='affinity'>")[1].split("</div>")[0]
    assert "<script" not in section and section.count("<img") == 2
    assert np.load(run_dir / "protocol2" / "toy" / "affinity.npy").shape == (24, 24)
    for needle in ("id='metrics'", "pr-protocol1", "pr-protocol2", "trajectory",
                   "exclusion: E=5 frames", "true positive"):
        assert needle in page, needle
    # a second report is refused unless asked
    code, _, err = run_cli(["report", run_dir], capsys)
    assert_one_line_error(code, err, "--overwrite")


def test_report_without_plotly_says_how_to_install(run_dir, capsys, monkeypatch):
    real_import = builtins.__import__

    def no_plotly(name, *args, **kwargs):
        if name == "plotly" or name.startswith("plotly."):
            raise ImportError("no plotly")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_plotly)
    code, _, err = run_cli(["report", run_dir], capsys)
    assert_one_line_error(code, err, "pip install 'lidar_iris_eval[report]'")


def _browser():
    """A headless Chromium driven by chromedriver, or a reason to skip."""
    if find_spec("selenium") is None:
        pytest.skip("selenium not installed (pip install -e '.[test]')")
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if chromium is None or driver is None:
        pytest.skip("Chromium not installed (Debian: apt-get install chromium chromium-driver)")
    from selenium import webdriver
    from selenium.common.exceptions import WebDriverException
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--window-size=1200,1400",
                "--disable-dev-shm-usage"):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    try:
        return webdriver.Chrome(service=Service(driver), options=options)
    except WebDriverException as err:
        pytest.skip(f"Chromium could not be started here: {str(err).splitlines()[0]}")


@needs_plotly
def test_report_loads_in_headless_chromium_without_console_errors(run_dir, capsys, tmp_path):
    code, _, err = run_cli(["report", run_dir], capsys)
    assert code == 0, err
    browser = _browser()
    try:
        from selenium.webdriver.support.ui import WebDriverWait

        browser.get((run_dir / "report" / "index.html").resolve().as_uri())
        WebDriverWait(browser, 30).until(lambda b: b.execute_script(
            "return document.querySelectorAll('#pr-protocol1 .scatterlayer .trace').length"))
        n_traces = browser.execute_script(
            "return document.querySelectorAll('#pr-protocol1 .scatterlayer .trace').length")
        assert n_traces == 2  # both descriptors' PR curves were drawn
        assert browser.execute_script("return typeof Plotly") == "object"
        images = browser.execute_script(
            "return Array.from(document.querySelectorAll('#affinity img'))"
            ".map(i => i.complete && i.naturalWidth)")
        assert images == [24, 24]  # decoded PNGs, one pixel per frame
        atlas = browser.execute_script(  # the failure atlas section: one decoded PNG a method
            "return Array.from(document.querySelectorAll('#failure-atlas img'))"
            ".map(i => i.complete && i.naturalWidth > 100)")
        assert atlas == [True, True]
        errors = [e for e in browser.get_log("browser") if e["level"] == "SEVERE"]
        assert errors == []
        shot = tmp_path / "report.png"
        browser.save_screenshot(str(shot))
        assert shot.stat().st_size > 10_000
    finally:
        browser.quit()
