"""A survey recorded in several segments (one per daemon start) replays as the whole survey:
the same navigation samples, the same trajectory and the same mosaic pixels."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import rasterio

from daemon.config import load_config
from daemon.recording import nav_name, sonar_name
from daemon.replay import replay, replay_survey
from drivers.errors import SeamapError
from drivers.mavlink import NavLogError, read_nav_log
from drivers.mavlink.framing import ScanTally, scan_tlog
from drivers.oculus.logfile import ITEM_TYPE_OCULUS, OculusLogWriter, iter_log_items
from seamap.cli import main
from tests.drivers import mavlink_fixtures as fx
from tools.sim import simulate

SEAMAP = Path(sys.executable).with_name("seamap")
"""The console script of the interpreter running the tests (the venv's)."""


def split_oculus(whole: Path, first: Path, second: Path) -> float:
    """Write the items of a v1 log into two v1 segments, split at the middle item.

    Returns the receive time (UNIX s) of the second segment's first item.
    """
    items = list(iter_log_items(whole))
    assert all(item.item_type == ITEM_TYPE_OCULUS for item in items)
    half = len(items) // 2
    for path, part in ((first, items[:half]), (second, items[half:])):
        with OculusLogWriter(path, start_time=part[0].time) as log:
            for item in part:
                log.write(item.message, item.time)
    return items[half].time


def split_tlog(whole: Path, first: Path, second: Path, at: float) -> None:
    """Cut an undamaged tlog into two at the first record received at or after ``at`` (s)."""
    data = whole.read_bytes()
    tally = ScanTally()
    starts: list[tuple[float, int]] = []
    offset = 0
    for time, msg in scan_tlog(data, tally):
        starts.append((time, offset))
        offset += 8 + len(msg.get_msgbuf())  # stamp, then the frame as received
    assert offset == len(data) and tally.bytes_skipped == 0
    cut = next(start for time, start in starts if time >= at)
    assert 0 < cut < len(data)
    first.write_bytes(data[:cut])
    second.write_bytes(data[cut:])


@pytest.fixture(scope="module")
def survey(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A simulated survey, and in ``segments/`` the same logs as two daemon segments."""
    folder = tmp_path_factory.mktemp("survey")
    simulate("quadrats", 2, folder, max_pings=120, n_beams=256)
    segments = folder / "segments"
    segments.mkdir()
    at = split_oculus(folder / "sonar.oculus", segments / sonar_name(1), segments / sonar_name(2))
    split_tlog(folder / "nav.tlog", segments / nav_name(1), segments / nav_name(2), at)
    return folder


def sonar_segments(survey: Path) -> list[Path]:
    return [survey / "segments" / sonar_name(n) for n in (1, 2)]


def nav_segments(survey: Path) -> list[Path]:
    return [survey / "segments" / nav_name(n) for n in (1, 2)]


@pytest.fixture(scope="module")
def whole(survey: Path) -> Path:
    out = survey / "whole"
    replay(survey / "sonar.oculus", survey / "nav.tlog", survey / "site.toml", "single-stage", out)
    return out


def assert_same_result(result: Path, expected: Path) -> None:
    """Byte-identical trajectory, pixel-identical georeferenced mosaic."""
    trajectory = (result / "trajectory.csv").read_text()
    assert trajectory == (expected / "trajectory.csv").read_text()
    assert trajectory.count("\n") > 100
    with (
        rasterio.open(result / "mosaic.tif") as got,
        rasterio.open(expected / "mosaic.tif") as want,
    ):
        assert (got.crs, got.transform, got.shape) == (want.crs, want.transform, want.shape)
        assert (got.read(1) == want.read(1)).all()


# --- navigation ----------------------------------------------------------------------------


def test_tlog_segments_read_as_one_log(survey: Path) -> None:
    whole = read_nav_log(survey / "nav.tlog")
    joined = read_nav_log(nav_segments(survey))
    for stream in ("imu", "gnss", "heading", "attitude"):
        assert getattr(joined, stream) == getattr(whole, stream), stream
    assert len(joined.gnss) > 10
    sources = ("autopilot", "imu_source", "heading_source", "gnss_source")
    assert [getattr(joined, s) for s in sources] == [getattr(whole, s) for s in sources]
    got, want = joined.report, whole.report
    assert got.path == " + ".join(str(path) for path in nav_segments(survey))
    same = (
        "format", "file_bytes", "messages", "counts", "bytes_skipped", "bad_packets",
        "bad_timestamps", "truncated", "time_backwards", "first_time", "last_time",
        "time_reference", "autopilot_id", "other_system_messages", "unusable_messages",
    )  # fmt: skip
    assert {k: getattr(got, k) for k in same} == {k: getattr(want, k) for k in same}


def test_a_cut_segment_is_reported_over_the_whole_log(survey: Path, tmp_path: Path) -> None:
    first, second = nav_segments(survey)
    cut = tmp_path / nav_name(1)
    cut.write_bytes(first.read_bytes()[:-5])  # the daemon died mid-write
    whole = read_nav_log(survey / "nav.tlog").report
    report = read_nav_log([cut, second]).report
    assert report.truncated and report.bytes_skipped == 0
    assert report.messages == whole.messages - 1
    assert report.file_bytes == whole.file_bytes - 5
    assert [note for note in report.notes if "ends inside" in note] == [
        f"{cut}: ends inside a message"
    ]


def test_only_tlog_segments_can_be_joined(tmp_path: Path) -> None:
    bins = [fx.ardupilot_dataflash(seconds=1).save(tmp_path / f"{n}.bin") for n in (1, 2)]
    tlog = fx.write_tlog(tmp_path / "a.tlog", fx.ardupilot_messages())
    for paths, named in (
        (bins, bins[0]),
        ([tlog, bins[1]], bins[1]),
        ([bins[0], tlog], bins[0]),
    ):
        with pytest.raises(NavLogError, match=r"only \.tlog segments") as raised:
            read_nav_log(paths)
        message = str(raised.value)
        assert message.startswith(f"{named}:") and "\n" not in message
    # One .bin in a list reads as the .bin itself.
    assert read_nav_log([bins[0]]).imu == read_nav_log(bins[0]).imu


# --- replay --------------------------------------------------------------------------------


def test_replay_over_segments_is_the_whole_survey(survey: Path, whole: Path) -> None:
    out = survey / "from-segments"
    config = load_config(survey / "site.toml")
    report = replay(
        sonar_segments(survey), nav_segments(survey), None, "single-stage", out, config=config
    )
    assert_same_result(out, whole)
    assert report["inputs"] == {
        "sonar": [str(path) for path in sonar_segments(survey)],
        "nav": [str(path) for path in nav_segments(survey)],
        "config": None,
    }
    assert report["frames"]["skipped_in_log"] == {"corrupt_pings": 0, "truncated": 0}
    whole_report = json.loads((whole / "report.json").read_text())
    for key in ("read", "mapped", "rejected"):
        assert report["frames"][key] == whole_report["frames"][key]
    assert whole_report["inputs"]["sonar"] == [str(survey / "sonar.oculus")]


def test_repeated_sonar_and_nav_options(survey: Path, whole: Path) -> None:
    args = ["replay", "--config", str(survey / "site.toml"), "--out", str(survey / "repeated")]
    for sonar, nav in zip(sonar_segments(survey), nav_segments(survey), strict=True):
        args += ["--sonar", str(sonar), "--nav", str(nav)]
    assert main(args) == 0
    assert_same_result(survey / "repeated", whole)


# --- seamap replay --survey ----------------------------------------------------------------


def seamap(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(SEAMAP), *map(str, args)], capture_output=True, text=True, timeout=300, check=False
    )


def test_survey_folder_replays_every_segment(survey: Path, whole: Path) -> None:
    out = survey / "from-survey"
    done = seamap(
        "replay", "--survey", survey / "segments", "--config", survey / "site.toml", "--out", out
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(f"{out}: ")
    assert_same_result(out, whole)


def test_survey_folder_without_segments(survey: Path, tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    done = seamap("replay", "--survey", empty, "--out", tmp_path / "o")
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and str(empty) in lines[0], done.stderr
    assert not (tmp_path / "o").exists()
    # Sonar without navigation is named as such.
    shutil.copy(sonar_segments(survey)[0], empty)
    with pytest.raises(SeamapError, match=r"no nav-NNN\.tlog segment") as raised:
        replay_survey(empty, load_config(None), tmp_path / "o")
    assert str(raised.value).startswith(f"{empty}:")


def test_survey_excludes_sonar_and_nav(survey: Path, tmp_path: Path) -> None:
    done = seamap(
        "replay", "--survey", survey / "segments", "--sonar", sonar_segments(survey)[0],
        "--out", tmp_path / "o",
    )  # fmt: skip
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "--survey" in lines[0], done.stderr
    assert "Traceback" not in done.stderr
