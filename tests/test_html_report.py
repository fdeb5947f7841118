"""The HTML report (`jaxvalve.io.html_report`): what it holds, that it needs no network, and,
in a real headless Chromium, that it loads without script errors and draws the valve.

Chromium comes from the system's packages (`.ci/run` installs Debian's ``chromium``);
where it is missing the browser tests are skipped, unless JAXVALVE_REQUIRE_BROWSER=1 (as
in the CI), which makes a missing browser a failure.
"""
import html
import json
import os
import re
import shutil
import subprocess

import numpy as np
import pytest

from jaxvalve import Scene, simulate
from jaxvalve.io.html_report import METRICS, html_report, write_html_report

FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--virtual-time-budget=5000")


@pytest.fixture(scope="module")
def result():
    """A coarse valve stopped after 40 steps: not converged, still open."""
    return simulate(Scene(h=3.0, max_steps=40), throw=False)


@pytest.fixture(scope="module")
def page(result, tmp_path_factory):
    path = tmp_path_factory.mktemp("report") / "report.html"
    return write_html_report(result, path)


def test_the_page_holds_status_metrics_figures_and_the_mesh(result, page):
    text = page.read_text(encoding="utf-8")
    assert not result.converged
    cls, banner = _banner(text)
    assert cls == "bad" and banner.startswith("NOT CONVERGED")
    assert "residual" in banner and "unconverged state" in banner
    s = result.summary()
    for key, label, unit, _ in METRICS:
        assert re.search(rf"<td>{re.escape(label)}</td><td class='num'>{s[key]:.2f}</td>"
                         rf"<td>{re.escape(unit)}</td>", text), label
    assert text.count("src='data:image/png;base64,") == 3
    # nothing is fetched: no address outside the page
    assert not re.search(r"(src|href)=['\"]?(https?:)?//", text)
    data = json.loads(re.search(r'<script id="valve-data" type="application/json">(.*?)'
                                r"</script>", text, re.S).group(1))
    n = 3 * result.valve.leaflet.n_nodes
    m = 3 * len(result.valve.leaflet.triangles)
    assert len(data["x"]) == 3 * n and len(data["t"]) == 3 * m and len(data["c"]) == 3 * m
    t = np.asarray(data["t"])
    assert t.min() == 0 and t.max() == n - 1
    assert 0 <= min(data["c"]) and max(data["c"]) <= 255
    x = np.asarray(data["x"]).reshape(-1, 3)
    np.testing.assert_allclose(x, np.asarray(result.x) - 0.5 * (np.asarray(result.x).min(0) +
                                                             np.asarray(result.x).max(0)),
                               atol=6e-4)


def _banner(text):
    return re.search(r'<p class="banner (\w+)" id="status">(.*?)</p>', text, re.S).groups()


def test_a_converged_report_says_so(result):
    import dataclasses
    ok = tuple(dataclasses.replace(s, converged=True, result="successful", residual=5e-5)
               for s in result.solves)
    cls, text = _banner(html_report(dataclasses.replace(result, solves=ok)))
    assert cls == "good" and text.startswith("Converged") and "5.0e-05" in text
    lim = (ok[0], dataclasses.replace(ok[1], converged=False, result="limit_point",
                                      limit_pressure=37.9))
    page = html_report(dataclasses.replace(result, solves=lim))
    cls, text = _banner(page)
    assert cls == "bad" and text.startswith("LIMIT POINT") and "37.9 mmHg" in text
    # the warnings (page, JSON, console) say whether the material explains the limit
    assert result.scene.model == "stvk"
    w, = [w for w in dataclasses.replace(result, solves=lim).warnings
          if w.startswith("limit point")]
    assert "stvk stiffens" in w and "not the membrane's inflation limit" in w
    assert html.escape(w) in page
    # the same state shrunk to half its size is compressed past StVK's stability limit
    x = result.x
    half = 0.5 * (x - x.mean(axis=0)) + x.mean(axis=0)
    w, = [w for w in dataclasses.replace(result, solves=lim, x=half).warnings
          if w.startswith("limit point")]
    assert "not the membrane's inflation limit" in w and "past the 0.577 below which" in w
    nh = dataclasses.replace(result, solves=lim,
                             scene=result.scene.replace(model="neo-hookean", E=0.1))
    w, = [w for w in nh.warnings if w.startswith("limit point")]   # P R0 = 1.2394 mu H, mu = E / 3: R0 = P R0 / (37.9 mmHg)
    r0 = 1.2394 * 0.1 / 3 * 0.3 / (37.9 * 1.33322e-4)
    assert "peaks at a stretch of 1.383" in w and f"radius {r0:.2f} mm" in w


def _chromium():
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        if os.environ.get("JAXVALVE_REQUIRE_BROWSER") == "1":
            pytest.fail("JAXVALVE_REQUIRE_BROWSER=1 but no chromium on PATH")
        pytest.skip("no chromium on PATH (the CI installs Debian's chromium)")
    return exe


def _run(args, tmp_path, tag):
    out = subprocess.run([_chromium(), *FLAGS, f"--user-data-dir={tmp_path / tag}", *args],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    return out


def _body(dom):
    return re.search(r"<body([^>]*)>", dom).group(1)


def test_chromium_loads_the_page_without_errors_and_draws_every_triangle(result, page,
                                                                         tmp_path):
    dom = _run(["--dump-dom", page.as_uri()], tmp_path, "dom").stdout
    body = _body(dom)
    assert "data-errors" not in body, body
    m = 3 * len(result.valve.leaflet.triangles)
    assert f'data-rendered="{m}"' in body
    # the error channel works: a page whose data cannot be parsed reports it
    broken = tmp_path / "broken.html"
    broken.write_text(page.read_text(encoding="utf-8").replace(
        '<script id="valve-data" type="application/json">{',
        '<script id="valve-data" type="application/json">{{'), encoding="utf-8")
    body = _body(_run(["--dump-dom", broken.as_uri()], tmp_path, "broken").stdout)
    assert "data-errors=" in body and "data-rendered" not in body


def test_chromium_screenshot_of_the_3d_view_is_not_blank(page, tmp_path):
    import matplotlib.image as mpimg
    dom = _run(["--dump-dom", "--window-size=1000,3000", page.as_uri()], tmp_path,
               "where").stdout
    x, y, w, h = (int(v) for v in re.search(r'data-canvas="([^"]+)"', dom).group(1).split(","))
    shot = tmp_path / "shot.png"
    _run([f"--screenshot={shot}", "--window-size=1000,3000", page.as_uri()], tmp_path, "shot")
    img = mpimg.imread(shot)[..., :3]
    assert img.shape[0] >= y + h and img.shape[1] >= x + w
    view = img[y + 2:y + h - 2, x + 2:x + w - 2]
    ink = np.any(view < 0.95, axis=-1)              # not white
    colours = {tuple(c) for c in np.round(view[ink] * 255).astype(int)[::7]}
    assert 0.05 < ink.mean() < 0.95, ink.mean()     # the valve, inside the frame
    assert len(colours) > 50                        # shaded faces, not one flat fill
    # outside the canvas, the page's margin to its left is white
    assert np.all(img[y + 10:y + h - 10, 2:max(3, x - 6)] > 0.9)
