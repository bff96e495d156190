"""Screenshots of a web page in headless Chromium, driven over the DevTools protocol.

Used by the viewer's browser tests and to make the README's screenshot:

  python -m jaxfusion.lab.viewer.browser http://127.0.0.1:8080 docs/viewer.png --wait 8

Chromium renders WebGL in software (SwiftShader), so no GPU is needed. Needs the `chromium`
executable (Debian: `apt-get install chromium`) and `websockets` (installed with viser).
"""

import argparse
import base64
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.request
from typing import Callable, Optional, Sequence

import numpy as np

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
CHROMIUM_FLAGS = (
    "--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader", "--disable-dev-shm-usage", "--no-first-run",
    "--no-default-browser-check", "--hide-scrollbars", "--mute-audio",
)
# The viser page warns about software WebGL when it can read the renderer's name; hide the
# name (the rendering itself is unchanged) so that screenshots show the scene, not the notice.
_HIDE_RENDERER_NAME = """
for (const C of [self.WebGLRenderingContext, self.WebGL2RenderingContext]) {
  if (!C) continue;
  const original = C.prototype.getExtension;
  C.prototype.getExtension = function (name) {
    return name === "WEBGL_debug_renderer_info" ? null : original.call(this, name);
  };
}
"""


def find_chromium() -> Optional[str]:
  """Path of a Chromium (or Chrome) executable on PATH, or None."""
  return next((p for p in map(shutil.which, CHROMIUM_NAMES) if p), None)


def decode_png(data: bytes) -> np.ndarray:
  """PNG bytes → `(H, W, 3) uint8` RGB."""
  import cv2
  image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
  if image is None:
    raise ValueError("not a PNG image")
  return image[:, :, ::-1].copy()


class HeadlessPage:
  """One page of a headless Chromium, opened on `url`; close it (or use `with`).

  Args:
    url: the page.
    width, height: viewport in CSS pixels.
    chromium: the executable (default: `find_chromium()`).
    timeout: seconds to wait for the browser to start.
    init_scripts: JavaScript sources run in the page before its own scripts (e.g. to
      instrument WebGL).
  """

  def __init__(self, url: str, *, width: int = 1280, height: int = 800,
               chromium: Optional[str] = None, timeout: float = 30.0,
               init_scripts: Sequence[str] = ()):
    from websockets.sync.client import connect
    chromium = chromium or find_chromium()
    if chromium is None:
      raise FileNotFoundError("no chromium executable on PATH (Debian: apt-get install chromium)")
    if width < 1 or height < 1:
      raise ValueError(f"viewport must be at least 1x1; got {width}x{height}")
    self._profile = tempfile.mkdtemp(prefix="jaxfusion-chromium-")
    self._log = open(os.path.join(self._profile, "chromium.log"), "wb")
    self._process = subprocess.Popen(
        [chromium, *CHROMIUM_FLAGS, f"--user-data-dir={self._profile}",
         "--remote-debugging-port=0", f"--window-size={width},{height}", "about:blank"],
        stdout=self._log, stderr=subprocess.STDOUT)
    self._ws, self._next_id, self._events = None, 0, set()
    try:
      port = self._devtools_port(timeout)
      deadline = time.monotonic() + timeout
      while True:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5) as r:
          pages = [t for t in json.load(r) if t.get("type") == "page"]
        if pages or time.monotonic() > deadline:
          break
        time.sleep(0.1)
      if not pages:
        raise RuntimeError("chromium opened no page")
      self._ws = connect(pages[0]["webSocketDebuggerUrl"], max_size=256 * 2**20,
                         open_timeout=timeout)
      self.call("Page.enable")
      for source in (_HIDE_RENDERER_NAME, *init_scripts):
        self.call("Page.addScriptToEvaluateOnNewDocument", source=source)
      self.call("Emulation.setDeviceMetricsOverride", width=width, height=height,
                deviceScaleFactor=1, mobile=False)
      self.call("Page.navigate", url=url)
      self._wait_for_event("Page.loadEventFired", timeout)
    except BaseException:
      self.close()
      raise

  def _devtools_port(self, timeout: float) -> int:
    path = os.path.join(self._profile, "DevToolsActivePort")
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
      if self._process.poll() is not None:
        raise RuntimeError(f"chromium exited with status {self._process.returncode}: "
                           f"{self.log_tail()}")
      if os.path.exists(path):
        with open(path) as f:
          first = f.readline().strip()
        if first.isdigit():
          return int(first)
      time.sleep(0.05)
    raise TimeoutError(f"chromium did not open its DevTools port in {timeout} s")

  def log_tail(self, chars: int = 2000) -> str:
    """The end of Chromium's own log (for error messages)."""
    try:
      with open(os.path.join(self._profile, "chromium.log"), "rb") as f:
        return f.read().decode(errors="replace")[-chars:]
    except OSError:
      return ""

  def call(self, method: str, timeout: float = 60.0, **params) -> dict:
    """Sends one DevTools command and returns its result (events in between are skipped)."""
    self._next_id += 1
    ident = self._next_id
    self._ws.send(json.dumps({"id": ident, "method": method, "params": params}))
    deadline = time.monotonic() + timeout
    while True:
      message = json.loads(self._ws.recv(timeout=max(deadline - time.monotonic(), 0.01)))
      if message.get("id") == ident:
        if "error" in message:
          raise RuntimeError(f"{method}: {message['error']}")
        return message.get("result", {})
      if "method" in message:
        self._events.add(message["method"])

  def _wait_for_event(self, name: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while name not in self._events:
      remaining = deadline - time.monotonic()
      if remaining <= 0:
        raise TimeoutError(f"the page sent no {name} within {timeout} s")
      try:
        message = json.loads(self._ws.recv(timeout=remaining))
      except TimeoutError:
        continue
      if "method" in message:
        self._events.add(message["method"])

  def evaluate(self, expression: str):
    """The value of a JavaScript expression in the page."""
    result = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
    return result.get("result", {}).get("value")

  def drag(self, start: tuple, end: tuple, *, steps: int = 10) -> None:
    """Drags the mouse with the left button held from `start` to `end` (CSS pixels)."""
    (x0, y0), (x1, y1) = start, end
    self.call("Input.dispatchMouseEvent", type="mouseMoved", x=x0, y=y0)
    self.call("Input.dispatchMouseEvent", type="mousePressed", x=x0, y=y0, button="left",
              buttons=1, clickCount=1)
    for i in range(1, steps + 1):
      x, y = x0 + (x1 - x0) * i / steps, y0 + (y1 - y0) * i / steps
      self.call("Input.dispatchMouseEvent", type="mouseMoved", x=x, y=y, button="left",
                buttons=1)
      time.sleep(0.02)
    self.call("Input.dispatchMouseEvent", type="mouseReleased", x=x1, y=y1, button="left",
              buttons=0, clickCount=1)

  def screenshot_png(self) -> bytes:
    return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])

  def screenshot(self) -> np.ndarray:
    """The page as it is now: `(H, W, 3) uint8` RGB."""
    return decode_png(self.screenshot_png())

  def wait_for(self, predicate: Callable[[np.ndarray], bool], *, timeout: float = 30.0,
               interval: float = 0.5) -> np.ndarray:
    """Screenshots until `predicate(image)` holds; returns that image.

    Raises:
      TimeoutError: it did not hold within `timeout` seconds.
    """
    deadline = time.monotonic() + timeout
    while True:
      image = self.screenshot()
      if predicate(image):
        return image
      if time.monotonic() > deadline:
        raise TimeoutError(f"the page did not show what was expected within {timeout} s")
      time.sleep(interval)

  def close(self) -> None:
    if self._ws is not None:
      try:
        self._ws.close()
      except Exception:   # the browser may already be gone; closing must not fail
        pass
      self._ws = None
    if self._process.poll() is None:
      self._process.terminate()
      try:
        self._process.wait(timeout=10)
      except subprocess.TimeoutExpired:
        self._process.kill()
        self._process.wait()
    self._log.close()
    shutil.rmtree(self._profile, ignore_errors=True)

  def __enter__(self) -> "HeadlessPage":
    return self

  def __exit__(self, *exc) -> None:
    self.close()


def main(argv=None) -> int:
  p = argparse.ArgumentParser(prog="python -m jaxfusion.lab.viewer.browser",
                              description="Screenshot a web page (e.g. the viewer) in headless "
                                          "Chromium.")
  p.add_argument("url")
  p.add_argument("out", help="PNG file")
  p.add_argument("--size", default="1280x800", help="viewport WIDTHxHEIGHT")
  p.add_argument("--wait", type=float, default=8.0, help="seconds to let the page render")
  args = p.parse_args(argv)
  try:
    width, height = (int(v) for v in args.size.lower().split("x"))
  except ValueError:
    print(f"--size must be WIDTHxHEIGHT; got {args.size!r}", file=sys.stderr)
    return 2
  try:
    with HeadlessPage(args.url, width=width, height=height) as page:
      time.sleep(args.wait)
      data = page.screenshot_png()
  except (FileNotFoundError, ValueError, RuntimeError, TimeoutError) as e:
    print(f"screenshot: error: {e}", file=sys.stderr)
    return 2
  from jaxfusion import io

  def write(tmp):
    with open(tmp, "wb") as f:
      f.write(data)

  io.atomic_write(args.out, write)
  print(f"wrote {args.out}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
