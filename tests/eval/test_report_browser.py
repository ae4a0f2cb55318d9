"""The comparison page in a real browser: headless Chromium opens index.html offline, with no console errors, the
summary table shows exactly the numbers of metrics.json, and the WebGL 3D view draws something.

Chromium is driven over the DevTools protocol on a pipe (fds 3 and 4, NUL-separated JSON), so no websocket client
and no network port are needed. Run by hand to get a screenshot to look at:
    python tests/eval/test_report_browser.py REPORT/index.html shot.png
"""

import base64
import io
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--remote-debugging-pipe"]


def _pipe_fds_to_3_and_4(read_fd, write_fd):
    """In the child: Chromium reads DevTools commands on fd 3 and writes answers on fd 4."""
    r, w = os.dup(read_fd), os.dup(write_fd)  # first out of the way, as the pipe ends may be 3 or 4 themselves
    os.dup2(r, 3)
    os.dup2(w, 4)


class Browser:
    """A headless Chromium with one page, spoken to over --remote-debugging-pipe."""

    def __init__(self, width=1400, height=1000):
        self.profile = tempfile.mkdtemp(prefix="chromium-profile-")
        to_chrome_r, self._to_chrome = os.pipe()
        self._from_chrome, from_chrome_w = os.pipe()
        self.proc = subprocess.Popen(
            [CHROMIUM, *FLAGS, f"--user-data-dir={self.profile}", "about:blank"],
            pass_fds=(3, 4), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            preexec_fn=lambda: _pipe_fds_to_3_and_4(to_chrome_r, from_chrome_w))
        os.close(to_chrome_r)
        os.close(from_chrome_w)
        self._buf, self._next_id, self.events = b"", 0, []
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        self.session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        for domain in ("Page", "Runtime", "Log"):
            self.call(f"{domain}.enable", session=True)
        self.call("Emulation.setDeviceMetricsOverride", session=True, width=width, height=height,
                  deviceScaleFactor=1, mobile=False)

    def _read_message(self, timeout: float) -> dict:
        import select

        deadline = time.monotonic() + timeout
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._from_chrome], [], [], left)[0]:
                raise TimeoutError("chromium did not answer in time")
            chunk = os.read(self._from_chrome, 1 << 20)
            if not chunk:
                raise RuntimeError("chromium closed the DevTools pipe")
            self._buf += chunk
        raw, self._buf = self._buf.split(b"\0", 1)
        return json.loads(raw)

    def call(self, method, session=False, timeout=60.0, **params):
        self._next_id += 1
        msg = {"id": self._next_id, "method": method, "params": params}
        if session:
            msg["sessionId"] = self.session
        os.write(self._to_chrome, json.dumps(msg).encode() + b"\0")
        while True:
            reply = self._read_message(timeout)
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})
            self.events.append(reply)

    def wait_event(self, method, timeout=60.0):
        for k, e in enumerate(self.events):
            if e.get("method") == method:
                return self.events.pop(k)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            e = self._read_message(deadline - time.monotonic())
            if e.get("method") == method:
                return e
            self.events.append(e)
        raise TimeoutError(f"no {method} within {timeout} s")

    def open(self, url):
        self.call("Page.navigate", session=True, url=url)
        self.wait_event("Page.loadEventFired")

    def evaluate(self, expression):
        result = self.call("Runtime.evaluate", session=True, expression=expression, returnByValue=True,
                           awaitPromise=True)
        if "exceptionDetails" in result:
            raise RuntimeError(f"{expression[:60]}...: {result['exceptionDetails']}")
        return result["result"].get("value")

    def screenshot(self, clip=None) -> bytes:
        params = {"format": "png", "captureBeyondViewport": True}
        if clip:
            params["clip"] = {**clip, "scale": 1}
        return base64.b64decode(self.call("Page.captureScreenshot", session=True, **params)["data"])

    def console_errors(self) -> list[str]:
        errors = []
        for e in self.events:
            p = e.get("params", {})
            if e.get("method") == "Runtime.exceptionThrown":
                errors.append(json.dumps(p.get("exceptionDetails", {}))[:300])
            elif e.get("method") == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
                errors.append(" ".join(str(a.get("value", a.get("description", ""))) for a in p.get("args", [])))
            elif e.get("method") == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
                errors.append(f"{p['entry'].get('source')}: {p['entry'].get('text')} {p['entry'].get('url', '')}")
        return errors

    def close(self):
        try:
            self.call("Browser.close", timeout=10)
        except (RuntimeError, TimeoutError, OSError):
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        os.close(self._to_chrome)
        os.close(self._from_chrome)
        shutil.rmtree(self.profile, ignore_errors=True)


def inspect_page(page: Path, full_shot: Path | None = None) -> dict:
    """Open the page; return its console errors, the summary table's cells and the 3D canvas's pixels."""
    browser = Browser()
    try:
        browser.open(page.resolve().as_uri())
        browser.evaluate("new Promise(r => setTimeout(r, 1500))")  # plotly draws after load
        cells = browser.evaluate("""JSON.stringify([...document.querySelectorAll('#summary td')].map(td =>
            [td.dataset.engine, td.dataset.metric, td.querySelector('.v').textContent,
             td.classList.contains('winner')]))""")
        rect = browser.evaluate("""(() => { const c = document.querySelector('#scene3d canvas');
            if (!c) return null; c.scrollIntoView(); const r = c.getBoundingClientRect();
            return {x: r.left + window.scrollX, y: r.top + window.scrollY, width: r.width, height: r.height}; })()""")
        canvas = None
        if rect and rect["width"] > 0 and rect["height"] > 0:
            from PIL import Image

            canvas = np.asarray(Image.open(io.BytesIO(browser.screenshot(rect))).convert("RGB"))
        if full_shot is not None:
            height = browser.evaluate("document.documentElement.scrollHeight")
            full_shot.write_bytes(browser.screenshot({"x": 0, "y": 0, "width": 1400, "height": height}))
        return {"errors": browser.console_errors(), "cells": json.loads(cells), "canvas": canvas}
    finally:
        browser.close()


@pytest.fixture(scope="module")
def report(colmap_runs, tmp_path_factory):
    """A real comparison page: COLMAP, and COLMAP on that database, on a small synthetic scene against its GT."""
    from mvrecon.eval.compare import compare_models
    from mvrecon.eval.report import write_report

    images, gt, colmap, same = colmap_runs
    comparison = compare_models([colmap.out_dir, same.out_dir], gt=gt)
    return write_report(comparison, tmp_path_factory.mktemp("browser") / "report")


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="chromium not found on PATH (the Makefile's test target installs it)")
def test_page_in_headless_chromium(report):
    from mvrecon.eval import figures
    from mvrecon.eval.report import format_value

    metrics = json.loads((report.parent / "metrics.json").read_text())
    seen = inspect_page(report, report.parent / "page.png")
    assert seen["errors"] == [], seen["errors"]
    expected = {(e, row["metric"]): (format_value(row["metric"], v), e in row["winners"])
                for row in metrics["rows"] for e, v in row["values"].items()}
    shown = {(e, m): (text, win) for e, m, text, win in seen["cells"]}
    assert shown == expected
    assert shown[("colmap", "registered")][0] == str(len(metrics["images"]))
    assert metrics["engines"]["colmap"]["summary"]["auc@5"] > 0.8  # a real, good model made the table
    canvas = seen["canvas"]
    assert canvas is not None and canvas.shape[0] > 300 and canvas.shape[1] > 300
    colours = np.unique(canvas.reshape(-1, 3), axis=0)
    assert len(colours) > 20, f"the 3D canvas looks blank ({len(colours)} colours)"
    # the engines' colours (their frustums and points) are drawn, not just the background and the axes
    drawn = 0
    for engine in metrics["engines"]:
        rgb = [int(figures.ENGINE_COLORS[engine][k:k + 2], 16) for k in (1, 3, 5)]
        drawn += np.all(np.abs(canvas.astype(int) - rgb) < 40, axis=-1).sum()
    assert drawn > 100


if __name__ == "__main__":
    out = inspect_page(Path(sys.argv[1]), Path(sys.argv[2]) if len(sys.argv) > 2 else None)
    print("console errors:", out["errors"])
    print("summary cells:", len(out["cells"]))
    if out["canvas"] is not None:
        print("canvas", out["canvas"].shape, "colours", len(np.unique(out["canvas"].reshape(-1, 3), axis=0)))
