"""A full disk (issue 13, 2), on a real small tmpfs: the survey state is still written
(its reserve given up), a tile that cannot be spilled stays in memory, and the daemon
ends a survey on SIGTERM with exit 0, no traceback, the recordings intact and the
survey-end pass deferred until space returns, when it runs by itself."""

from __future__ import annotations

import asyncio
import contextlib
import errno
import json
import os
import shutil
import signal
import subprocess
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from daemon.survey import RESERVE_BYTES, RESERVE_FILE, SurveyState, read_state, write_state
from drivers.formats.tilespill import DiskSpill
from mapping.tiles import MemorySpill, TileStore
from tests.daemon.harness import DaemonProcess
from tests.daemon.test_lifecycle import config_file, ctl, wait_for
from tests.mapping.test_tiles import GRID, TILES, frame, pose
from tools.sim import simulate


@contextlib.contextmanager
def mounted_tmpfs(folder: Path, size_mb: int) -> Iterator[Path]:
    """A tmpfs of ``size_mb`` at ``folder`` (skips the test where it cannot be mounted)."""
    folder.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root (CI runs as root)")
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size_mb}m", "tmpfs", str(folder)],
        capture_output=True, text=True, timeout=30, check=False,
    )  # fmt: skip
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.strip()}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], timeout=30, check=False)


@pytest.fixture
def small_fs(tmp_path: Path) -> Iterator[Path]:
    with mounted_tmpfs(tmp_path / "fs", 4) as folder:
        yield folder


def fill(folder: Path, name: str = "filler") -> Path:
    """Write zeros until the file system is full; the filler's path. Only on a small
    file system (a tmpfs the test mounted), never the machine's disk."""
    fs = os.statvfs(folder)
    assert fs.f_blocks * fs.f_frsize <= 256 * 2**20, f"{folder} is not a small tmpfs"
    path = folder / name
    block = b"\0" * 65536
    with open(path, "wb", buffering=0) as out:
        with contextlib.suppress(OSError):
            while True:
                out.write(block)
        with contextlib.suppress(OSError):
            while True:
                out.write(b"\0" * 512)
    with pytest.raises(OSError) as full:
        (folder / "probe").write_bytes(b"\0" * 4096)
    assert full.value.errno == errno.ENOSPC
    return path


def test_the_survey_state_is_written_on_a_full_disk(small_fs: Path) -> None:
    survey = small_fs / "20260101-000000"
    survey.mkdir()
    state = SurveyState(survey.name, "boat1", started=1.0)
    write_state(survey, state)
    assert (survey / RESERVE_FILE).stat().st_size == RESERVE_BYTES
    filler = fill(small_fs)
    state.state, state.reason = "finishing", "shutdown"
    state.live = {"1": {"frames_mapped": 12345, "notes": "x" * 20000}}  # larger than before
    write_state(survey, state)
    assert read_state(survey) == state
    assert not (survey / RESERVE_FILE).exists()  # given up for it
    assert sorted(p.name for p in survey.iterdir()) == ["survey.json"]  # no temp file left
    # Space back: the next write takes the reserve again.
    filler.unlink()
    (small_fs / "probe").unlink(missing_ok=True)
    state.state = "done"
    write_state(survey, state)
    assert (survey / RESERVE_FILE).stat().st_size == RESERVE_BYTES
    assert read_state(survey) == state


def test_a_tile_that_cannot_be_spilled_stays_in_memory(small_fs: Path) -> None:
    spill = DiskSpill(small_fs / "tiles")
    store = TileStore(TILES, spill=spill, evict_after_s=1.0, memory_bytes=0)
    image, score, mask = frame(0.5)
    store.insert(0, image, score, mask, GRID, pose(0.2, 0.1), time=0.0)
    before = store.render((0, 0)).values
    fill(small_fs)
    store.evict_idle(now=5.0)
    assert (0, 0) in store.active and store.spill_failures == 1
    assert store.spill_error == os.strerror(errno.ENOSPC)
    assert list((small_fs / "tiles").iterdir()) == []  # no half file
    store.evict_idle(now=6.0)  # not tried again at once
    assert store.spill_failures == 1
    (small_fs / "filler").unlink()
    (small_fs / "probe").unlink(missing_ok=True)
    store.evict_idle(now=40.0)
    assert (0, 0) not in store.active
    np.testing.assert_array_equal(next(store.rendered_tiles()).values, before)


def test_a_memory_spill_never_fails() -> None:
    # The protocol's other implementation, for completeness of the contract above.
    store = TileStore(TILES, spill=MemorySpill(), evict_after_s=1.0, memory_bytes=0)
    image, score, mask = frame(0.5)
    store.insert(0, image, score, mask, GRID, pose(0.2, 0.1), time=0.0)
    store.evict_idle(now=5.0)
    assert store.spill_failures == 0 and not store.active


def test_sigterm_on_a_full_disk_defers_the_survey_end_pass_until_space_returns(
    tmp_path: Path,
) -> None:
    with mounted_tmpfs(tmp_path / "state", 48) as state_dir:
        _daemon_on_a_full_disk(tmp_path, state_dir)


def _daemon_on_a_full_disk(tmp_path: Path, state_dir: Path) -> None:
    sim = tmp_path / "sim"
    simulate("quadrats", 2, sim, max_pings=30)
    config = config_file(tmp_path, min_free_mb=1.0)  # its state folder: the tmpfs
    log_path = tmp_path / "daemon.log"
    earlier = state_dir / "surveys" / "20260101-000000"

    async def main() -> int:
        daemons: list[DaemonProcess] = []
        try:
            return await steps(daemons)
        finally:
            for daemon in daemons:
                await daemon.ensure_stopped()

    async def steps(daemons: list[DaemonProcess]) -> int:
        daemon = DaemonProcess(config, state_dir, log_path)
        daemons.append(daemon)
        await daemon.start()
        await asyncio.to_thread(wait_for, lambda: (state_dir / "control.sock").exists(), 30)
        started = await asyncio.to_thread(ctl, config, "start")
        assert started.returncode == 0, started.stderr
        survey = state_dir / "surveys" / started.stdout.strip()
        # A survey recorded earlier, whose pass a cut shutdown left waiting.
        earlier.mkdir(parents=True)
        shutil.copy(sim / "sonar.oculus", earlier / "sonar-001.oculus")
        shutil.copy(sim / "nav.tlog", earlier / "nav-001.tlog")
        write_state(earlier, SurveyState(earlier.name, "boat1", state="finishing", started=1.0))
        filler = fill(state_dir)
        code = await daemon.stop(signal.SIGTERM, 60)
        assert code == 0, daemon.log()
        state = json.loads((survey / "survey.json").read_text())
        assert state["state"] == "finishing", state
        assert "deferred" in state["reason"] and "min_free_mb" in state["reason"]
        assert (survey / "sonar-001.oculus").is_file() and (survey / "nav-001.tlog").is_file()
        # Started again on the full disk: both passes wait; space returns, they run.
        daemon = DaemonProcess(config, state_dir, log_path)
        daemons.append(daemon)
        await daemon.start()
        await asyncio.to_thread(
            wait_for, lambda: daemon.log().count("survey-end pass deferred") >= 3, 60
        )
        assert json.loads((earlier / "survey.json").read_text())["state"] == "finishing"
        filler.unlink()
        (state_dir / "probe").unlink(missing_ok=True)

        def mapped() -> bool:
            return json.loads((earlier / "survey.json").read_text())["state"] == "done"

        await asyncio.to_thread(wait_for, mapped, 120)
        return await daemon.stop(signal.SIGTERM, 60)

    recorded = {p.name: p.read_bytes() for p in sim.glob("*.*") if p.suffix in (".oculus", ".tlog")}
    code = asyncio.run(main())
    log = log_path.read_text(errors="replace")
    assert code == 0 and "Traceback" not in log, log
    assert "disk space is back: running the deferred survey-end pass" in log
    assert (earlier / "sonar-001.oculus").read_bytes() == recorded["sonar.oculus"]
    assert (earlier / "nav-001.tlog").read_bytes() == recorded["nav.tlog"]
    for name in ("mosaic.tif", "trajectory.csv", "report.json"):
        assert (earlier / name).is_file()
