"""Debian's Chromium, headless, driven by Playwright (its own browser download needs the
internet): shared by the browser tests. ``require()`` at a test module's top skips the
module, saying why, when either is missing."""

from __future__ import annotations

import contextlib
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

CHROMIUM = "/usr/bin/chromium"
ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]  # fmt: skip
"""Without the background-networking flags Chromium's connections to the closed network
are refused, many at a time."""


def require() -> Any:
    """The ``playwright.sync_api`` module; skips the calling test module without it or
    without Chromium."""
    api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
    if not Path(CHROMIUM).exists():
        pytest.skip(
            f"{CHROMIUM} is missing (apt-get install chromium; `make test` installs it as root)",
            allow_module_level=True,
        )
    return api


@contextlib.contextmanager
def browser(width: int = 1200, height: int = 800) -> Iterator[Any]:
    """A headless Chromium context with a fresh profile."""
    api = require()
    profile = tempfile.mkdtemp(prefix="seamap-chromium-")
    with api.sync_playwright() as p:
        context = p.chromium.launch_persistent_context(
            profile, executable_path=CHROMIUM, headless=True, args=ARGS,
            viewport={"width": width, "height": height}, device_scale_factor=1,
        )  # fmt: skip
        try:
            yield context
        finally:
            context.close()
            shutil.rmtree(profile, ignore_errors=True)
