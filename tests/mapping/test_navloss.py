"""Navigation lost: with no IMU between two frames the filter holds its heading, and the
registration chain must carry the turn (issue 13, item 1).

The gyro epochs the survey-end pass computes from the log equal the ones the live filter
gives as the samples arrive; the chain's own motion is what a frame is checked against
without them; and a 30 s silence over a U-turn, cut from a simulated survey's autopilot
log, is carried through by the live map and the survey-end pass alike."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from daemon.config import load_config
from daemon.replay import (
    mount_from_config,
    ping_source,
    pipeline_params,
    read_navigation,
    stream_survey,
)
from mapping.ekf import EkfParams, ImuInput, NavFilter
from mapping.frames import LocalRegistration, RegistrationParams, SonarMount, _Kept
from mapping.navigation import NavInputs, gyro_epochs
from mapping.se2 import RelativePose
from tools.navloss import cut_tlog, measure, window_start
from tools.sim import simulate


def test_gyro_epochs_offline_equal_the_live_filters() -> None:
    rng = np.random.default_rng(3)
    steps = rng.choice([0.02, 0.02, 0.02, 0.1, 0.3, 2.0, 31.0], size=400)
    imu_t = np.cumsum(steps)
    frames = np.sort(rng.uniform(0.0, imu_t[-1] + 1.0, 300))
    inputs = NavInputs([ImuInput(float(t), 0.0, 0.0, 0.0) for t in imu_t], [], [])
    offline = gyro_epochs(inputs, frames, EkfParams().max_imu_gap_s)

    nav = NavFilter()
    live = []
    events = sorted([(float(t), 0) for t in imu_t] + [(float(t), 1) for t in frames])
    for t, kind in events:
        if kind == 0:
            nav.add_imu(ImuInput(t, 0.0, 0.0, 0.0))
        else:
            epoch = nav.gyro_epoch_at(t)
            live.append(-1 if epoch is None else epoch)
    np.testing.assert_array_equal(offline, live)
    assert (offline < 0).any() and offline.max() >= 3  # silences and returns were met


def test_without_the_gyro_a_frame_is_expected_where_the_chain_was_going() -> None:
    params = RegistrationParams()
    local = LocalRegistration(SonarMount(), params=params)
    pose = np.zeros(3)
    # The chain's last steps: 0.4 m/s ahead, turning 12 degrees a second, 1 s of them.
    local._rate = ((0.4, 0.0, math.radians(12.0)), 10.0, 1.0)
    last = _Kept(1, 10.0, pose, None, None, None, None, None)  # type: ignore[arg-type]
    here = _Kept(2, 10.5, pose, None, None, None, None, None)  # type: ignore[arg-type]
    held, sigma_short, _ = local._coasting(last, here, _held())
    assert math.degrees(held.yaw_rad) == pytest.approx(6.0, abs=1e-9)
    # The chord of the arc: turned by half the turn, sinc-shortened.
    chord = 0.2 * math.sin(math.radians(3.0)) / math.radians(3.0)
    assert held.forward_m == pytest.approx(chord * math.cos(math.radians(3.0)), abs=1e-9)
    assert held.starboard_m == pytest.approx(chord * math.sin(math.radians(3.0)), abs=1e-9)
    # The longer the prediction, the less it is worth...
    later = _Kept(3, 11.5, pose, None, None, None, None, None)  # type: ignore[arg-type]
    _, sigma_long, _ = local._coasting(last, later, _held())
    assert sigma_long > 3 * sigma_short
    # ... and once the rate is older than a boat's speed can say, or without one, the
    # filter's held motion is all there is, as uncertain as a boat's speed and turn.
    much_later = _Kept(4, 14.0, pose, None, None, None, None, None)  # type: ignore[arg-type]
    after = _Kept(5, 14.5, pose, None, None, None, None, None)  # type: ignore[arg-type]
    expected, sigma_p, sigma_a = local._coasting(much_later, after, _held())
    assert expected == _held()
    assert sigma_p == pytest.approx(params.coast_speed_sigma_mps * 0.5)
    assert sigma_a == pytest.approx(params.coast_yaw_rate_sigma_rps * 0.5)
    local._rate = None
    assert local._coasting(last, here, _held())[0] == _held()


def _held() -> RelativePose:
    return RelativePose(0.2, 0.0, 0.0)


GAP_S = 30.0


@pytest.fixture(scope="module")
def silenced(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[str, dict[str, float]]]:
    root = tmp_path_factory.mktemp("navloss")
    sim = root / "sim"
    simulate("quadrats", 5, sim, max_pings=180, ping_rate_hz=2.0)
    pings = json.loads((sim / "truth.json").read_text())["pings"]
    start = window_start(pings, GAP_S, "turn")
    assert cut_tlog(sim / "nav.tlog", root / "cut.tlog", start, start + GAP_S) > 1000
    config = load_config(sim / "site.toml")
    samples, _ = read_navigation([root / "cut.tlog"], config)
    final, (live, _) = stream_survey(
        ping_source([sim / "sonar.oculus"], {}),
        samples,
        mount_from_config(config.sonar),
        pipeline_params(config),
    )
    out = {}
    for name, result in (("final", final), ("live", live)):
        east, north = result.frame.to_utm(result.poses[:, 0], result.poses[:, 1])
        poses = np.column_stack([east, north, result.poses[:, 2]])
        out[name] = measure(np.asarray(result.times), poses, pings, start, start + GAP_S)
    return out


@pytest.mark.parametrize("which", ["final", "live"])
def test_a_silence_over_a_turn_is_carried_by_the_chain(
    silenced: dict[str, dict[str, dict[str, float]]], which: str
) -> None:
    gap, after = silenced[which]["gap"], silenced[which]["after"]
    print(which, gap, after)
    assert gap["posed"] >= 0.95 * gap["pings"]
    assert gap["heading_drift_max_deg"] <= 5.0
    assert gap["drift_max_m"] <= 0.5
    # The navigation back: the map takes it up again.
    assert after["posed"] >= 0.95 * after["pings"]
    assert after["heading_drift_median_deg"] <= 3.0
