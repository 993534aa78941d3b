"""A real headless Chromium (Debian's chromium + chromium-driver) driven by selenium, for the
browser tests, the screenshots in assets/ and studies/bench_viewer.py.

Software WebGL (SwiftShader), a fixed window size, and free ports for the driver and DevTools.
`chromium_available()` says whether the machine has both binaries.
"""

from __future__ import annotations

import contextlib
import shutil
import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

FLAGS = (
    "--headless=new",
    "--use-gl=angle",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--window-size=1600,1000",
    "--no-sandbox",
    "--disable-dev-shm-usage",
    "--hide-scrollbars",
)


def _binary(*names: str) -> str | None:
    return next((p for n in names if (p := shutil.which(n))), None)


def chromium_available() -> bool:
    return _binary("chromium", "chromium-browser") is not None and _binary("chromedriver") is not None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def chromium() -> Iterator:
    """A selenium WebDriver of headless Chromium; quit on exit."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = _binary("chromium", "chromium-browser")
    for f in FLAGS:
        opts.add_argument(f)
    opts.add_argument(f"--remote-debugging-port={free_port()}")
    driver = webdriver.Chrome(service=Service(_binary("chromedriver"), port=free_port()), options=opts)
    try:
        yield driver
    finally:
        driver.quit()


class CountingProxy:
    """A TCP relay from a free local port to 127.0.0.1:`port` that records every chunk the server sends
    back, (time.monotonic(), bytes): what a browser pointed at `self.port` receives on the wire (viser's
    page talks to the server from a web worker, out of reach of the page's own scripts)."""

    def __init__(self, port: int) -> None:
        self.target = port
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = int(self.listener.getsockname()[1])
        self.received: list[tuple[float, int]] = []
        self._socks: list[socket.socket] = [self.listener]
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:  # closed
                return
            server = socket.create_connection(("127.0.0.1", self.target))
            self._socks += [client, server]
            threading.Thread(target=self._pump, args=(client, server, False), daemon=True).start()
            threading.Thread(target=self._pump, args=(server, client, True), daemon=True).start()

    def _pump(self, src: socket.socket, dst: socket.socket, count: bool) -> None:
        try:
            while data := src.recv(65536):
                if count:
                    self.received.append((time.monotonic(), len(data)))
                dst.sendall(data)
        except OSError:
            pass
        finally:
            for s in (src, dst):
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)

    def close(self) -> None:
        for s in self._socks:
            with contextlib.suppress(OSError):
                s.close()

    def __enter__(self) -> CountingProxy:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def wait_until(cond, timeout: float = 60.0, every: float = 0.25, what: str = "condition"):
    """Poll `cond()` until it returns something truthy; TimeoutError naming `what`."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        v = cond()
        if v:
            return v
        time.sleep(every)
    raise TimeoutError(f"timed out waiting for {what}")


def screenshot_png(driver, timeout: float = 300.0) -> bytes:
    """The page as PNG bytes, from DevTools' Page.captureScreenshot. Chromedriver's own screenshot
    command gives the renderer a fixed 10 s, which a software-GL canvas on a busy machine can exceed
    on every try; a capture that failed anyway is asked for again until `timeout`."""
    import base64

    from selenium.common.exceptions import TimeoutException

    def attempt() -> bytes | None:
        try:
            return base64.b64decode(driver.execute_cdp_cmd("Page.captureScreenshot", {"format": "png"})["data"])
        except TimeoutException:
            return None

    return wait_until(attempt, timeout, every=1.0, what="a screenshot")


def quiet_app(out, **settings):
    """An AppConfig for a test: a long run (the test stops it) on a free port, with no recording, periodic
    images, checkpoints or final evaluation; `settings` add to these or override them."""
    from flipviz.viz.app.app import AppConfig

    base = dict(steps=100_000, no_rrd=True, port=0, images_every=0, checkpoint_every=0, eval_on_stop=False)
    return AppConfig.from_settings(**(base | settings), out=out)


MUG_LESSON = dict(  # the mug's configuration 4 mirrored through x = 0 shows its handle where no input saw it
    res=32,
    batch_rays=512,
    log_every=2,
    view_width=64,
    mirror_plane="official",
    uncertainty_start=0.0005,  # the NLL, and the gate, from step 50
    disagreement_limit=float("inf"),  # no pooled verdict: the mirrors leave one by one
    mirror_disagreement_limit=2.0,  # low: the gate drops mirrors within a minute or two at 32 px
    after_drop="continue",
)
