"""The command line as a user meets it: one line and exit status 2 on bad input."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest


def seamap(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "seamap", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


def assert_one_line_error(result: subprocess.CompletedProcess[str], *fragments: str) -> None:
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    for fragment in fragments:
        assert fragment in lines[0]


def test_help_lists_the_subcommands() -> None:
    result = seamap("--help")
    assert result.returncode == 0
    for command in ("info", "simulate", "demo"):
        assert command in result.stdout


@pytest.mark.parametrize(
    ("content", "reason"),
    [
        (b"", "empty file"),
        (b"hello, this is not a log\n" * 10, "not an Oculus log or capture, nor a MAVLink log"),
        (b"\x89PNG\r\n\x1a\n" + bytes(200), "not an Oculus log or capture, nor a MAVLink log"),
    ],
)
def test_info_on_a_non_log_is_one_line_and_status_2(
    tmp_path: Path, content: bytes, reason: str
) -> None:
    path = tmp_path / "thing.tlog"
    path.write_bytes(content)
    assert_one_line_error(seamap("info", path), str(path), reason)


def test_info_on_a_missing_file(tmp_path: Path) -> None:
    assert_one_line_error(seamap("info", tmp_path / "nope.oculus"), "nope.oculus", "no such file")


def test_info_on_a_directory(tmp_path: Path) -> None:
    assert_one_line_error(seamap("info", tmp_path), "directory")


def test_simulate_then_info(tmp_path: Path) -> None:
    out = tmp_path / "sim"
    result = seamap(
        "simulate",
        "--scenario",
        "quadrats",
        "--seed",
        "3",
        "--out",
        out,
        "--max-pings",
        "12",
        "--beams",
        "128",
    )
    assert result.returncode == 0, result.stderr
    for name in ("sonar.oculus", "nav.tlog", "truth.json", "site.toml", "seabed.tif"):
        assert (out / name).is_file(), name

    sonar = seamap("info", out / "sonar.oculus", "--json")
    assert sonar.returncode == 0, sonar.stderr
    summary = json.loads(sonar.stdout)
    assert summary["kind"] == "oculus"
    assert summary["count"] == 12
    assert summary["beams"] == [128]
    assert summary["first_time"] < summary["last_time"]

    nav = seamap("info", out / "nav.tlog", "--json")
    assert nav.returncode == 0, nav.stderr
    summary = json.loads(nav.stdout)
    assert summary["kind"] == "mavlink"
    assert summary["messages"]["GPS_RAW_INT"] > 0
    assert summary["messages"]["RAW_IMU"] > summary["messages"]["GPS_RAW_INT"]
    assert summary["count"] == sum(summary["messages"].values())
    assert summary["first_time"] <= summary["last_time"]

    text = seamap("info", out / "nav.tlog")
    assert text.returncode == 0
    assert "GPS_RAW_INT" in text.stdout


def test_simulate_rejects_an_unknown_scenario(tmp_path: Path) -> None:
    result = seamap("simulate", "--scenario", "moon", "--out", tmp_path)
    assert result.returncode == 2
    assert "Traceback" not in result.stderr


def test_bench_reports_the_numbers_we_steer_by(tmp_path: Path) -> None:
    plot = tmp_path / "memory.png"
    result = seamap("bench", "--pings", "40", "--beams", "64", "--json", "--plot", plot)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    for key in (
        "frames_per_second",
        "realtime_factor_10hz",
        "peak_rss_mb",
        "rss_growth_mb_per_1000_frames",
        "latency_p95_s",
        "stall_max_s",
        "flush_s",
        "ms_per_frame_pinging",
        "stages",
    ):
        assert key in report
    assert report["frames"] == 40
    assert 0 <= report["ms_per_frame_pinging"] <= report["ms_per_frame"]
    assert report["frames_per_second"] > 0
    assert report["realtime_factor_10hz"] == pytest.approx(report["frames_per_second"] / 10)
    assert {"preprocess", "registration", "blending", "render"} <= set(report["stages"])
    # The memory curve: a sample every 200 frames and one at the end, drawn as a PNG.
    assert report["memory_samples"][-1][0] == 40
    assert all(rss > 0 for _, rss in report["memory_samples"])
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert report["range_m"] == pytest.approx(5.0)


def test_bench_runs_at_the_range_asked_for() -> None:
    # The cost of a frame at a long range (issue 34): the pings come at 10 m, with the
    # M1200d's range lines there (600 of 1.67 cm).
    result = seamap("bench", "--pings", "10", "--beams", "64", "--range", "10", "--json")
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["frames"] == 10
    assert report["range_m"] == pytest.approx(10.0, abs=0.02)


@pytest.mark.parametrize(
    "command",
    [
        ["run", "--config", "{site}"],
        [
            "replay",
            "--config",
            "{site}",
            "--sonar",
            "{dir}/a.oculus",
            "--nav",
            "{dir}/a.tlog",
            "--out",
            "{dir}/out",
        ],
        ["ctl", "--config", "{site}", "status"],
        ["shore", "--config", "{site}", "--out", "{dir}/shore", "--duration", "1"],
        [
            "survey",
            "plan",
            "--config",
            "{site}",
            "--area",
            "{dir}/area.geojson",
            "--out",
            "{dir}/plan.plan",
        ],
    ],
)
def test_every_command_reading_the_site_file_refuses_a_bad_value(
    tmp_path: Path, command: list[str]
) -> None:
    site = tmp_path / "site.toml"
    site.write_text("[mapping]\nmosaic_res_m = -0.02\n")
    for name in ("a.oculus", "a.tlog", "area.geojson"):
        (tmp_path / name).write_bytes(b"x")
    result = seamap(*[part.format(dir=tmp_path, site=site) for part in command])
    assert_one_line_error(result, "[mapping] mosaic_res_m = -0.02 is outside")
    assert not (tmp_path / "out").exists() and not (tmp_path / "shore").exists()


def _children(pid: int) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                found.append(int(entry.name))
    return found


def test_the_bench_simulator_leaves_when_the_bench_is_killed() -> None:
    bench = subprocess.Popen(
        [sys.executable, "-m", "seamap", "bench", "--pings", "5000", "--beams", "64"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        while not (children := _children(bench.pid)):
            assert time.monotonic() < deadline and bench.poll() is None, "no simulator process"
            time.sleep(0.2)
        time.sleep(5.0)  # the simulator is writing the survey's logs
    finally:
        bench.kill()
        bench.wait(30)
    deadline = time.monotonic() + 30
    while any(Path(f"/proc/{c}").exists() and "Z" not in _state(c) for c in children):
        assert time.monotonic() < deadline, "the simulator outlived the bench"
        time.sleep(0.2)


def _state(pid: int) -> str:
    try:
        return (Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split() or ["?"])[0]
    except OSError:
        return "Z"


def test_the_product_loads_no_tool_and_finds_the_installed_ones() -> None:
    # `seamap run` (the boat's service) builds its parser without importing tools; the
    # development tools' commands come in through the seamap.commands entry points.
    code = (
        "import sys\n"
        "from seamap.cli import build_parser\n"
        "parser = build_parser(['run', '--help'])\n"
        "loaded = sorted(m for m in sys.modules if m == 'tools' or m.startswith('tools.'))\n"
        "print(loaded)\n"
        "build_parser(['simulate', '--help'])\n"
        "print('tools.commands.simulate' in sys.modules)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["[]", "True"]


def test_a_full_disk_is_one_line_naming_the_file(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import errno

    import daemon.replay
    from seamap.cli import main

    def full(*args: object, **kwargs: object) -> dict[str, object]:
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "mosaic.tif"))

    monkeypatch.setattr(daemon.replay, "replay", full)
    for name in ("s.oculus", "n.tlog"):
        (tmp_path / name).write_bytes(b"x")
    args = ["replay", "--sonar", tmp_path / "s.oculus", "--nav", tmp_path / "n.tlog"]
    assert main([*map(str, args), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"seamap replay: {tmp_path / 'mosaic.tif'}: No space left on device"]
