"""``seamap demo`` end to end (short): emulators, the daemon(s), the zenoh router and the
shore station on 127.0.0.1; the shore's mosaic is each daemon's result, and the accuracy
is printed. Plain (one boat through the router), secure (the boat is the TLS endpoint),
and two boats of neighbouring areas through the router."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import pytest

SEAMAP = str(Path(sys.executable).parent / "seamap")


@pytest.mark.parametrize("secure", [False, True], ids=["plain", "secure"])
def test_demo_runs_the_whole_system_on_loopback(tmp_path: Path, secure: bool) -> None:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    out = tmp_path / "demo"
    done = subprocess.run(
        [SEAMAP, "demo", "--out", str(out), "--max-pings", "80",
         "--zenoh-listen", f"tcp/127.0.0.1:{port}", *(["--secure"] if secure else [])],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr + (out / "daemon.log").read_text()
    text = done.stdout
    for step in range(1, 6):
        assert f"[{step}/5]" in text
    assert "80 of 80 frames mapped" in text
    assert "identical to the daemon's" in text, text
    assert "trajectory error" in text
    (survey,) = (out / "boat" / "surveys").iterdir()
    for name in ("mosaic.tif", "mosaic.png", "trajectory.csv", "report.json", "sonar-001.oculus"):
        assert (survey / name).is_file()
    # The planned area's covered fraction and gaps: 80 pings leave most of it to do.
    area = json.loads((survey / "report.json").read_text())["coverage"]["area"]
    assert f"coverage: {100 * area['covered_fraction']:.1f} % of the planned area" in text
    assert area["gaps"] >= 1 and (survey / "gaps.geojson").is_file()
    assert (survey / "replan.plan").is_file() and "the way back to them" in text
    assert ", covered " in text  # the live fraction in the progress lines
    shore = out / "shore" / "demo"
    assert (shore / survey.name / "mosaic.tif").is_file()
    assert (shore / "track.csv").read_text().startswith("time,lat,lon,east,north,heading_deg")
    if secure:  # the same, over TLS with the set's certificates, password and rules
        assert f"zenoh tls/127.0.0.1:{port} (secured by" in text
        assert (out / "security" / "boat" / "boat.key").is_file()
    else:
        assert f"router: seamap router --listen tcp/127.0.0.1:{port}" in text
        assert "router exit 0" in text


def test_demo_of_two_boats_through_one_router(tmp_path: Path) -> None:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    out = tmp_path / "demo"
    done = subprocess.run(
        [SEAMAP, "demo", "--out", str(out), "--max-pings", "40", "--boats", "2",
         "--zenoh-listen", f"tcp/127.0.0.1:{port}"],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    text = done.stdout
    for vehicle in ("demo", "demo2"):
        assert f"{vehicle}: 40 of 40 frames mapped" in text
        (survey,) = (out / f"boat-{vehicle}" / "surveys").iterdir()
        assert (out / "shore" / vehicle / survey.name / "mosaic.tif").is_file()
    assert text.count("identical to the daemon's") == 2, text
    assert "demo daemon exit 0, demo2 daemon exit 0" in text
    # Neighbouring areas: the second boat's mosaic lies east of the first's.
    import rasterio

    bounds = []
    for vehicle in ("demo", "demo2"):
        (tif,) = (out / f"boat-{vehicle}" / "surveys").glob("*/mosaic.tif")
        with rasterio.open(tif) as image:
            bounds.append(image.bounds)
    assert bounds[1].left > bounds[0].right
