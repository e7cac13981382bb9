"""Debian's Chromium for the browser tests (tools/ensure-system installs it), headless, through Playwright: never a
downloaded browser. The `browser` fixture (tests/conftest.py) launches it once per module."""

from __future__ import annotations

from pathlib import Path

import pytest

CHROMIUM = Path("/usr/bin/chromium")
# as root in a sandbox, with no network beyond this machine: no sandboxing of its own, no background calls home
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def require_chromium() -> None:
    """Fail, not skip: CI must run the browser tests (tools/test runs tools/ensure-system first)."""
    if not CHROMIUM.exists():
        pytest.fail(f"{CHROMIUM} is missing: the browser tests need Debian's chromium; run tools/ensure-system "
                    "(apt-get install chromium)")
    try:
        import playwright.sync_api  # noqa: F401 - only asked whether it is there
    except ImportError:
        pytest.fail("the Python package playwright is missing: run tools/ensure-venv (the 'test' extra pins it)")
