"""A minimal Chrome DevTools Protocol client for headless Chromium, standard library only.

Chromium is started with ``--remote-debugging-pipe``: it reads NUL-terminated JSON commands on
its fd 3 and writes NUL-terminated JSON responses and events on its fd 4. Every read has a
deadline, so nothing here can hang; :meth:`Chromium.close` kills the browser's process group.

Used by tests/test_report_browser.py.
"""

from __future__ import annotations

import base64
import fcntl
import json
import os
import select
import shutil
import signal
import time
from pathlib import Path

#: the DevTools protocol's field that routes a command to an attached target
PAGE_KEY = "sessionId"

CHROMIUM_PACKAGE = "chromium"  # Debian package name (scripts/test-deps.sh installs it)

# The network is closed on these machines: without these flags Chromium blocks on connections.
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-dev-shm-usage", "--hide-scrollbars", "--mute-audio")


def find_chromium():
    """Path of the Chromium executable, or None when it is not installed."""
    for name in ("chromium", "chromium-browser"):
        path = shutil.which(name)
        if path:
            return path
    return None


def _above(fd, lowest=10):
    """Duplicate ``fd`` onto a number >= ``lowest`` (close-on-exec) and close the original."""
    new = fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, lowest)
    os.close(fd)
    return new


class CDPError(RuntimeError):
    pass


class Chromium:
    """Headless Chromium driven over the DevTools pipe; one page target, attached (flat mode)."""

    def __init__(self, user_data_dir, *, executable=None, width=1600, height=1000, timeout=30.0):
        exe = executable or find_chromium()
        if exe is None:
            raise FileNotFoundError(f"Chromium is not installed (Debian package '{CHROMIUM_PACKAGE}')")
        self.timeout = timeout
        self.events = []
        self._buf = b""
        self._next_id = 0
        to_browser_r, self._to_browser = os.pipe()
        self._from_browser, from_browser_w = os.pipe()
        # Keep the browser's ends above fd 4 so that the redirections below cannot clobber them.
        to_browser_r, from_browser_w = (_above(to_browser_r), _above(from_browser_w))
        args = [exe, *FLAGS, "--remote-debugging-pipe", f"--user-data-dir={user_data_dir}",
                f"--window-size={width},{height}", "about:blank"]
        self.stderr_path = Path(str(user_data_dir) + "-stderr.log")
        self._stderr = open(self.stderr_path, "wb")
        try:
            # The browser's ends of the pipes go on its fds 3 and 4; every other descriptor of
            # this process is close-on-exec. setsid: a process group of its own, which close() kills whole.
            self.pid = os.posix_spawn(exe, args, dict(os.environ), setsid=True, file_actions=[
                (os.POSIX_SPAWN_OPEN, 0, os.devnull, os.O_RDONLY, 0),
                (os.POSIX_SPAWN_DUP2, self._stderr.fileno(), 1),
                (os.POSIX_SPAWN_DUP2, self._stderr.fileno(), 2),
                (os.POSIX_SPAWN_DUP2, to_browser_r, 3),
                (os.POSIX_SPAWN_DUP2, from_browser_w, 4),
            ])
        finally:
            os.close(to_browser_r)
            os.close(from_browser_w)
        self.returncode = None
        self.page = None
        try:
            targets = self.send("Target.getTargets")["targetInfos"]
            page = next(t for t in targets if t["type"] == "page")
            attached = self.send("Target.attachToTarget", {"targetId": page["targetId"], "flatten": True})
            self.page = attached[PAGE_KEY]
            # A viewport of exactly width × height CSS pixels (the window has browser chrome).
            self.send("Emulation.setDeviceMetricsOverride", {
                "width": width, "height": height, "deviceScaleFactor": 1, "mobile": False})
        except Exception:
            self.close()
            raise

    # -- protocol -----------------------------------------------------------------------------
    def _read_message(self, deadline):
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError("no message from Chromium before the deadline")
            ready, _, _ = select.select([self._from_browser], [], [], left)
            if not ready:
                continue
            chunk = os.read(self._from_browser, 1 << 20)
            if not chunk:
                raise CDPError(f"Chromium closed the pipe (exit {self.poll()}); "
                               f"stderr: {self.stderr_tail()}")
            self._buf += chunk
        raw, self._buf = self._buf.split(b"\0", 1)
        return json.loads(raw)

    def send(self, method, params=None, *, timeout=None, to_page=True):
        """Send one command (to the attached page unless ``to_page=False``); return its result."""
        self._next_id += 1
        msg = {"id": self._next_id, "method": method, "params": params or {}}
        if to_page and self.page is not None:
            msg[PAGE_KEY] = self.page
        data = json.dumps(msg).encode() + b"\0"
        while data:
            data = data[os.write(self._to_browser, data):]
        deadline = time.monotonic() + (timeout or self.timeout)
        while True:
            reply = self._read_message(deadline)
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise CDPError(f"{method}: {reply['error']}")
                return reply.get("result", {})
            if "method" in reply:
                self.events.append(reply)

    def wait_event(self, method, timeout=None):
        """Return the first event ``method`` received (already or within ``timeout`` s)."""
        deadline = time.monotonic() + (timeout or self.timeout)
        while True:
            for i, ev in enumerate(self.events):
                if ev["method"] == method:
                    return self.events.pop(i)
            ev = self._read_message(deadline)
            if "method" in ev:
                self.events.append(ev)

    def evaluate(self, expression, timeout=None):
        """Evaluate JavaScript in the page (awaiting a returned promise); return its JSON value."""
        t = timeout or self.timeout
        res = self.send("Runtime.evaluate", {"expression": expression, "awaitPromise": True,
                                             "returnByValue": True, "timeout": int(t * 1000)},
                        timeout=t + 5)
        if "exceptionDetails" in res:
            det = res["exceptionDetails"]
            raise CDPError(f"JavaScript exception: {det.get('exception', {}).get('description') or det}")
        return res["result"].get("value")

    def click(self, expression, timeout=10.0):
        """Click, with the mouse, the middle of the element that ``expression`` evaluates to, as
        a user would: scrolled into view, once its box has stopped moving (CSS transitions) and
        the element itself is what the point hits."""
        box = self.evaluate(f"""new Promise((resolve) => {{
            const t0 = performance.now();
            let last = null, still = 0;
            (function poll() {{
                const el = ({expression});
                let box = null;
                if (el) {{
                    el.scrollIntoView({{block: 'nearest', inline: 'nearest'}});
                    const r = el.getBoundingClientRect();
                    box = [r.left + r.width / 2, r.top + r.height / 2, r.width, r.height];
                    const hit = document.elementFromPoint(box[0], box[1]);
                    const same = last && box.every((v, i) => Math.abs(v - last[i]) < 0.5);
                    still = (same && hit && el.contains(hit)) ? still + 1 : 0;
                    last = box;
                    if (still >= 3 && box[2] > 0 && box[3] > 0) return resolve(box);
                }}
                if (performance.now() - t0 > {int(timeout * 1000)}) return resolve(null);
                setTimeout(poll, 50);
            }})();
        }})""", timeout + 5)
        if not box:
            raise CDPError(f"nothing visible and still to click within {timeout} s: {expression}")
        x, y = box[0], box[1]
        self.send("Input.dispatchMouseEvent", {"type": "mouseMoved", "x": x, "y": y})
        for kind in ("mousePressed", "mouseReleased"):
            self.send("Input.dispatchMouseEvent", {"type": kind, "x": x, "y": y,
                                                   "button": "left", "clickCount": 1})

    def screenshot(self, path):
        """Save a PNG screenshot of the viewport to ``path``; return its bytes."""
        data = base64.b64decode(self.send("Page.captureScreenshot", {"format": "png"})["data"])
        Path(path).write_bytes(data)
        return data

    def stderr_tail(self, n=2000):
        try:
            self._stderr.flush()
            return self.stderr_path.read_text(errors="replace")[-n:]
        except OSError:
            return ""

    def poll(self):
        """The browser's exit status, or None while it runs."""
        if self.returncode is None:
            pid, status = os.waitpid(self.pid, os.WNOHANG)
            if pid:
                self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def close(self):
        """Kill Chromium (its whole process group), reap it and release the pipes."""
        try:
            if self.poll() is None:
                try:  # a clean exit lets the browser reap its own helper processes
                    self.send("Browser.close", to_page=False, timeout=5)
                except Exception:
                    pass
                deadline = time.monotonic() + 5
                while self.poll() is None and time.monotonic() < deadline:
                    time.sleep(0.05)
            if self.poll() is None:
                try:
                    os.killpg(self.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                deadline = time.monotonic() + 10
                while self.poll() is None and time.monotonic() < deadline:
                    time.sleep(0.05)
        finally:
            for fd in (self._to_browser, self._from_browser):
                try:
                    os.close(fd)
                except OSError:
                    pass
            self._stderr.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
