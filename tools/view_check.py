"""The live view in a real headless browser during ``optitac-edge bench``'s end-to-end run at 240 fps.

Measures what the acceptance of the view asks, on this machine:
* updates the page shows per second (target >= 15);
* frame-to-page latency: the time the page shows an update minus its frame's capture time
  (both CLOCK_MONOTONIC: the camera stamps frames with it, this script reads it when the DOM changes);
* the first contact on the page after the frame that carried it;
* console errors;
* frames the pipeline dropped with the browser on the view (from the bench's JSON);
and saves a screenshot of the page (docs/figures/view.png).

    python tools/view_check.py [--seconds 60] [--fps 240] [--screenshot docs/figures/view.png]

Needs Debian's chromium and chromium-driver, and selenium (the test extra).
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--fps", type=float, default=240.0)
    ap.add_argument("--screenshot", type=Path, default=Path("docs/figures/view.png"))
    ap.add_argument("--service-nice", type=int, default=0,
                    help="run the bench (the service loop) at this niceness, e.g. -10 as the systemd unit does")
    ap.add_argument("--browser-nice", type=int, default=0,
                    help="run the browser at this niceness (on a robot the browser is on another computer; "
                         "here it shares the board's CPUs)")
    args = ap.parse_args()
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    out = Path(tempfile.mkdtemp()) / "bench.json"
    nice = ["nice", "-n", str(args.service_nice)] if args.service_nice else []
    bench = subprocess.Popen([*nice, sys.executable, "-m", "optitac_edge.cli", "bench", "--frames", "2000",
                              "--reference-frames", "0", "--memory-frames", "0", "--no-startup",
                              "--e2e-seconds", str(args.seconds), "--fps", str(args.fps),
                              "--view", "127.0.0.1:0", "--json", str(out)],
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    url = None
    assert bench.stdout is not None
    for line in bench.stdout:
        print(line.rstrip())
        m = re.search(r"view: (http://\S+)", line)
        if m:
            url = m.group(1)
            break
    if url is None:
        sys.exit("the bench did not start the view")
    options = webdriver.ChromeOptions()
    options.binary_location = "/usr/bin/chromium"
    if args.browser_nice:
        wrapper = Path(tempfile.mkdtemp()) / "chromium"
        wrapper.write_text(f'#!/bin/sh\nexec nice -n {args.browser_nice} /usr/bin/chromium "$@"\n')
        wrapper.chmod(0o755)
        options.binary_location = str(wrapper)
    for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--window-size=1500,1050", "--disable-dev-shm-usage"):
        options.add_argument(a)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=options)
    try:
        driver.get(url)
        offset_ms = (time.time_ns() - time.monotonic_ns()) / 1e6  # CLOCK_MONOTONIC -> the page's epoch clock
        time.sleep(8)
        args.screenshot.parent.mkdir(parents=True, exist_ok=True)
        for _ in range(400):  # a picture with a contact in it
            if driver.execute_script("return document.body.dataset.contacts") not in (None, "0"):
                break
            time.sleep(0.05)
        driver.save_screenshot(str(args.screenshot))
        time.sleep(max(args.seconds - 20, 1))  # the page runs on its own; nothing polls it
        shown = driver.execute_script("return window.optitacShown")
        errors = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
    finally:
        driver.quit()
    seqs = [row[3] for row in shown]
    lat = [row[3] - (row[1] / 1e6 + offset_ms) for row in shown]
    first_contact = next((row[3] - (row[1] / 1e6 + offset_ms) for row in shown if row[2]), None)
    for line in bench.stdout:
        print(line.rstrip())
    bench.wait()
    res = json.loads(out.read_text())["end_to_end"]
    span = (seqs[-1] - seqs[0]) / 1e3 if len(seqs) > 1 else float("nan")
    lat.sort()
    print(json.dumps({
        "page_updates_per_s": round((len(seqs) - 1) / span, 1),
        "frame_to_page_ms": {"median": round(statistics.median(lat), 1), "p99": round(lat[int(0.99 * len(lat))], 1),
                             "max": round(lat[-1], 1)},
        "first_contact_frame_to_page_ms": None if first_contact is None else round(first_contact, 1),
        "console_errors": len(errors), "browser_nice": args.browser_nice,
        "service_nice": args.service_nice,
        "bench": {k: res.get(k) for k in ("fps", "frames", "frames_dropped", "frames_dropped_by_pipeline",
                                          "packets_lost", "achieved_fps", "latency_us", "view")},
        "screenshot": str(args.screenshot)}, indent=1))


if __name__ == "__main__":
    main()
