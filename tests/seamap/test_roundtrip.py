"""Simulator output read back by our readers and by the independent ones agree exactly."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from drivers.mavlink import read_nav_log
from drivers.oculus.logfile import iter_pings
from tools.sim import simulate


def test_simulated_survey_reads_identically_with_bps_oculus_and_pymavlink(tmp_path: Path) -> None:
    summary = simulate("quadrats", 5, tmp_path, max_pings=6, n_beams=128)
    np.NAN = np.nan  # type: ignore[attr-defined]  # noqa: NPY201  (oculus-python uses it)
    import bps_oculus.io as bps_io

    theirs = list(bps_io.process_v1(summary.sonar_path))
    ours = list(iter_pings(summary.sonar_path))
    assert len(ours) == len(theirs) == 6
    for (info, result, polar, _), mine in zip(theirs, ours, strict=True):
        assert info.timestamp == mine.time
        assert result.pingId == mine.ping_id
        np.testing.assert_array_equal(polar.polar_image, mine.image)
        np.testing.assert_allclose(polar.bearing_table, mine.bearings_rad, atol=1e-12)
        assert mine.gains is not None
        np.testing.assert_array_equal(polar.gain_table, mine.gains)

    nav = read_nav_log(summary.nav_path)
    # pymavlink's reader switches dialect settings for the whole process: run it apart.
    script = (
        "import json, sys\n"
        "from pymavlink import mavutil\n"
        "c = mavutil.mavlink_connection(sys.argv[1])\n"
        "out = []\n"
        "while (m := c.recv_match(type='GPS_RAW_INT')) is not None:\n"
        "    if m.get_srcSystem() == 1:\n"
        "        out.append([m._timestamp, m.lat / 1e7, m.lon / 1e7, m.h_acc / 1000])\n"
        "print(json.dumps(out))\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script, str(summary.nav_path)],
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
    )
    fixes = [tuple(row) for row in json.loads(result.stdout)]
    assert len(fixes) > 0
    assert [(f.time, f.lat_deg, f.lon_deg, f.h_acc_m) for f in nav.gnss] == fixes
