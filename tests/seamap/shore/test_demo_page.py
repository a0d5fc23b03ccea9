"""The live demo's page in a real headless Chromium: ``seamap demo --boats 2 --web`` (two
boats' daemons through a router, the shore serving its page) shows both boats, their
status and their mosaics as they are mapped; after the surveys the page stays up until
SIGTERM, and then every part exits 0. ``SEAMAP_DEMO_SCREENSHOT=path`` saves the page (the
README's picture)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from tests.ports import free_tcp_port
from tests.seamap.shore import chromium

SEAMAP = str(Path(sys.executable).parent / "seamap")
SCREENSHOT_ENV = "SEAMAP_DEMO_SCREENSHOT"
PINGS = int(os.environ.get("SEAMAP_DEMO_PINGS", "60"))
"""Pings a boat (more for the README's picture)."""
BOATS = ("demo", "demo2")
WAIT_S = 180.0

chromium.require()


def _wait_for_line(log: Path, pattern: str, proc: subprocess.Popen[bytes]) -> re.Match[str]:
    deadline = time.monotonic() + WAIT_S
    while True:
        found = re.search(pattern, log.read_text(errors="replace"))
        if found:
            return found
        assert proc.poll() is None, log.read_text()
        assert time.monotonic() < deadline, f"no {pattern!r} in the demo's output"
        time.sleep(0.1)


def _mapped(panel: str) -> int:
    found = re.search(r"(\d+) mapped", panel)
    return int(found.group(1)) if found else 0


def _tiles_drawn(page: Any) -> dict[str, int]:
    """Tiles the page has drawn, per boat."""
    counts: dict[str, int] = page.evaluate(
        """() => Object.fromEntries([...seamap.model.vehicles].map(([name, v]) => [name,
             [...v.surveys.values()].reduce((n, s) => n + [...s.tiles.values()]
               .filter(t => t.drawnVersion >= 0).length, 0)]))"""
    )
    return counts


def test_the_demo_page_shows_two_boats_through_a_router(tmp_path: Path) -> None:
    out, log = tmp_path / "demo", tmp_path / "demo.out"
    with open(log, "wb") as stream:
        proc = subprocess.Popen(
            [SEAMAP, "demo", "--out", str(out), "--boats", "2", "--max-pings", str(PINGS),
             "--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}", "--web", "127.0.0.1:0"],
            stdout=stream, stderr=subprocess.STDOUT,
        )  # fmt: skip
    try:
        url = _wait_for_line(log, r"live map: (http://127\.0\.0\.1:\d+/)", proc).group(1)
        with chromium.browser() as context:
            page = context.new_page()
            errors: list[str] = []
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            page.goto(url)
            page.wait_for_function("() => window.seamap !== undefined")
            for vehicle in BOATS:
                page.locator(f'section[data-vehicle="{vehicle}"]').wait_for(timeout=WAIT_S * 1e3)
            # Both boats map while the page watches: their tiles arrive.
            deadline = time.monotonic() + WAIT_S
            while not all(_tiles_drawn(page).get(v, 0) > 0 for v in BOATS):
                assert time.monotonic() < deadline, _tiles_drawn(page)
                page.wait_for_timeout(200)
            # Their status: frames mapped as the surveys go on.
            panels = [page.locator(f'section[data-vehicle="{v}"]') for v in BOATS]
            deadline = time.monotonic() + WAIT_S
            while not all(_mapped(p.inner_text()) >= PINGS // 2 for p in panels):
                assert time.monotonic() < deadline, [p.inner_text() for p in panels]
                page.wait_for_timeout(200)
            path = os.environ.get(SCREENSHOT_ENV)
            if path:
                page.locator("#fit").click()
                page.wait_for_timeout(500)
                page.screenshot(path=path)
            _wait_for_line(log, "the live map page stays up", proc)
            for panel in panels:
                assert "live" in panel.inner_text()
            assert not errors, errors
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(120) == 0, log.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = log.read_text()
    assert "shore exit 0, router exit 0, demo daemon exit 0, demo2 daemon exit 0" in text, text
    assert text.count("identical to the daemon's") == 2, text
