"""``run --view live`` in a real browser: headless Chromium (Debian's chromium + chromium-driver,
installed by .ci/run) loads the viewer page served by the run, and the screenshot must show the
deformed mesh in the 3-D view in the colours of its displacement, and the camera frame, the depth
map and the force in their panels. No network is needed (CI has none)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from test_runtime_support import build_test_plugin

from tactile_deploy.runtime.predictor import MeshPredictor
from tactile_deploy.runtime.sources.npz import load_clip

CHROMIUM = os.environ.get("CHROMIUM", "/usr/bin/chromium")
CHROMEDRIVER = os.environ.get("CHROMEDRIVER", "/usr/bin/chromedriver")
#: Browser window (CSS px); the screenshot is the page's viewport.
WINDOW = (1280, 800)


@pytest.fixture(scope="module")
def plugin(tmp_path_factory):
    return build_test_plugin(tmp_path_factory.mktemp("plugins") / "testsensor", n_frames=6)


@pytest.fixture(scope="module")
def browser():
    """Headless Chromium through chromedriver; a missing browser fails the test (CI installs it)."""
    if not (shutil.which(CHROMIUM) and shutil.which(CHROMEDRIVER)):
        pytest.fail(f"headless browser test needs {CHROMIUM} and {CHROMEDRIVER}: install Debian's "
                    "packages chromium and chromium-driver (apt-get install -y chromium "
                    "chromium-driver; .ci/run does), or set CHROMIUM / CHROMEDRIVER")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader", "--disable-dev-shm-usage", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                f"--window-size={WINDOW[0]},{WINDOW[1]}"):
        opts.add_argument(arg)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)
    driver.set_page_load_timeout(120)
    yield driver
    driver.quit()


def _viridis_distance(pixels: np.ndarray, colours: np.ndarray) -> np.ndarray:
    """Distance of each pixel (m, 3) to the nearest of ``colours`` (k, 3), RGB units."""
    d = np.full(len(pixels), np.inf)
    for c in np.unique(colours, axis=0):
        d = np.minimum(d, np.abs(pixels.astype(np.int32) - c.astype(np.int32)).max(axis=1))
    return d


def test_live_view_draws_the_mesh_frame_depth_and_force_in_a_browser(plugin, browser, tmp_path):
    import cv2

    from tactile_deploy.runtime.forces import ForceEstimator, SurfaceStiffness
    from tactile_deploy.runtime.live_view import LiveView
    from tactile_deploy.runtime.preview import colourise
    from tactile_deploy.runtime.run import Runner, RunOptions
    from tactile_deploy.runtime.sources.base import ArrayPlayback

    predictor = MeshPredictor.from_plugin(plugin)
    topo = predictor.topology
    frames, t, _ = load_clip(plugin.demo_clip_path())
    last = predictor.predict_frame(frames[-1])
    mag = np.linalg.norm(last.displacement_mm, axis=1)
    scale_mm = float(np.percentile(mag, 99.5))          # colours span the whole scale
    n = len(topo.sensing_nodes)
    forces = ForceEstimator(SurfaceStiffness(topo.sensing_nodes, np.eye(n), "identity"), 1.0,
                            topo.rest_vertices_mm, np.ones(n))
    view = LiveView("testsensor", topo, web_port=0, colour_max_mm=scale_mm, max_hz=0)
    url = view.serve()
    summary = Runner(predictor, ArrayPlayback(list(frames), t, "clip"),
                     RunOptions(colour_max_mm=scale_mm), forces=forces, sinks=[view]).run()
    assert summary.sinks["live view"]["shown"] == 6 and not summary.sinks["live view"]["dropped"]

    browser.get(url)
    colours = colourise(mag, scale_mm)                   # the last frame's vertex colours
    high = colours[mag > 0.6 * scale_mm]
    low = colours[mag < 0.2 * scale_mm]
    assert len(high) > 20 and len(low) > 20
    deadline = time.monotonic() + 150
    shot = tmp_path / "live_view.png"
    while True:
        time.sleep(3)
        browser.save_screenshot(str(shot))
        img = cv2.cvtColor(cv2.imread(str(shot)), cv2.COLOR_BGR2RGB)
        h, w = img.shape[:2]
        # the 3-D view: the left two thirds of the page, below the top bar
        mesh_region = img[int(0.1 * h):int(0.9 * h), int(0.02 * w):int(0.62 * w)].reshape(-1, 3)
        near_high = int((_viridis_distance(mesh_region, high) <= 24).sum())
        near_low = int((_viridis_distance(mesh_region, low) <= 24).sum())
        if (near_high > 200 and near_low > 2000) or time.monotonic() > deadline:
            break
    keep = os.environ.get("TACTILE_DEPLOY_SCREENSHOT")
    if keep:
        shutil.copy(shot, keep)
    assert near_low > 2000, f"the mesh's low-displacement colours: {near_low} px ({shot})"
    assert near_high > 200, f"the mesh's high-displacement colours: {near_high} px ({shot})"
    # the right column: camera frame, depth map, force plot, each drawn (not a blank panel)
    right = img[:, int(0.7 * w):]
    for i, what in enumerate(("camera frame", "depth map", "force plot")):
        panel = right[int((0.1 + 0.28 * i) * h):int((0.3 + 0.28 * i) * h)]
        assert panel.std() > 12, f"the {what} panel looks empty ({shot})"
    # the depth map's inferno colours (its deepest pixels are bright orange-yellow)
    depth_panel = right[int(0.38 * h):int(0.58 * h)].reshape(-1, 3)
    inferno_high = colourise(np.linspace(0.5, 1.0, 64), 1.0, cv2.COLORMAP_INFERNO)
    assert (_viridis_distance(depth_panel, inferno_high) <= 24).sum() > 10, shot


def test_cli_view_live_serves_the_page_until_ctrl_c(plugin, tmp_path):
    """`run --view live` prints the page's address, serves it after the clip ended, and stops
    cleanly on Ctrl-C; the page comes from this computer (no network)."""
    cmd = [sys.executable, "-m", "tactile_deploy.cli.main", "run", "--sensor", str(plugin.folder),
           "--view", "live", "--view-port", "0", "--no-forces"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=tmp_path, env={**os.environ, "COLUMNS": "400"},
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    url, lines = None, []
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line:
            break
        lines.append(line)
        if "live view: open" in line:
            url = line.split("open", 1)[1].split()[0]
        if "stays at" in line:
            break
    assert url is not None, "".join(lines)
    assert url.startswith("http://localhost:") and "url=rerun%2Bhttp%3A%2F%2F127.0.0.1" in url
    page = urllib.request.urlopen(url, timeout=30).read().decode()
    assert "re_viewer" in page
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 0, stderr
    assert "live view: " in stdout and "stopped by end of source" in stdout
