"""The Snakemake HTML report opens in a real browser and every figure in it loads.

``snakemake --report`` writes one self-contained HTML file: a React single-page app whose results
(``var results``: path → {data_uri, ...}; ``var categories``: category → subcategory → paths) are
embedded as data URIs. The landing page draws the rule graph with vega; clicking a category in
the navigation bar lists its results, and the eye button of a row shows the result: for a PNG an
``<img src=data:...>`` in the content pane.

Here headless Chromium (Debian package ``chromium``) opens the report over the DevTools protocol
(tests/browser.py, standard library only), and, with real mouse clicks, navigates the app to
every PNG the workflow writes under ``results/summary/``. For each, the browser itself reports
that the shown ``<img>`` is complete with natural size equal to the PNG file's, its decoded
pixels (drawn to a canvas) match the file's mean colour and are not blank, and the painted
pixels on screen are not blank. A screenshot of the landing page must be non-blank too.
"""

from __future__ import annotations

import base64
import io
import json
import struct
import time

import numpy as np
import pytest

from browser import CHROMIUM_PACKAGE, Chromium, find_chromium
from wfrun import QUICK, snakemake_cli

pytestmark = pytest.mark.skipif(
    find_chromium() is None,
    reason=f"needs headless Chromium: install the Debian package '{CHROMIUM_PACKAGE}' "
           "(scripts/test-deps.sh does so as root)")

# Figures the study must put into the report (besides any other PNG under results/summary/).
REQUIRED = {"figures/fig07_percentile_curves.png", "figures/fig10_multireturn.png",
            "figures/fig11_cbh_cpa_errors.png", "figures/fig12_height_errors.png",
            "pad_validation.png"}

# Helpers installed in the page; every wait is bounded and rejects with a message on timeout.
PAGE_HELPERS = r"""
window.__vls = {
  waitFor(cond, ms, what) {
    return new Promise((resolve, reject) => {
      const t0 = performance.now();
      (function poll() {
        let v;
        try { v = cond(); } catch (err) { v = undefined; }
        if (v) return resolve(true);
        if (performance.now() - t0 > ms) return reject(new Error('timed out waiting for ' + what));
        setTimeout(poll, 50);
      })();
    });
  },
  text(el) { return (el.textContent || '').trim(); },
  home() { return document.querySelector('nav nav ol a'); },
  menuLink(label) {
    return [...document.querySelectorAll('nav li a')].find(a => __vls.text(a) === label);
  },
  row(path) {
    return [...document.querySelectorAll('nav table tbody tr')]
      .find(tr => tr.cells.length > 1 && __vls.text(tr.cells[0]) === path);
  },
  eyeButton(path) {
    const tr = __vls.row(path);
    return tr && tr.cells[tr.cells.length - 1].querySelector('a');
  },
  contentImages() { return [...document.images].filter(img => !img.closest('nav')); },
  async landing() {
    await __vls.waitFor(() => getComputedStyle(document.querySelector('#loading-screen')).display === 'none'
                              && document.querySelector('#app nav'), 20000, 'the app');
    await __vls.waitFor(() => document.querySelector('#rulegraph canvas, #rulegraph svg'), 20000,
                        'the rule graph');
    const g = document.querySelector('#rulegraph canvas, #rulegraph svg').getBoundingClientRect();
    return {title: document.title, nav: __vls.text(document.querySelector('#app nav')),
            menu: [...document.querySelectorAll('nav li a')].map(__vls.text),
            jsWarningShown: getComputedStyle(document.querySelector('#jswarning')).display !== 'none',
            rulegraph: [g.width, g.height]};
  },
  async shownImage(path, ms) {
    const uri = results[path].data_uri;
    await __vls.waitFor(() => __vls.contentImages().some(i => i.getAttribute('src') === uri),
                        ms, 'the <img> of ' + path);
    const imgs = __vls.contentImages();
    const img = imgs.find(i => i.getAttribute('src') === uri);
    await __vls.waitFor(() => img.complete, ms, 'loading ' + path);
    try { await img.decode(); } catch (err) { return {path, error: String(err)}; }
    const c = document.createElement('canvas');
    c.width = img.naturalWidth; c.height = img.naturalHeight;
    const ctx = c.getContext('2d', {willReadFrequently: true});
    ctx.fillStyle = '#fff'; ctx.fillRect(0, 0, c.width, c.height);
    ctx.drawImage(img, 0, 0);
    const d = ctx.getImageData(0, 0, c.width, c.height).data;
    const sum = [0, 0, 0], colours = new Set();
    let nonWhite = 0;
    for (let i = 0; i < d.length; i += 4) {
      sum[0] += d[i]; sum[1] += d[i + 1]; sum[2] += d[i + 2];
      if (d[i] < 250 || d[i + 1] < 250 || d[i + 2] < 250) nonWhite++;
      if (colours.size < 5000) colours.add((d[i] << 16) | (d[i + 1] << 8) | d[i + 2]);
    }
    const n = d.length / 4;
    img.scrollIntoView({block: 'start', inline: 'start'});
    const r = img.getBoundingClientRect();
    return {path, nContentImages: imgs.length, complete: img.complete,
            naturalWidth: img.naturalWidth, naturalHeight: img.naturalHeight,
            box: [r.left, r.top, r.width, r.height], meanRGB: sum.map(s => s / n),
            nonWhiteFraction: nonWhite / n, nColours: colours.size};
  },
};
true
"""


def png_size(path):
    """(width, height) from a PNG file's IHDR chunk."""
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR", path
    return struct.unpack(">II", head[16:24])


def png_mean_rgb(path):
    """Mean R, G, B (0–255) of a PNG file composited over white, as the canvas above does."""
    import matplotlib.image as mpimg

    img = mpimg.imread(path).astype(float)
    rgb = img[..., :3] if img.ndim == 3 else np.repeat(img[..., None], 3, axis=2)
    if img.ndim == 3 and img.shape[2] == 4:
        a = img[..., 3:4]
        rgb = rgb * a + (1 - a)
    return rgb.reshape(-1, 3).mean(axis=0) * 255


def decode_png(data):
    import matplotlib.image as mpimg

    return mpimg.imread(io.BytesIO(data), format="png")


@pytest.fixture(scope="module")
def built_report(quick_run, tmp_path_factory):
    """``snakemake --report`` on the completed quick run, written outside its working directory
    (the shared run's results/ must stay as the workflow left them for the other tests)."""
    workdir, _, _ = quick_run
    report = tmp_path_factory.mktemp("report") / "report.html"
    t0 = time.perf_counter()
    proc = snakemake_cli("--configfile", QUICK, "--report", report, cwd=workdir, timeout=240)
    seconds = time.perf_counter() - t0
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    assert report.is_file()
    print(f"\nsnakemake --report: {seconds:.1f} s")
    return workdir, report


def test_report_opens_in_headless_chromium_with_every_figure_loaded(built_report, tmp_path):
    workdir, report = built_report
    summary = workdir / "results" / "summary"
    pngs = {p.relative_to(summary).as_posix(): p for p in sorted(summary.rglob("*.png"))}
    assert REQUIRED <= set(pngs), sorted(REQUIRED - set(pngs))

    t0 = time.perf_counter()
    with Chromium(tmp_path / "profile", width=1600, height=1000, timeout=30) as browser:
        browser.send("Page.enable")
        browser.send("Runtime.enable")
        browser.send("Page.navigate", {"url": report.as_uri()})
        browser.wait_event("Page.loadEventFired", timeout=60)
        assert browser.evaluate(PAGE_HELPERS) is True

        # The app rendered: loading screen gone, no "enable JavaScript" warning, navigation with
        # the result categories, and the rule graph drawn by vega.
        landing = browser.evaluate("__vls.landing()", timeout=45)
        assert landing["title"] == "Snakemake Report"
        assert not landing["jsWarningShown"]
        assert "Snakemake" in landing["nav"] and "Report" in landing["nav"]
        categories = browser.evaluate("categories")
        assert {"Workflow", "Statistics", "About", *categories} <= set(landing["menu"]), landing
        assert landing["rulegraph"][0] > 100 and landing["rulegraph"][1] > 100, landing

        # Screenshot of the landing page: the size of the window and not blank.
        shot = decode_png(browser.screenshot(tmp_path / "landing.png"))
        assert shot.shape[:2] == (1000, 1600), shot.shape
        rgb = shot[..., :3].reshape(-1, 3)
        assert float(rgb.std()) > 0.05, "landing page screenshot is blank"
        assert len(np.unique((rgb * 255).astype(np.uint8), axis=0)) > 50

        # Every PNG under results/summary/ is a result of the report, in some category.
        in_report = {}
        for cat, subs in categories.items():
            for sub, paths in subs.items():
                for p in paths:
                    in_report[p] = (cat, sub)
        missing = [rel for rel in pngs if f"results/summary/{rel}" not in in_report]
        assert not missing, f"figures not in the report: {missing}"

        for rel, file in pngs.items():
            path = f"results/summary/{rel}"
            cat, sub = in_report[path]
            # Navigate as a user: home → category (→ subcategory) → the row's eye button.
            browser.click("__vls.home()")
            browser.evaluate(f"__vls.waitFor(() => __vls.menuLink({json.dumps(cat)}), 10000, 'menu')")
            browser.click(f"__vls.menuLink({json.dumps(cat)})")
            if len(categories[cat]) > 1:
                browser.evaluate(f"__vls.waitFor(() => __vls.menuLink({json.dumps(sub)}), 10000, 'sub')")
                browser.click(f"__vls.menuLink({json.dumps(sub)})")
            browser.evaluate(f"__vls.waitFor(() => __vls.eyeButton({json.dumps(path)}), 10000, "
                             f"'the row of {path}')")
            browser.click(f"__vls.eyeButton({json.dumps(path)})")
            info = browser.evaluate(f"__vls.shownImage({json.dumps(path)}, 15000)", timeout=30)

            assert "error" not in info, info
            assert info["nContentImages"] == 1, info
            assert info["complete"] and info["naturalWidth"] > 0, info
            assert (info["naturalWidth"], info["naturalHeight"]) == png_size(file), info
            assert info["nonWhiteFraction"] > 0.01 and info["nColours"] > 16, f"{rel} is blank: {info}"
            assert np.allclose(info["meanRGB"], png_mean_rgb(file), atol=1.5), \
                (rel, info["meanRGB"], png_mean_rgb(file))
            # ... and it is painted on screen: the visible part of the <img> is not blank.
            left, top, width, height = info["box"]
            x0, y0 = max(left, 0), max(top, 0)
            w, h = min(left + width, 1600) - x0, min(top + height, 1000) - y0
            assert w > 50 and h > 50, info
            clip = {"x": x0, "y": y0, "width": w, "height": h, "scale": 1}
            painted = decode_png(base64.b64decode(
                browser.send("Page.captureScreenshot", {"format": "png", "clip": clip})["data"]))
            assert float(painted[..., :3].std()) > 0.02, f"{rel} is not painted"

        errors = [ev["params"] for ev in browser.events if ev["method"] == "Runtime.exceptionThrown"]
        assert not errors, errors[:3]
    print(f"\nbrowser check of {len(pngs)} figures: {time.perf_counter() - t0:.1f} s")
