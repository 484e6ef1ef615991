"""The web viewer: ``meshseq view`` serves the scene to headless Chromium; playback; port errors.

Needs /usr/bin/chromium and /usr/bin/chromedriver (tools/install_test_deps.sh installs them);
the test fails, never skips, when they are missing. Every wait is bounded.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_file

from meshseq.cli import main
from meshseq.errors import MeshseqError
from meshseq.viewer import ViewItem, Viewer

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--enable-unsafe-swiftshader",  # software WebGL (the scene is three.js)
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--window-size=1200,800",
]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def port_is_free(port: int) -> bool:
    """Whether a server could listen on the port now (old connections in TIME_WAIT allowed)."""
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
            return True
        except OSError:
            return False


@pytest.fixture(scope="module")
def horse():
    data = np.load(shared_file("horse-gallop.npz"))
    return data["vertices"][::4].astype(np.float64), data["faces"].astype(np.int64)


def _browser(profile: str):
    if not CHROMIUM.exists() or not CHROMEDRIVER.exists():
        pytest.fail(f"headless Chromium needs {CHROMIUM} and {CHROMEDRIVER}: run tools/install_test_deps.sh", pytrace=False)
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = str(CHROMIUM)
    for flag in CHROMIUM_FLAGS + [f"--user-data-dir={profile}"]:
        opts.add_argument(flag)
    driver = webdriver.Chrome(options=opts, service=Service(str(CHROMEDRIVER)))
    driver.set_page_load_timeout(30)
    driver.set_script_timeout(30)
    return driver


def _scene_pixels(png: bytes) -> tuple[float, int, int]:
    """Fraction of non-background pixels in the middle of the screenshot, and counts of pixels
    in the two sequences' colours (blue-grey, orange)."""
    import io

    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    h, w = img.shape[:2]
    mid = img[int(0.25 * h) : int(0.9 * h), int(0.15 * w) : int(0.7 * w)]  # clear of the panel and notices
    fg = np.abs(mid - 255).max(axis=-1) > 20
    r, g, b = mid[..., 0], mid[..., 1], mid[..., 2]
    bluish = int((fg & (b - r > 12) & (b > 80)).sum())
    orange = int((fg & (r - b > 50) & (r > 100)).sum())
    return float(fg.mean()), bluish, orange


def test_meshseq_view_serves_the_scene_to_headless_chromium(tmp_path):
    horse_path = str(shared_file("horse-gallop.npz"))
    port = free_port()
    cmd = [sys.executable, "-c", "from meshseq.cli import run; run()", "view", horse_path, horse_path, "--port", str(port)]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    # Ctrl-C must reach the child even when the tests run as a background job (a shell then starts
    # them with SIGINT ignored, which exec passes on): the child starts with SIGINT at its default
    server = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                              preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    driver = None
    try:
        # Wait (bounded) for the command to say where it serves.
        deadline = time.monotonic() + 90
        url = None
        while time.monotonic() < deadline and url is None:
            line = server.stdout.readline()
            if not line:
                if server.poll() is not None:
                    pytest.fail(f"meshseq view exited early: {server.stderr.read()[-2000:]}")
                continue
            if line.startswith("meshseq view: open "):
                url = line.split()[3]
        assert url == f"http://127.0.0.1:{port}/"

        with tempfile.TemporaryDirectory() as profile:
            driver = _browser(profile)
            driver.get(url)
            deadline = time.monotonic() + 60
            shown = (0.0, 0, 0)
            png = b""
            while time.monotonic() < deadline:
                time.sleep(1.0)
                png = driver.get_screenshot_as_png()
                shown = _scene_pixels(png)
                if shown[0] > 0.02 and shown[1] > 400 and shown[2] > 400:
                    break
            (tmp_path / "viewer.png").write_bytes(png)
            frac, bluish, orange = shown
            assert frac > 0.02 and bluish > 400 and orange > 400, (
                f"the scene did not appear: {frac:.3f} non-background, {bluish} blue-grey and {orange} orange "
                f"pixels (screenshot: {tmp_path / 'viewer.png'})"
            )
            driver.quit()
            driver = None
    finally:
        if driver is not None:
            driver.quit()
        server.send_signal(signal.SIGINT)
        try:
            rc = server.wait(timeout=20)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait(timeout=10)
            pytest.fail("meshseq view did not stop on Ctrl-C within 20 s")
    assert rc == 0
    assert port_is_free(port)
    # The port can be served again at once (the browser's old connections may linger in TIME_WAIT).
    data = np.load(horse_path)
    Viewer([ViewItem(data["vertices"][:2], data["faces"], "again")], port=port).stop()


def test_playback_play_pause_and_slider(horse):
    verts, faces = horse
    a = ViewItem(verts, faces, "a")
    b = ViewItem(verts[:5], faces, "b")  # shorter: holds its last frame
    viewer = Viewer([a, b], port=free_port(), fps=50)
    try:
        assert viewer.n_frames == len(verts)
        seen = set()
        for _ in range(20):
            seen.add(int(viewer.frame_slider.value))
            time.sleep(0.011)
        assert len(seen) > 3  # playing advances the frame
        viewer.play_button._impl.value = True  # what a click does: run the button's callbacks
        for cb in viewer.play_button._impl.update_cb:
            cb(None)
        assert not viewer.playing and viewer.play_button.label == "Play"
        time.sleep(0.1)
        held = int(viewer.frame_slider.value)
        time.sleep(0.3)
        assert int(viewer.frame_slider.value) == held  # paused
        viewer.set_frame(8)
        placed_a, placed_b = viewer._placed
        np.testing.assert_allclose(viewer._meshes[0].vertices, placed_a[8])
        np.testing.assert_allclose(viewer._meshes[1].vertices, placed_b[4])
        # Side by side: the two sequences' motions do not overlap along the camera's right axis.
        right = viewer_right = np.asarray(placed_b.reshape(-1, 3).mean(0) - placed_a.reshape(-1, 3).mean(0))
        right = right / np.linalg.norm(viewer_right)
        assert (placed_a.reshape(-1, 3) @ right).max() < (placed_b.reshape(-1, 3) @ right).min()
        # The shapes themselves are the input's, only moved.
        np.testing.assert_allclose(placed_a[3] - placed_a[3].mean(0), verts[3] - verts[3].mean(0), atol=1e-5)
    finally:
        viewer.stop()


def test_port_in_use_is_a_clear_error(horse, capsys):
    verts, faces = horse
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(MeshseqError, match=f"{port}.*in use"):
            Viewer([ViewItem(verts, faces, "a")], port=port)
        assert main(["view", str(shared_file("pcow.npz")), "--port", str(port)]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("meshseq: error: --port") and "in use" in err and "\n" not in err


def test_mismatched_connectivity_is_refused(horse):
    verts, faces = horse
    other = ViewItem(verts[:, :100], faces[:10] % 100, "other")
    with pytest.raises(MeshseqError, match="other.*connectivity"):
        Viewer([ViewItem(verts, faces, "a"), other], port=free_port())
