"""One survey logged at 2 Hz and at 10 Hz is one map.

The same simulated field day (the same boat, seabed, GNSS wander, compass and gyro: the
simulator draws each from its own stream) pinged at 2 Hz and at 10 Hz, each replayed
single-stage. Every weight is physical, nothing is weighted per frame, and each frame is
registered against a keyframe (the registrations' errors add up by the distance
travelled, not by the frame), so the two maps must draw the seabed in the same place:
the seabed points a frame sees are put where the estimated pose puts them, their error
against the truth compared between the runs at the same moments.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from daemon.replay import replay
from tools.evaluation.truth import load_truth
from tools.sim import simulate

pytestmark = pytest.mark.slow

Array = npt.NDArray[np.float64]

# Seabed points in the vehicle frame (forward, starboard metres from the antenna): across
# the lit fan of the sonar, which sits 0.45 m behind it and looks ahead.
FAN_POINTS = np.array([(2.0, 0.0), (3.0, -1.5), (3.0, 1.5), (4.0, 0.0)])


def _place(poses: Array) -> Array:
    """(n, 4, 2) east/north of FAN_POINTS from poses (east, north, heading rad)."""
    s, c = np.sin(poses[:, 2])[:, None], np.cos(poses[:, 2])[:, None]
    f, st = FAN_POINTS[None, :, 0], FAN_POINTS[None, :, 1]
    return np.stack([poses[:, 0:1] + f * s + st * c, poses[:, 1:2] + f * c - st * s], axis=-1)


def _placement_errors(result: Path, truth_path: Path) -> tuple[Array, Array, Array]:
    """Frame times, (n, 4, 2) placement error (estimated minus true) of FAN_POINTS, and
    their true places."""
    truth = load_truth(truth_path)
    by_time = {round(p["time"], 6): p for p in truth["pings"]}
    times, est, true = [], [], []
    with (result / "trajectory.csv").open(newline="") as handle:
        for row in csv.DictReader(handle):
            ping = by_time[round(float(row["time"]), 6)]
            times.append(float(row["time"]))
            est.append(
                (float(row["east"]), float(row["north"]), math.radians(float(row["heading_deg"])))
            )
            true.append((ping["east"], ping["north"], math.radians(ping["heading_deg"])))
    placed = _place(np.array(true))
    return np.array(times), _place(np.array(est)) - placed, placed


@pytest.fixture(scope="module")
def errors(
    tmp_path_factory: pytest.TempPathFactory,
) -> dict[float, tuple[Array, Array, Array]]:
    out = {}
    for rate in (2.0, 10.0):
        folder = tmp_path_factory.mktemp(f"rate{rate:g}")
        simulate("quadrats", 3, folder, ping_rate_hz=rate, duration_s=75.0, n_beams=256)
        replay(
            folder / "sonar.oculus",
            folder / "nav.tlog",
            folder / "site.toml",
            "single-stage",
            folder / "result",
        )
        out[rate] = _placement_errors(folder / "result", folder / "truth.json")
    return out


def test_2hz_and_10hz_logs_of_one_survey_give_one_map(
    errors: dict[float, tuple[Array, Array, Array]],
) -> None:
    slow_t, slow, slow_true = errors[2.0]
    fast_t, fast, _ = errors[10.0]
    assert slow_t.size > 100 and fast_t.size > 5 * 100
    inside = (slow_t >= fast_t[0]) & (slow_t <= fast_t[-1])
    fast_at_slow = np.stack(
        [
            np.stack([np.interp(slow_t[inside], fast_t, fast[:, p, a]) for a in range(2)], -1)
            for p in range(FAN_POINTS.shape[0])
        ],
        axis=1,
    )
    apart = np.linalg.norm(slow[inside] - fast_at_slow, axis=-1)
    rms = float(np.sqrt(np.mean(apart**2)))
    # The maps' shapes: the 2 Hz placements after the rigid motion (2-D Procrustes) that
    # brings them nearest the 10 Hz ones. What is left is what the ping rate changes in
    # the map itself; the motion, where each map sits on the GNSS.
    a = (slow_true[inside] + slow[inside]).reshape(-1, 2)
    b = (slow_true[inside] + fast_at_slow).reshape(-1, 2)
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    rotation = (u @ vt).T
    shape = np.linalg.norm((a - ca) @ rotation.T + cb - b, axis=-1)
    shape_rms = float(np.sqrt(np.mean(shape**2)))
    shift = float(np.linalg.norm(cb - ca))
    turn = math.degrees(math.atan2(rotation[1, 0], rotation[0, 0]))
    # Both maps sit on the same GNSS error, metres of it: what differs is only what the
    # ping rate changes.
    offset = float(np.sqrt(np.mean(np.sum(slow[inside] ** 2, axis=-1))))
    print(f"2 Hz vs 10 Hz: RMS {rms:.4f} m, p90 {np.percentile(apart, 90):.4f} m; shape "
          f"{shape_rms:.4f} m after {shift:.3f} m and {turn:.3f} deg; error against the truth "
          f"{offset:.3f} m")  # fmt: skip
    assert rms < 0.02, (rms, offset)
