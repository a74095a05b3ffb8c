"""Headless Chromium driven through the DevTools protocol, for tests that check what a page looks like.

``--dump-dom`` and ``--screenshot`` show the page but not its layout: whether a block lies on the first
screen, or an image decoded, is only known inside the browser. The protocol runs here over
``--remote-debugging-pipe`` (fds 3 and 4, messages ended by a NUL byte), so it needs no websocket library
and no free port. Debian's ``chromium`` is what scripts/bootstrap.sh installs.
"""

from __future__ import annotations

import base64
import contextlib
import fcntl
import json
import os
import select
import subprocess
import tempfile
import time
from typing import Any


class Browser:
    """One page in a headless Chromium with a ``width`` x ``height`` viewport; a context manager, so the
    browser is closed when a test fails halfway."""

    def __init__(self, binary: str, width: int, height: int) -> None:
        to_child, self._write = os.pipe()
        self._read, from_child = os.pipe()
        # above 4, so "3<&" cannot overwrite the other end before "4>&" reads it (bash, not dash: dash's
        # redirections take single-digit fds only)
        ends = [fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 10) for fd in (to_child, from_child)]
        for fd in (to_child, from_child):
            os.close(fd)
        flags = ["--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--remote-debugging-pipe"]
        self._log = tempfile.TemporaryFile()  # noqa: SIM115 (closed in close(), with the browser)
        self._proc = subprocess.Popen(
            ["bash", "-c", f'exec "$0" "$@" 3<&{ends[0]} 4>&{ends[1]}', binary, *flags, "about:blank"],
            pass_fds=ends,
            stdout=self._log,
            stderr=self._log,
        )
        for fd in ends:
            os.close(fd)
        self._buffer = b""
        self._next = 0
        self._events: list[dict[str, Any]] = []
        self._session = ""
        try:
            target = self.call("Target.createTarget", url="about:blank")["targetId"]
            self._session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
            self.call("Page.enable", session=True)
            self.resize(width, height)
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _message(self, deadline: float) -> dict[str, Any]:
        while b"\0" not in self._buffer:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._read], [], [], left)[0]:
                raise TimeoutError("chromium did not answer")
            chunk = os.read(self._read, 1 << 20)
            if not chunk:
                raise RuntimeError(f"chromium closed the pipe; its log ends:\n{self._log_tail()}")
            self._buffer += chunk
        message, self._buffer = self._buffer.split(b"\0", 1)
        return json.loads(message)

    def _log_tail(self) -> str:
        self._log.seek(0)
        return self._log.read().decode(errors="replace")[-2000:]

    def call(self, method: str, session: bool = False, timeout: float = 60.0, **params: Any) -> dict[str, Any]:
        """Send one command (to the page's session if ``session``) and return its result; events that arrive
        meanwhile are kept for :meth:`wait_for`."""
        self._next += 1
        request: dict[str, Any] = {"id": self._next, "method": method, "params": params}
        if session:
            request["sessionId"] = self._session
        try:
            os.write(self._write, json.dumps(request).encode() + b"\0")
        except BrokenPipeError:
            raise RuntimeError(f"chromium is gone; its log ends:\n{self._log_tail()}") from None
        deadline = time.monotonic() + timeout
        while True:
            message = self._message(deadline)
            if message.get("id") == self._next:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message["result"]
            self._events.append(message)

    def wait_for(self, event: str, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while True:
            for k, message in enumerate(self._events):
                if message.get("method") == event:
                    del self._events[k]
                    return
            self._events.append(self._message(deadline))

    def resize(self, width: int, height: int) -> None:
        self.call(
            "Emulation.setDeviceMetricsOverride",
            session=True,
            width=width,
            height=height,
            deviceScaleFactor=1,
            mobile=False,
        )

    def open(self, url: str) -> None:
        """Load ``url`` and wait for its load event (images included)."""
        self._events.clear()
        self.call("Page.navigate", session=True, url=url)
        self.wait_for("Page.loadEventFired")

    def evaluate(self, expression: str) -> Any:
        """The value of a JavaScript expression in the page (JSON-able values only)."""
        return self.call("Runtime.evaluate", session=True, expression=expression, returnByValue=True)["result"]["value"]

    def screenshot(self) -> bytes:
        """The viewport as PNG bytes."""
        return base64.b64decode(self.call("Page.captureScreenshot", session=True, format="png")["data"])

    def close(self) -> None:
        with contextlib.suppress(RuntimeError, TimeoutError, OSError):  # the browser may be gone already
            self.call("Browser.close", timeout=10)
        try:
            self._proc.wait(10)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        os.close(self._read)
        os.close(self._write)
        self._log.close()
