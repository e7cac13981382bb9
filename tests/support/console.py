"""The web console's tests share: opening it on a daemon, its step, its colours, a PNG it shows."""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np

STEP_JS = """() => { const m = document.querySelector('#job-step').textContent.match(/step (\\d+) \\//);
                     return m ? Number(m[1]) : -1; }"""


def check_png(path: Path, min_std: float = 10.0) -> np.ndarray:
    """A real picture: a PNG that decodes, of some size, not one flat colour."""
    assert path.stat().st_size > 1000 and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", path
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert image is not None and image.shape[0] > 50 and image.shape[1] > 50, path
    assert float(image.std()) > min_std, f"{path} looks blank (std {image.std():.1f})"
    return image


def step_of(page) -> int:
    return page.evaluate(STEP_JS)


BAD = "rgb(198, 40, 40)"  # console.css --bad


def colour_of(page, selector: str) -> str:
    return page.evaluate(f"getComputedStyle(document.querySelector('{selector}')).color")


def open_console(page, daemon) -> None:
    page.goto(daemon.url + "/")  # redirected to /console/
    assert page.url.endswith("/console/")
    page.wait_for_selector("#routine option[value='virtual-grid']", state="attached")
    page.wait_for_selector("#devices tbody tr")


@contextmanager
def browser_page(browser, timeout_ms: float = 30_000):
    """A page of its own context (1400 x 1000), collecting the page's uncaught errors in `page.errors` and what
    the browser's console shows as errors (a resource that failed to load) in `page.console_errors`."""
    context = browser.new_context(viewport={"width": 1400, "height": 1000})
    page = context.new_page()
    page.errors, page.console_errors = [], []
    page.on("pageerror", lambda exc: page.errors.append(str(exc)))
    page.on("console", lambda message: page.console_errors.append(message.text) if message.type == "error" else None)
    page.set_default_timeout(timeout_ms)
    try:
        yield page
    finally:
        context.close()
