"""The live view: its server refuses what it should, and a real headless browser shows the sensor.

The browser tests use Debian's chromium and chromedriver (installed by .ci/run; skipped, saying how to
install them, where they are missing) through selenium.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from contextlib import contextmanager

import numpy as np
import pytest

from optitac_edge.calibration.fibers import calibrate_fibers
from optitac_edge.core.pipeline import Pipeline
from optitac_edge.service.view.live import STAT_FIELDS, LiveView
from optitac_edge.service.view.server import ViewServer, parse_bind
from optitac_edge.sim.sensor import SimulatedSensor
from optitac_edge.sim.skin import Indenter

CHROMIUM, CHROMEDRIVER = shutil.which("chromium"), shutil.which("chromedriver")


class Stats:
    def __init__(self) -> None:
        for name in STAT_FIELDS:
            setattr(self, name, 0)


@contextmanager
def _served(bundle, frames: list[np.ndarray], period_ns: int):
    """A LiveView fed by a pipeline on ``frames`` (one every ``period_ns``), the last one observed, and its
    server."""
    pipeline = Pipeline(bundle)
    view = LiveView(bundle, "gray", rate_hz=1e9)
    stats = Stats()
    t = 0
    for frame in frames:
        pipeline.process_recorded(frame, t)
        stats.frames += 1
        t += period_ns
    view.observe(frames[-1], t, pipeline, stats)
    assert view.wait_published(0) is not None
    server = ViewServer(view, "127.0.0.1:0")
    try:
        yield view, server
    finally:
        server.close()
        view.close()


@pytest.fixture(scope="module")
def fed_view():
    """A LiveView fed by a pipeline on simulated frames (a press in the last one), with its server."""
    sensor = SimulatedSensor(seed=2)
    bundle = calibrate_fibers([sensor.frame(()) for _ in range(8)], "gray")
    press = Indenter("circle", 3.0, -2.0, 0.0, 6.0, 3.0)
    with _served(bundle, [sensor.frame((press,) if k >= 8 else ()) for k in range(12)], 16_666_667) as served:
        yield (*served, bundle)


def _get(url: str, method: str = "GET", headers: dict[str, str] | None = None, data: bytes | None = None):
    req = urllib.request.Request(url, method=method, headers=headers or {}, data=data)
    try:
        with urllib.request.urlopen(req, timeout=5) as r:
            return r.status, r.read(), dict(r.headers)
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read(), dict(exc.headers)


def test_the_view_serves_its_page_the_fiber_map_and_live_data(fed_view) -> None:
    _, server, bundle = fed_view
    base = f"http://127.0.0.1:{server.port}"
    status, page, headers = _get(base + "/")
    assert status == 200 and b'<script src="app.js">' in page and "default-src 'self'" in headers[
        "Content-Security-Policy"]
    assert _get(base + "/app.js")[0] == 200 and _get(base + "/style.css")[0] == 200
    layout = json.loads(_get(base + "/api/layout")[1])
    assert len(layout["fibers"]) == 217 and (layout["width"], layout["height"]) == (640, 480)
    state = json.loads(_get(base + "/api/state")[1])
    import base64

    levels = np.frombuffer(base64.b64decode(state["levels"]), np.uint8)
    assert levels.size == 217 and np.median(levels) > 50
    assert state["surface"]["n"] ** 2 == len(base64.b64decode(state["surface"]["values"]))
    assert len(state["contacts"]) == 1
    c = state["contacts"][0]
    assert abs(c["x_mm"] - 3.0) < 1.0 and abs(c["y_mm"] + 2.0) < 1.0
    u, v = bundle.transform.layout_to_image(np.array([[c["x_mm"], c["y_mm"]]]))[0]
    assert abs(c["u"] - u) < 0.2 and abs(c["v"] - v) < 0.2
    status, jpeg, headers = _get(base + "/api/frame.jpg")
    assert status == 200 and jpeg[:2] == b"\xff\xd8" and headers["Content-Type"] == "image/jpeg"


def test_actions_need_the_header_and_reach_the_loop(fed_view) -> None:
    view, server, _ = fed_view
    base = f"http://127.0.0.1:{server.port}"
    assert _get(base + "/api/tare", "POST")[0] == 403  # a cross-site form cannot set X-OptiTac
    assert _get(base + "/api/tare", "POST", {"X-OptiTac": "1"})[0] == 200
    assert view.actions and view.actions[-1][0] == "tare"
    view.actions.clear()
    status, png, _ = _get(base + "/api/snapshot", "POST", {"X-OptiTac": "1"})
    assert status == 200 and png[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("request_bytes, status", [
    (b"GET /" + b"a" * 300 + b" HTTP/1.1\r\nHost: localhost\r\n\r\n", b"414"),
    (b"POST /api/tare HTTP/1.1\r\nHost: localhost\r\nX-OptiTac: 1\r\nContent-Length: 99999\r\n\r\n", b"413"),
    (b"GET /api/state HTTP/1.1\r\nHost: evil.example\r\n\r\n", b"403"),
    (b"GET /../../etc/passwd HTTP/1.1\r\nHost: localhost\r\n\r\n", b"404"),
    (b"PUT /api/tare HTTP/1.1\r\nHost: localhost\r\n\r\n", b"405"),
    (b"\x16\x03\x01\x02\x00garbage\r\n\r\n", b"400"),
    (b"GET /api/state?after=abc HTTP/1.1\r\nHost: localhost\r\n\r\n", b"400"),
    # '\u00b2' is a digit to str.isdigit() and not to int(): a ValueError traceback closed the connection
    (b"GET /api/state?after=%C2%B2 HTTP/1.1\r\nHost: localhost\r\n\r\n", b"400"),
])
def test_malformed_or_oversized_requests_are_refused_and_the_server_goes_on(fed_view, request_bytes, status) -> None:
    _, server, _ = fed_view
    with socket.create_connection(("127.0.0.1", server.port), timeout=5) as s:
        s.sendall(request_bytes)
        reply = s.recv(4096)
    # a request line that is not HTTP gets http.server's bare error page (HTTP/0.9 has no status line)
    assert reply.split(b" ")[1] == status if reply.startswith(b"HTTP/") else b"Error code: " + status in reply
    assert _get(f"http://127.0.0.1:{server.port}/api/layout")[0] == 200


def test_bound_beyond_localhost_actions_need_the_token(fed_view) -> None:
    view, _, _ = fed_view
    with ViewServer(view, "0.0.0.0:0") as server:
        assert server.token and f"?token={server.token}" in server.url
        base = f"http://127.0.0.1:{server.port}"
        assert _get(base + "/api/state")[0] == 200  # reading needs no token
        assert _get(base + "/api/tare", "POST", {"X-OptiTac": "1"})[0] == 403
        assert _get(base + "/api/tare", "POST", {"X-OptiTac": "1", "X-OptiTac-Token": "wrong"})[0] == 403
        assert _get(base + "/api/tare", "POST", {"X-OptiTac": "1", "X-OptiTac-Token": server.token})[0] == 200
    view.actions.clear()


def test_slow_clients_neither_hold_a_connection_for_ever_nor_keep_others_from_an_answer(fed_view, monkeypatch) -> None:
    """16 clients sending a header line every 2 s took every slot for ever (the 5 s timeout was per read):
    now a request has 5 s in all, and clients still sending do not keep others from being answered."""
    import threading

    from optitac_edge.service.view import server as view_server

    _, server, _ = fed_view
    monkeypatch.setattr(view_server, "TIMEOUT_S", 1.5)  # a line every 0.6 s: each read well within it
    slow = [socket.create_connection(("127.0.0.1", server.port), timeout=10) for _ in range(16)]
    stop = threading.Event()

    def dribble() -> None:
        for s in slow:
            s.sendall(b"GET /api/state HTTP/1.1\r\nHost: localhost\r\n")
        while not stop.wait(0.6):
            for s in slow:
                try:
                    s.sendall(b"X-Slow: 1\r\n")
                except OSError:
                    pass

    thread = threading.Thread(target=dribble, daemon=True)
    thread.start()
    try:
        time.sleep(0.5)
        started = time.monotonic()
        assert _get(f"http://127.0.0.1:{server.port}/api/layout")[0] == 200
        assert time.monotonic() - started < 2.0
        closed = 0
        for s in slow:  # cut off once their 5 s are up
            s.settimeout(view_server.TIMEOUT_S + 3)
            try:
                closed += s.recv(1) == b""
            except OSError:
                closed += 1
        assert closed == 16
    finally:
        stop.set()
        for s in slow:
            s.close()


def test_a_body_that_never_comes_holds_no_answer_slot(fed_view) -> None:
    """16 connections that send a Content-Length and no body held every answer slot (a GET waited 4.2 s): the
    slot was taken after the headers, the body read while holding it (issue 38, item 22). The body is now read
    before a slot is taken."""
    from optitac_edge.service.view import server as view_server

    _, server, _ = fed_view
    hold = [socket.create_connection(("127.0.0.1", server.port), timeout=10) for _ in range(view_server.MAX_CLIENTS)]
    try:
        for s in hold:
            s.sendall(b"POST /api/tare HTTP/1.1\r\nHost: localhost\r\nX-OptiTac: 1\r\nContent-Length: 100\r\n\r\n")
        answering = server._server.answering
        deadline = time.monotonic() + 1.5  # the server has read their headers well before
        fewest = view_server.MAX_CLIENTS
        while time.monotonic() < deadline:
            fewest = min(fewest, answering._value)
            time.sleep(0.05)
        # none held by them: they wait for their bodies slotless (before the fix all 16 were, 0 free); a slot
        # another request of this module's server takes for a moment (one was seen once in CI) is not theirs
        assert fewest > view_server.MAX_CLIENTS // 2, fewest
        assert _get(f"http://127.0.0.1:{server.port}/api/layout")[0] == 200
    finally:
        for s in hold:
            s.close()


def test_a_client_that_goes_away_is_counted_not_a_traceback(fed_view, capfd) -> None:
    _, server, _ = fed_view
    before = getattr(server._server, "client_errors", 0)
    for _ in range(20):
        with socket.create_connection(("127.0.0.1", server.port), timeout=5) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")  # RST
            s.sendall(b"GET /api/frame.jpg HTTP/1.1\r\nHost: localhost\r\n\r\n")
    time.sleep(0.5)
    err = capfd.readouterr().err
    assert "Traceback" not in err and "BrokenPipe" not in err and "ConnectionReset" not in err
    assert _get(f"http://127.0.0.1:{server.port}/api/layout")[0] == 200
    assert server._server.client_errors > before


@pytest.mark.parametrize("bind, host", [("127.0.0.2:0", "127.0.0.2"), ("[::1]:0", "[::1]")])
def test_the_view_answers_its_own_printed_url(fed_view, bind, host) -> None:
    """--bind 127.0.0.2:P answered 403 to its own URL (only 127.0.0.1 and ::1 were taken as this host), and
    --bind [::1]:P could not listen (an IPv4 server)."""
    if host == "[::1]" and not socket.has_ipv6:
        pytest.skip("no IPv6 on this machine")
    view, _, _ = fed_view
    with ViewServer(view, bind) as server:
        assert server.url.startswith(f"http://{host}:{server.port}/")
        assert _get(server.url + "api/layout")[0] == 200
        assert _get(server.url.split("?")[0] + "api/state", headers={"Host": f"evil.example:{server.port}"})[0] == 403


def test_the_frame_loop_never_waits_for_the_view(fed_view) -> None:
    """While the worker holds the buffers, observe() skips the update instead of waiting."""
    view, _, bundle = fed_view
    pipeline = Pipeline(bundle)
    frame = np.zeros((480, 640), np.uint8)
    pipeline.process_recorded(frame, 0)
    view._next_ns = 0
    with view._lock:  # the worker swapping buffers at this instant
        before = view.published.seq
        view.observe(frame, 10**12, pipeline, Stats())  # returns at once
    assert view.published.seq == before


@pytest.mark.parametrize("text", ["8080", "localhost", "host:99999", "example.com:80", ":80"])
def test_bad_bind_addresses_are_one_line(text) -> None:
    from optitac_edge.errors import OptiTacError

    with pytest.raises(OptiTacError, match="HOST:PORT"):
        parse_bind(text)


def test_snapshot_writes_the_picture(tmp_path) -> None:
    from optitac_edge.cli import main

    out = tmp_path / "shot.png"
    assert main(["snapshot", "-o", str(out), "--frames", "3"]) == 0
    import cv2

    picture = cv2.imread(str(out))
    assert picture is not None and picture.shape[1] > 1100
    # the view's picture, not the camera frame beside a black square: 40 % of it was black (0..4)
    assert (picture.max(axis=2) <= 4).mean() < 0.15
    # the surface's colour scale: a column of the colour map's colours, bright at the top, black at the bottom
    bar = np.array([[[v]] for v in np.linspace(255, 0, 40)], np.uint8)
    ramp = cv2.applyColorMap(bar, cv2.COLORMAP_INFERNO)[:, 0]
    found = any(np.abs(picture[:, x].astype(int)[:, None] - ramp[None].astype(int)).max(axis=2).min(axis=0).max() < 12
                for x in range(picture.shape[1] - 1, picture.shape[1] // 2, -1))
    assert found


# -- a real browser -----------------------------------------------------------------------------------

@pytest.fixture
def view_process():
    proc = subprocess.Popen([sys.executable, "-m", "optitac_edge.cli", "view", "--bind", "127.0.0.1:0",
                             "--duration", "120"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    url = None
    assert proc.stdout is not None
    for line in proc.stdout:
        m = re.search(r"view: (http://\S+)", line)
        if m:
            url = m.group(1)
            break
    assert url, "the view did not start"
    yield url
    proc.terminate()
    proc.wait(timeout=10)


def browser():
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--window-size=1400,1000",
                "--disable-dev-shm-usage"):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)


@pytest.mark.skipif(not (CHROMIUM and CHROMEDRIVER),
                    reason="needs a browser: apt-get install chromium chromium-driver (.ci/run does)")
def test_a_headless_browser_shows_217_fibers_and_a_press_as_a_contact(view_process) -> None:
    from selenium.webdriver.common.by import By

    driver = browser()
    try:
        driver.get(view_process)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and driver.execute_script("return document.body.dataset.fibers") != "217":
            time.sleep(0.05)
        assert len(driver.find_elements(By.CSS_SELECTOR, "#fibers [data-fiber]")) == 217
        seen = None
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:  # the simulated sensor presses every second or two
            seen = driver.execute_script(  # read in one go: the page replaces the rows at every update
                "const r = document.querySelector('#contacts tbody tr');"
                "return document.querySelector('#contacts-layer polygon.contact') && r ? r.innerText : null")
            if seen:
                break
            time.sleep(0.02)
        assert seen and re.match(r"1\s+[-+]?\d+\.\d\d, [-+]?\d+\.\d\d", seen), seen
        widths = set()
        for _ in range(100):  # the picture is replaced at every update: one of them loaded
            widths.add(driver.execute_script("return document.getElementById('frame').naturalWidth"))
            if 640 in widths:
                break
            time.sleep(0.05)
        assert 640 in widths
        # the sensor's axes on the camera picture, the dark and saturated levels with the fibers' light
        assert [t.text for t in driver.find_elements(By.CSS_SELECTOR, "#axes text")] == ["+x", "+y"]
        levels = driver.execute_script("const c = document.getElementById('levels');"
                                       "return [c.dataset.darkLevel, c.dataset.saturatedLevel]")
        assert 10 < float(levels[0]) < 120 and float(levels[1]) == 250.0
        assert float(driver.execute_script("return document.getElementById('surface').dataset.max")) >= 0
        driver.find_element(By.ID, "tare").click()
        driver.find_element(By.ID, "snapshot").click()  # it says what happened
        note = ""
        for _ in range(100):
            note = driver.find_element(By.ID, "note").text
            if note.startswith("snapshot saved as optitac-snapshot-"):
                break
            time.sleep(0.05)
        assert note.startswith("snapshot saved as optitac-snapshot-"), note
        errors = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
        assert errors == []
    finally:
        driver.quit()


def test_the_guided_orientation_in_the_view_corrects_the_bundle_and_swaps_the_loops_pipeline(tmp_path) -> None:
    sensor = SimulatedSensor(seed=4)
    rest = [sensor.frame(()) for _ in range(8)]
    right = calibrate_fibers(rest, "gray")
    wrong = calibrate_fibers(rest, "gray", rotation_hint_deg=120.0)
    pipeline = Pipeline(wrong)
    view = LiveView(wrong, "gray", rate_hz=1e9)
    view.bundle_path = tmp_path / "cal.npz"
    swapped: list[Pipeline] = []
    view.swap_pipeline = swapped.append
    stats = Stats()
    try:
        assert view.start_orientation().startswith("orientation: press near the +x edge")
        t = 0
        plan = [None] * 8 + [(8.5, 0.5)] * 60 + [None] * 30 + [(-0.5, 8.8)] * 60 + [None] * 30
        for k, xy in enumerate(plan):
            frame = sensor.frame(() if xy is None else (Indenter("circle", xy[0], xy[1], 0.0, 5.0, 2.5),))
            pipeline.process_recorded(frame, t)
            stats.frames += 1
            before = view.published.seq if view.published else 0
            view._next_ns = 0
            view.observe(frame, t, pipeline, stats)
            assert view.wait_published(before) is not None
            t += 16_666_667
        assert view.procedure is None and view.message.startswith("orientation corrected (the fiber map was rotated")
        view.observe(frame, t, pipeline, stats)  # the loop applies the queued swap between frames
        assert len(swapped) == 1 and np.array_equal(swapped[0].bundle.fibers.pixel_index, right.fibers.pixel_index)
        assert (tmp_path / "cal.npz").exists()
    finally:
        view.close()


def test_the_views_guided_orientation_runs_on_the_simulated_camera(tmp_path) -> None:
    """On the simulated camera a simulated operator does what the view's prompts ask (the simulator's own
    presses ignored them)."""
    from types import SimpleNamespace

    from optitac_edge.cli.commands.run import simulated_operator_for_the_view as _simulated_operator_for_the_view
    from optitac_edge.io.clock import VirtualClock
    from optitac_edge.sim.camera import SimCamera

    # frames 1/60 s apart on a virtual clock (the presses are held and released for so many seconds)
    with SimCamera(realtime=False, clock=VirtualClock()) as camera:
        rest = [camera.read().frame.copy() for _ in range(8)]
        wrong = calibrate_fibers(rest, "gray", rotation_hint_deg=120.0)
        pipeline = Pipeline(wrong)
        view = LiveView(wrong, "gray", rate_hz=1e9)
        view.bundle_path = tmp_path / "cal.npz"
        session = SimpleNamespace(camera=camera, view=view)
        _simulated_operator_for_the_view(session)
        stats = Stats()
        try:
            for _ in range(12):  # the baseline (the simulator's rest frames)
                captured = camera.read()
                pipeline.process_recorded(captured.frame, captured.t_ns)
            assert pipeline.process_recorded(camera.read().frame, captured.t_ns + 1).baseline_ready
            view.start_orientation()
            for _ in range(600):
                captured = camera.read()
                pipeline.process_recorded(captured.frame, captured.t_ns)
                stats.frames += 1
                before = view.published.seq if view.published else 0
                view._next_ns = 0
                view.observe(captured.frame, captured.t_ns, pipeline, stats)
                view.wait_published(before)
                if view.procedure is None:
                    break
            assert view.message.startswith("orientation corrected (the fiber map was rotated")
        finally:
            view.close()


@pytest.fixture(scope="module")
def sliding_view():
    """A LiveView fed by a pipeline at 240 fps on a press held, then slid along +x at 30 mm/s, with its server."""
    from fakes.slide import slide_frames

    bundle = calibrate_fibers([SimulatedSensor(seed=4, fps=240.0).frame(()) for _ in range(8)], "gray")
    with _served(bundle, slide_frames(30, 60, 40, 30.0, seed=4, y_mm=1.0), 4_166_667) as served:
        yield (*served, bundle)


def test_a_sliding_contact_has_an_arrow_along_its_motion_and_the_frame_its_vibration(sliding_view) -> None:
    _, server, bundle = sliding_view
    state = json.loads(_get(f"http://127.0.0.1:{server.port}/api/state")[1])
    (c,) = state["contacts"]
    assert c["sliding"] and abs(c["vx_mm_s"] - 30.0) < 3.0 and abs(c["vy_mm_s"]) < 3.0
    (u0, v0), (u1, v1) = c["arrow"]
    ahead = bundle.transform.layout_to_image(np.array([[c["x_mm"] + 0.25 * c["vx_mm_s"],
                                                        c["y_mm"] + 0.25 * c["vy_mm_s"]]]))[0]
    assert (u0, v0) == (c["u"], c["v"]) and np.allclose((u1, v1), ahead, atol=0.2)  # a quarter of a second on
    assert state["vibration"] is not None and state["vibration"] >= 0 and isinstance(state["vibrating"], bool)


@pytest.mark.skipif(not (CHROMIUM and CHROMEDRIVER),
                    reason="needs a browser: apt-get install chromium chromium-driver (.ci/run does)")
def test_a_headless_browser_draws_the_sliding_contacts_arrow(sliding_view) -> None:
    _, server, _ = sliding_view
    driver = browser()
    try:
        driver.get(f"http://127.0.0.1:{server.port}/")
        found = None
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and not found:
            found = driver.execute_script(
                "const a = document.querySelector('#contacts-layer line.arrow.sliding');"
                "const r = document.querySelector('#contacts tbody tr');"
                "return a && r ? [a.getAttribute('marker-end'), r.innerText, "
                "document.getElementById('figures').textContent] : null")
            time.sleep(0.05)
        assert found, "no arrow drawn"
        marker, row, figures = found
        assert marker == "url(#arrowhead)" and re.search(r"\b(2[7-9]|3[0-3])\.\d sliding\b", row), row
        assert re.search(r"vibration \d+\.\d", figures), figures
        errors = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
        assert errors == []
    finally:
        driver.quit()


@pytest.mark.skipif(not (CHROMIUM and CHROMEDRIVER),
                    reason="needs a browser: apt-get install chromium chromium-driver (.ci/run does)")
def test_at_1280_px_every_panel_is_side_by_side_above_the_fold(view_process) -> None:
    """Before: at a 1280 x 800 window the page was one column, the surface, contacts and fiber light below the
    fold (the camera's section 781 px wide beside a 571 px one). Now two columns from 1000 px, one below."""
    driver = browser()
    try:
        panels = "section.camera, #frame, #surface, #contacts, #levels"
        for size, columns in (((1280, 800), 2), ((1920, 1080), 2), ((800, 1000), 1)):
            driver.set_window_size(*size)
            driver.get(view_process)
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline and not driver.execute_script(
                    "return document.getElementById('frame').naturalWidth"):
                time.sleep(0.05)
            boxes, inner = driver.execute_script(
                "return [[...document.querySelectorAll(arguments[0])].map(e => { const r = e.getBoundingClientRect();"
                " return [r.left, r.top, r.right, r.bottom]; }), [innerWidth, innerHeight]]", panels)
            camera, side = boxes[0], boxes[2]
            assert (side[0] >= camera[2]) == (columns == 2), (size, boxes)
            assert all(b[2] <= inner[0] for b in boxes), (size, boxes)  # nothing wider than the window
            if columns == 2:
                assert all(b[3] <= inner[1] for b in boxes), (size, inner, boxes)  # every panel above the fold
    finally:
        driver.quit()
