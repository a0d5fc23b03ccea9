"""The navigation record (``mapping.stream_navigation``) over simulated surveys: the local
frame laid at the first fix, the measurements the later stages get, the filter's pose at
each ping against the simulator's truth, the ping's attitude and seabed, and every sample
back for the survey-end pass."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from daemon.replay import mount_from_config, pipeline_params
from mapping.ekf import level_imu
from mapping.samples import AttitudeSample, GnssFix, HeadingSample, ImuSample, Ping, RangeSample
from mapping.stream_navigation import (
    LIVE_BOTTOM_REFRESH_S,
    NOTHING,
    ImuRecord,
    Measured,
    NavigationRecord,
    PingNavigation,
)
from mapping.stream_reorder import Sample
from tools.sim.stream import SimStream, survey_events

Array = npt.NDArray[np.float64]
OFFSET_S = 0.1


@dataclass(frozen=True)
class Survey:
    """A simulated survey's samples in time order, and the simulator's stream."""

    sim: SimStream
    samples: list[Sample]

    def record(self, project_attitude: bool = True) -> NavigationRecord:
        config = self.sim.site_config
        params = pipeline_params(config)
        if not project_attitude:
            params = replace(params, project_attitude=False)
        return NavigationRecord(mount_from_config(config.sonar), params, OFFSET_S)


@functools.cache
def quadrats() -> Survey:
    """8 s of the quadrats survey (40 pings)."""
    sim = survey_events("quadrats", 4, max_pings=40, n_beams=64)
    return Survey(sim, [s for _, s in sim.events])  # type: ignore[misc]


@functools.cache
def shore() -> Survey:
    """30 s of the sloping shore, with an echosounder on the autopilot (150 pings)."""
    sim = survey_events("shore", 1, max_pings=150, n_beams=32)
    return Survey(sim, [s for _, s in sim.events])  # type: ignore[misc]


def _run(
    survey: Survey, record: NavigationRecord
) -> tuple[list[tuple[Sample, Measured]], list[tuple[Ping, PingNavigation]]]:
    """Every sample through the record: what each navigation sample gave, and the
    filter at each ping."""
    taken: list[tuple[Sample, Measured]] = []
    pings: list[tuple[Ping, PingNavigation]] = []
    for sample in survey.samples:
        if isinstance(sample, Ping):
            pings.append((sample, record.at_ping(sample)))
        else:
            taken.append((sample, record.take(sample)))
    return taken, pings


def test_the_local_frame_is_laid_at_the_first_fix_and_the_fixes_come_out_in_it() -> None:
    survey = quadrats()
    record = survey.record()
    first_fix: GnssFix | None = None
    attitude: AttitudeSample | None = None
    initialised_at: float | None = None
    for sample in survey.samples:
        if isinstance(sample, Ping):
            continue
        was_initialised = record.nav.initialised
        out = record.take(sample)
        if isinstance(sample, GnssFix) and sample.usable:
            first_fix = first_fix or sample
            frame = record.frame
            assert frame is not None
            xs, ys = frame.to_local([sample.lat_deg], [sample.lon_deg])
            assert out.gnss is not None
            assert out.gnss[:3] == (sample.time, float(xs[0]), float(ys[0]))
            if was_initialised:
                # The anchor's fix: the same place, at the time it showed the antenna.
                assert out.chain_fix == (sample.time - OFFSET_S, out.gnss[1], out.gnss[2])
            else:
                assert out.chain_fix is None
        elif isinstance(sample, HeadingSample):
            # Before the first fix there is no frame to take a grid heading in.
            assert (out.heading is None) == (first_fix is None)
            if out.heading is not None:
                assert first_fix is not None and record.frame is not None
                convergence = record.frame.convergence_rad(first_fix.lat_deg, first_fix.lon_deg)
                grid = (sample.heading_rad + convergence) % (2 * math.pi)
                assert out.heading == (sample.time, grid)
        elif isinstance(sample, ImuSample):
            # The gyro levelled by the latest attitude report within a second.
            fresh = attitude is not None and sample.time - attitude.time < 1.0
            roll = attitude.roll_rad if fresh and attitude is not None else None
            pitch = attitude.pitch_rad if fresh and attitude is not None else None
            _, _, rate = level_imu(sample.accel_mps2, sample.gyro_rps, roll, pitch)
            assert out.yaw_rate == (sample.time, rate)
        else:
            attitude = sample if isinstance(sample, AttitudeSample) else attitude
            assert out == NOTHING
        if record.nav.initialised and initialised_at is None:
            initialised_at = sample.time
    assert first_fix is not None and attitude is not None and initialised_at is not None
    assert initialised_at >= first_fix.time  # a heading and a fix start the filter


def test_each_ping_gets_the_filters_pose_there() -> None:
    survey = quadrats()
    record = survey.record()
    _, pings = _run(survey, record)
    frame = record.frame
    assert frame is not None
    placed = 0
    for k, (ping, at) in enumerate(pings):
        if at.prior is None:
            assert at.odometry is None and at.gyro is None
            continue
        placed += 1
        east, north = frame.to_utm(at.prior[0], at.prior[1])
        true_east, true_north, true_heading = survey.sim.truth_pose(k)
        # The GNSS's wander (a metre) and the compass's error (a degree or so).
        assert math.hypot(float(east) - true_east, float(north) - true_north) < 2.5
        assert abs(math.degrees(math.remainder(at.prior[2] - true_heading, 2 * math.pi))) < 3.0
        assert at.odometry is not None and at.gyro is not None  # the IMU runs throughout
        assert at.compass_time <= ping.time < at.compass_time + 1.0  # the compass at 2 Hz
    assert placed >= len(pings) - 2


def test_a_pings_tilt_is_the_attitude_between_the_reports_around_it() -> None:
    survey = quadrats()
    record = survey.record()
    _, pings = _run(survey, record)
    reports = [s for s in survey.samples if isinstance(s, AttitudeSample)]
    latency = record.pipeline.single_stage.graph.sonar_latency_s
    ping = pings[len(pings) // 2][0]
    t = ping.time - latency
    before = max((a for a in reports if a.time <= t), key=lambda a: a.time)
    after = min((a for a in reports if a.time > t), key=lambda a: a.time)
    tilt = record.tilt_at(ping.time)
    assert tilt is not None
    w = (t - before.time) / (after.time - before.time)
    assert tilt.pitch_rad == before.pitch_rad + w * (after.pitch_rad - before.pitch_rad)
    low, high = sorted((before.roll_rad, after.roll_rad))
    assert low <= tilt.roll_rad <= high
    # No report within half a second: no attitude.
    assert record.tilt_at(reports[-1].time + latency + 0.6) is None
    assert record.tilt_at(reports[-1].time + latency + 0.4) is not None
    # Without an echosounder the ping's attitude is the tilt alone (and level when the
    # pipeline does not project the attitude).
    assert record.ping_attitude(ping.time, [], []) == tilt
    level = survey.record(project_attitude=False)
    _run(survey, level)
    assert level.ping_attitude(ping.time, [], []) is None


def test_the_seabed_under_a_ping_comes_from_the_soundings_placed_by_the_live_map() -> None:
    survey = shore()
    record = survey.record()
    assert record.pipeline.bottom.use_echosounder
    latency = record.pipeline.single_stage.graph.sonar_latency_s
    truth = survey.sim.truth
    times: list[float] = []
    poses: list[Array] = []  # the filter's priors stand for the live map here
    errors, models = [], []
    for sample in survey.samples:
        if not isinstance(sample, Ping):
            record.take(sample)
            continue
        at = record.at_ping(sample)
        attitude = record.ping_attitude(sample.time, times, poses)
        models.append(record.live_bottom(sample.time, times, poses))
        times.append(sample.time)
        poses.append(at.prior if at.prior is not None else np.full(3, np.nan))
        if attitude is None or attitude.altitude_m is None:
            continue
        assert math.isfinite(attitude.slope_forward) and math.isfinite(attitude.slope_starboard)
        k = int(np.argmin(np.abs(truth.acquisition_time - (sample.time - latency))))
        errors.append(attitude.altitude_m - float(truth.altitude_m[k]))
    # After the first seconds every ping has the soundings' seabed under it, within a
    # few centimetres of the truth (waves move the head by as much).
    assert len(errors) >= 0.85 * len(times)
    assert float(np.median(np.abs(errors))) < 0.06
    # The model is built again only every LIVE_BOTTOM_REFRESH_S of survey time.
    rebuilt = [k for k in range(1, len(models)) if models[k] is not models[k - 1]]
    gaps = np.diff([times[k] for k in rebuilt])
    assert len(rebuilt) >= 5 and float(gaps.min()) >= LIVE_BOTTOM_REFRESH_S
    # Without a placed frame the soundings cannot be placed: no seabed from them.
    fresh = survey.record()
    for sample in survey.samples:
        if not isinstance(sample, Ping):
            fresh.take(sample)
    nowhere = [np.full(3, np.nan)] * len(times)
    assert fresh.live_bottom(times[-1], times, nowhere) is None


def test_the_survey_end_pass_gets_every_sample_back() -> None:
    survey = shore()
    record = survey.record()
    _run(survey, record)
    nav = record.survey()
    kinds = (ImuSample, GnssFix, HeadingSample, AttitudeSample, RangeSample)
    given = {kind: [s for s in survey.samples if isinstance(s, kind)] for kind in kinds}
    assert nav.imu == given[ImuSample]  # through the compact record, exactly
    assert nav.gnss == given[GnssFix]
    assert nav.heading == given[HeadingSample]
    assert nav.attitude == given[AttitudeSample]
    assert nav.ranges == given[RangeSample] and len(nav.ranges) > 100


def test_the_imu_record_keeps_samples_across_its_chunks() -> None:
    class Small(ImuRecord):
        CHUNK = 7

    imu = [s for s in quadrats().samples if isinstance(s, ImuSample)][:40]
    no_magnetometer = [replace(s, mag_gauss=None) for s in imu]
    samples = [*imu[:20], *no_magnetometer[20:]]
    record = Small()
    assert record.samples() == []
    for sample in samples:
        record.append(sample)
    assert record.samples() == samples
