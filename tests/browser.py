"""A headless Chromium driven over the DevTools protocol, standard library only.

Chromium is started with ``--remote-debugging-pipe``: it reads protocol
messages (JSON, each ended by a NUL byte) from file descriptor 3 and writes
its answers and events to descriptor 4. That needs no port, no websocket and
no Python package beyond the standard library.

Used by ``tests/test_report.py`` (the report loads without console errors and
its figures are not blank) and to make the screenshot docs/report.png::

    python tests/browser.py REPORT.html docs/report.png [HEIGHT_PX]
"""
from __future__ import annotations

import base64
import json
import os
import queue
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-extensions",
    "--disable-default-apps",
    "--hide-scrollbars",
    "--mute-audio",
)


def find_chromium() -> str | None:
    """Path of a Chromium (or Chrome) binary, or None."""
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        p = shutil.which(name)
        if p:
            return p
    return None


class BrowserError(RuntimeError):
    """The browser did not answer as expected."""


class Chromium:
    """One headless Chromium with one page, driven over ``--remote-debugging-pipe``.

    Use as a context manager::

        with Chromium() as b:
            page = b.load("file:///tmp/report.html")
    """

    def __init__(self, binary: str | None = None, *, timeout_s: float = 60.0, extra_flags: tuple = ()):
        self.binary = binary or find_chromium()
        if self.binary is None:
            raise BrowserError("no chromium binary found")
        self.timeout_s = timeout_s
        self._tmp = tempfile.TemporaryDirectory(prefix="psdcal-chromium-")
        self._events: list = []
        self._answers: dict = {}
        self._inbox: queue.Queue = queue.Queue()
        self._next_id = 0
        r_ours, w_theirs = os.pipe()  # chromium writes fd 4 -> we read
        r_theirs, w_ours = os.pipe()  # we write -> chromium reads fd 3
        # the child's ends move to descriptors >= 10 so that redirecting them onto 3 and 4 cannot collide
        r_theirs, w_theirs = (self._high(fd) for fd in (r_theirs, w_theirs))
        args = [*FLAGS, *extra_flags, f"--user-data-dir={self._tmp.name}/profile", "--remote-debugging-pipe", "about:blank"]
        self._log = open(Path(self._tmp.name) / "stderr.txt", "wb")
        self.proc = subprocess.Popen(
            # bash, not sh: dash's redirections take single-digit descriptors only
            [shutil.which("bash") or "/bin/bash", "-c", f'exec "$0" "$@" 3<&{r_theirs} 4>&{w_theirs}', self.binary, *args],
            pass_fds=(r_theirs, w_theirs), stdin=subprocess.DEVNULL, stdout=self._log, stderr=self._log,
        )
        os.close(r_theirs)
        os.close(w_theirs)
        self._rfd, self._wfd = r_ours, w_ours
        self._reader = threading.Thread(target=self._read_loop, daemon=True)
        self._reader.start()
        self.session = None

    @staticmethod
    def _high(fd: int) -> int:
        import fcntl

        new = fcntl.fcntl(fd, fcntl.F_DUPFD, 10)
        os.close(fd)
        return new

    # -- protocol ------------------------------------------------------------------------
    def _read_loop(self):
        buf = b""
        while True:
            try:
                chunk = os.read(self._rfd, 1 << 16)
            except OSError:
                break
            if not chunk:
                break
            buf += chunk
            while b"\0" in buf:
                msg, buf = buf.split(b"\0", 1)
                self._inbox.put(json.loads(msg))
        self._inbox.put(None)

    def _pump(self, until, timeout_s):
        deadline = time.monotonic() + timeout_s
        while not until():
            left = deadline - time.monotonic()
            if left <= 0:
                raise BrowserError("timed out waiting for the browser; its log: " + self.log_text()[-2000:])
            try:
                msg = self._inbox.get(timeout=min(left, 0.5))
            except queue.Empty:
                continue
            if msg is None:
                raise BrowserError("the browser closed its pipe; its log: " + self.log_text()[-2000:])
            if "id" in msg:
                self._answers[msg["id"]] = msg
            else:
                self._events.append(msg)

    def send(self, method: str, params: dict | None = None, *, session: bool = True, timeout_s: float | None = None):
        """Send one command and return its result (raises BrowserError on a protocol error)."""
        self._next_id += 1
        mid = self._next_id
        msg = {"id": mid, "method": method, "params": params or {}}
        if session and self.session is not None:
            msg["sessionId"] = self.session
        data = json.dumps(msg).encode() + b"\0"
        while data:
            n = os.write(self._wfd, data)
            data = data[n:]
        self._pump(lambda: mid in self._answers, timeout_s or self.timeout_s)
        ans = self._answers.pop(mid)
        if "error" in ans:
            raise BrowserError(f"{method}: {ans['error']}")
        return ans.get("result", {})

    def wait_event(self, method: str, timeout_s: float | None = None) -> dict:
        """Wait for (and return) the first not yet consumed event named ``method``."""
        def found():
            return any(e.get("method") == method and not e.get("_seen") for e in self._events)

        self._pump(found, timeout_s or self.timeout_s)
        for e in self._events:
            if e.get("method") == method and not e.get("_seen"):
                e["_seen"] = True
                return e
        raise BrowserError(method)  # pragma: no cover

    def log_text(self) -> str:
        try:
            self._log.flush()
            return (Path(self._tmp.name) / "stderr.txt").read_text(errors="replace")
        except OSError:
            return ""

    # -- use --------------------------------------------------------------------------------
    def open_page(self, width: int = 1200, height: int = 3000):
        """Open a blank page and attach to it (console, log and page events enabled)."""
        target = self.send("Target.createTarget", {"url": "about:blank"}, session=False)["targetId"]
        self.session = self.send("Target.attachToTarget", {"targetId": target, "flatten": True}, session=False)["sessionId"]
        for m in ("Page.enable", "Runtime.enable", "Log.enable"):
            self.send(m)
        self.resize(width, height)

    def resize(self, width: int, height: int):
        self.send("Emulation.setDeviceMetricsOverride",
                  {"width": int(width), "height": int(height), "deviceScaleFactor": 1, "mobile": False})

    def load(self, url: str, timeout_s: float | None = None):
        """Navigate and wait for the load event."""
        if self.session is None:
            self.open_page()
        self.send("Page.navigate", {"url": url})
        self.wait_event("Page.loadEventFired", timeout_s)

    def evaluate(self, expression: str):
        """Evaluate a JavaScript expression in the page and return its (JSON) value."""
        r = self.send("Runtime.evaluate", {"expression": expression, "returnByValue": True, "awaitPromise": True})
        if "exceptionDetails" in r:
            raise BrowserError(f"evaluate: {r['exceptionDetails']}")
        return r["result"].get("value")

    def screenshot(self) -> bytes:
        """PNG bytes of the current viewport."""
        return base64.b64decode(self.send("Page.captureScreenshot", {"format": "png"})["data"])

    def errors(self) -> list:
        """Console errors, uncaught exceptions and failed loads seen so far (as strings)."""
        time.sleep(0.2)  # let late messages arrive, then drain what is there
        while True:
            try:
                msg = self._inbox.get_nowait()
            except queue.Empty:
                break
            if msg is None:
                break
            (self._answers.__setitem__(msg["id"], msg) if "id" in msg else self._events.append(msg))
        out = []
        for e in self._events:
            m, p = e.get("method"), e.get("params", {})
            if m == "Runtime.exceptionThrown":
                d = p.get("exceptionDetails", {})
                out.append("exception: " + str(d.get("exception", {}).get("description") or d.get("text")))
            elif m == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
                out.append("console.error: " + " ".join(str(a.get("value", a.get("description", ""))) for a in p.get("args", [])))
            elif m == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
                ent = p["entry"]
                out.append(f"log ({ent.get('source')}): {ent.get('text')} {ent.get('url', '')}")
        return out

    def close(self):
        try:
            if self.proc.poll() is None:
                try:
                    self.send("Browser.close", session=False, timeout_s=5)
                except (BrowserError, OSError):
                    pass
                try:
                    self.proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait(timeout=10)
        finally:
            for fd in (self._rfd, self._wfd):
                try:
                    os.close(fd)
                except OSError:
                    pass
            self._log.close()
            self._tmp.cleanup()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


FIGURES_JS = """JSON.stringify(Array.from(document.images).map(function (i) {
  var r = i.getBoundingClientRect();
  return {alt: i.alt, complete: i.complete, natural: [i.naturalWidth, i.naturalHeight],
          rect: [r.left + window.scrollX, r.top + window.scrollY, r.width, r.height]};
}))"""


def inspect_page(path, *, width: int = 1200, max_height: int = 16000) -> dict:
    """Load a local HTML file and return what a test needs to judge it.

    Returns
    -------
    dict with ``errors`` (list of str), ``figures`` (list of dicts: alt,
    complete, natural size, rect in CSS px), ``height`` (px) and
    ``screenshot`` (PNG bytes of the whole page, up to ``max_height`` px).
    """
    url = Path(path).resolve().as_uri()
    with Chromium() as b:
        b.open_page(width, 1000)
        b.load(url)
        height = int(b.evaluate("document.documentElement.scrollHeight"))
        b.resize(width, min(height, max_height))
        figures = json.loads(b.evaluate(FIGURES_JS))
        png = b.screenshot()
        errors = b.errors()
    return {"errors": errors, "figures": figures, "height": height, "screenshot": png}


def screenshot(path, out_png, *, width: int = 1200, height: int = 2400) -> None:
    """Write a PNG screenshot of the top ``height`` px of a local HTML file."""
    url = Path(path).resolve().as_uri()
    with Chromium() as b:
        b.open_page(width, height)
        b.load(url)
        Path(out_png).write_bytes(b.screenshot())


if __name__ == "__main__":  # pragma: no cover
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    screenshot(sys.argv[1], sys.argv[2], height=int(sys.argv[3]) if len(sys.argv) > 3 else 2400)
