"""``simulate``: one simulated survey, from a scenario and a seed to an output folder.

Order of work: the site frame; the boat's true motion; the ping times and the time span
of the logs (cut by ``duration_s`` / ``max_pings``); the seabed under everything the sonar
can reach; the sensor tracks; then the files (see ``writer.py`` for truth.json).

Randomness: every component draws from its own ``numpy.random.Generator`` seeded with
``[seed, component]``, and no file carries the wall clock, so the same scenario, seed and
overrides give byte-identical files.
"""

from __future__ import annotations

import math
import time as wallclock
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from drivers.oculus.logfile import OculusLogWriter
from drivers.oculus.ping import build_simple_ping
from drivers.oculus.protocol import PingRate
from mapping.samples import Ping
from tools.sim import writer
from tools.sim.scenarios import Scenario, resolve_scenario
from tools.sim.seabed import Seabed, generate_seabed
from tools.sim.sensors import simulate_gps, simulate_heading, simulate_imu
from tools.sim.site import SiteFrame
from tools.sim.sonar import SonarModel, SonarPose, render_ping, rot_z, sonar_pose
from tools.sim.tlog import NavStreams, write_tlog
from tools.sim.trajectory import Motion, euler_to_matrix, simulate_motion
from tools.sim.truth import PingTruth, build_truth, write_truth

FloatArray = npt.NDArray[np.float64]

# Generator streams, one per component (changing one component's draws leaves the others).
_STREAMS = {
    "motion": 1,
    "seabed": 2,
    "sonar_model": 3,
    "speckle": 4,
    "gps": 5,
    "heading": 6,
    "imu": 7,
    "tlog": 8,
    "pings": 9,
    "sonar_attitude": 10,
}
_FIRST_PING_DELAY_S = 1.0  # the sonar log starts a little after the telemetry
_END_MARGIN_S = 0.5
_SONAR_DEVIATION_DEG = 8.0  # the sonar's own compass is uncalibrated near the thrusters


@dataclass(frozen=True)
class SimulationSummary:
    """What ``simulate`` wrote. duration_s: span of the nav log (s); area_m2: the seabed
    map's area (m^2); survey_area_m2: the lawnmower's lanes x spacing."""

    scenario: str
    seed: int
    out: Path
    sonar_path: Path
    nav_path: Path
    truth_path: Path
    seabed_path: Path
    config_path: Path
    ping_count: int
    duration_s: float
    area_m2: float
    survey_area_m2: float
    nav_message_counts: dict[str, int] = field(default_factory=dict)
    elapsed_s: float = 0.0
    """Wall-clock seconds the simulation took (not written to any file)."""

    def describe(self) -> str:
        """A few lines for people: what was simulated and where it went."""
        sizes = {
            p.name: p.stat().st_size / 1e6
            for p in (self.sonar_path, self.nav_path, self.truth_path, self.seabed_path)
            if p.exists()
        }
        counts = ", ".join(f"{name} {n}" for name, n in self.nav_message_counts.items())
        return "\n".join(
            [
                f"{self.scenario} (seed {self.seed}) -> {self.out}",
                f"  {self.ping_count} pings over {self.duration_s:.1f} s; seabed map "
                f"{self.area_m2:.0f} m^2, survey lanes {self.survey_area_m2:.0f} m^2",
                "  " + ", ".join(f"{name} {mb:.1f} MB" for name, mb in sizes.items()),
                f"  nav.tlog: {counts}",
            ]
        )


def _rng(seed: int, component: str) -> np.random.Generator:
    return np.random.default_rng([seed, _STREAMS[component]])


@dataclass(frozen=True)
class _PingPlan:
    acquisition: FloatArray
    receive: FloatArray
    ids: npt.NDArray[np.int64]
    end_time: float


def _plan_pings(s: Scenario, motion: Motion, rng: np.random.Generator) -> _PingPlan:
    """Ping acquisition/receive times (UNIX s) and the end of the logs."""
    end = motion.end
    if s.duration_s is not None:
        end = min(end, motion.start + s.duration_s)
    first = motion.start + _FIRST_PING_DELAY_S
    count = max(0, math.floor((end - _END_MARGIN_S - first) * s.ping_rate_hz))
    if s.max_pings is not None:
        count = min(count, s.max_pings)
    k = np.arange(count)
    acquisition = first + k / s.ping_rate_hz + rng.normal(0.0, s.ping_jitter_s, count)
    receive = acquisition + s.sonar_latency_s
    if s.max_pings is not None and count == s.max_pings and count > 0:
        end = min(end, float(receive[-1]) + _END_MARGIN_S)
    first_id = round(s.sonar_uptime_s * s.ping_rate_hz)
    return _PingPlan(acquisition, receive, first_id + k, end)


def _seabed_bounds(s: Scenario, motion: Motion) -> tuple[float, float, float, float]:
    """Whole-metre local bounds holding everything the sonar can see during the whole
    survey (not only the part simulated: the seabed of a site and seed never changes)."""
    reach = s.range_m + math.hypot(s.mount_x_m, s.mount_y_m) + s.seabed_margin_m
    return (
        math.floor(float(motion.east.min()) - reach),
        math.floor(float(motion.north.min()) - reach),
        math.ceil(float(motion.east.max()) + reach),
        math.ceil(float(motion.north.max()) + reach),
    )


def _ping_truth(
    motion: Motion, model: SonarModel, seabed: Seabed, plan: _PingPlan
) -> tuple[dict[str, FloatArray], list[SonarPose]]:
    """True poses at the pings' acquisition times, and the sonar head's pose per ping."""
    at = motion.at(plan.acquisition)
    r_grid = euler_to_matrix(at["heading"], at["pitch"], at["roll"])
    poses = []
    for k in range(len(plan.acquisition)):
        antenna = np.array([at["north"][k], at["east"][k], -at["up"][k]])
        poses.append(sonar_pose(antenna, r_grid[k], model))
    sonar_ned = np.array([p.position_ned for p in poses]).reshape(-1, 3)
    at["sonar_north"] = sonar_ned[:, 0]
    at["sonar_east"] = sonar_ned[:, 1]
    at["sonar_depth"] = sonar_ned[:, 2]
    at["altitude"] = seabed.depth_at(sonar_ned[:, 1], sonar_ned[:, 0]) - sonar_ned[:, 2]
    return at, poses


def _sonar_attitude(
    s: Scenario, site: SiteFrame, pose: SonarPose, rng: np.random.Generator
) -> tuple[float, float, float]:
    """What the sonar's own attitude sensor reports (radians: magnetic heading with an
    uncalibrated deviation, pitch including the tilt, roll), with noise."""
    r = rot_z(site.convergence_rad) @ pose.rotation  # grid -> true north
    heading = math.atan2(r[1, 0], r[0, 0]) - s.declination_rad
    heading += math.radians(_SONAR_DEVIATION_DEG) + rng.normal(0.0, math.radians(1.0))
    pitch = -math.asin(max(-1.0, min(1.0, r[2, 0]))) + rng.normal(0.0, math.radians(0.3))
    roll = math.atan2(r[2, 1], r[2, 2]) + rng.normal(0.0, math.radians(0.3))
    return heading % (2 * math.pi), pitch, roll


def _write_sonar(
    path: Path,
    s: Scenario,
    site: SiteFrame,
    model: SonarModel,
    seabed: Seabed,
    plan: _PingPlan,
    poses: list[SonarPose],
    seed: int,
) -> FloatArray:
    """Render every ping and write the Oculus v1 log; returns each ping's gain-assist dB."""
    speckle_rng = _rng(seed, "speckle")
    attitude_rng = _rng(seed, "sonar_attitude")
    n = len(plan.acquisition)
    # The gain assist drifts slowly from ping to ping (AR(1), ~5 s memory at 10 Hz).
    rho = math.exp(-1.0 / (5.0 * s.ping_rate_hz))
    assist = np.zeros(n)
    drive = _rng(seed, "pings").normal(0.0, s.gain_assist_db * math.sqrt(1 - rho * rho), n)
    for k in range(1, n):
        assist[k] = rho * assist[k - 1] + drive[k]
    power_on = s.start_time - s.sonar_uptime_s
    # The fire message's rate code nearest the simulated rate (echoed in every ping).
    rate_code = min((r for r in PingRate if r.hz > 0), key=lambda r: abs(r.hz - s.ping_rate_hz))
    with OculusLogWriter(path, start_time=s.start_time, overwrite=True) as log:
        for k, pose in enumerate(poses):
            image = render_ping(model, pose, seabed, speckle_rng, float(assist[k]))
            heading, pitch, roll = _sonar_attitude(s, site, pose, attitude_rng)
            depth_bar = max(0.0, float(pose.position_ned[2])) * 0.1005
            ping = Ping(
                time=float(plan.receive[k]),
                ping_id=int(plan.ids[k]),
                master_mode=s.master_mode,
                frequency_hz=s.frequency_hz,
                range_resolution_m=s.range_resolution_m,
                bearings_rad=model.bearings_rad,
                image=image,
                gains=model.gain_words(float(assist[k])),
                speed_of_sound_mps=s.speed_of_sound_mps,
                gain_percent=s.gain_percent,
                gamma=s.gamma,
                heading_rad=heading,
                pitch_rad=pitch,
                roll_rad=roll,
                extra={
                    "ping_start_time": float(plan.acquisition[k]) - power_on,
                    "temperature_c": s.water_temperature_c,
                    "pressure_bar": 1.01325 + depth_bar,
                    "range_demand": s.range_m,
                    "salinity_ppt": s.salinity_ppt,
                },
            )
            message = build_simple_ping(ping, version=2, send_gain=True, ping_rate=int(rate_code))
            log.write(message, float(plan.receive[k]))
    return assist


def simulate(scenario: str, seed: int, out: Path, **overrides: Any) -> SimulationSummary:
    """Simulate survey ``scenario`` with ``seed`` into folder ``out`` (created if needed).

    Writes sonar.oculus, nav.tlog, truth.json, seabed.tif, seabed_height.tif and site.toml
    (see ``tools.sim.writer`` for what each holds). ``overrides`` replace scenario fields,
    e.g. ``flavour="px4"``, ``max_pings=20``, ``duration_s=30``, ``n_beams=128``,
    ``range_resolution_m``, ``ping_rate_hz``, ``current_mps``, ``gps_bias_sigma_m``,
    ``sonar_latency_s``. A bad name, key or value raises SeamapError.
    """
    started = wallclock.perf_counter()
    s = resolve_scenario(scenario, **overrides)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)

    site = SiteFrame.at(s.origin_lat_deg, s.origin_lon_deg)
    survey_path, motion = simulate_motion(s, _rng(seed, "motion"))
    plan = _plan_pings(s, motion, _rng(seed, "pings"))
    start, end = motion.start, plan.end_time
    bounds = _seabed_bounds(s, motion)
    seabed = generate_seabed(s, bounds, _rng(seed, "seabed"))
    model = SonarModel.from_scenario(s, _rng(seed, "sonar_model"))
    at, poses = _ping_truth(motion, model, seabed, plan)

    sonar_path = out / "sonar.oculus"
    assist = _write_sonar(sonar_path, s, site, model, seabed, plan, poses, seed)

    gps_times = np.arange(start + 0.13, end, 1.0 / s.gps_rate_hz)
    heading_times = np.arange(start + 0.29, end, 1.0 / s.heading_rate_hz)
    imu_rng = _rng(seed, "imu")
    imu_times = np.arange(start + 0.004, end, 1.0 / s.imu_rate_hz)
    imu_times = imu_times + imu_rng.uniform(-0.0005, 0.0005, len(imu_times))
    streams = NavStreams(
        gps=simulate_gps(s, site, motion, gps_times, _rng(seed, "gps")),
        heading=simulate_heading(s, site, motion, heading_times, _rng(seed, "heading")),
        imu=simulate_imu(s, site, motion, imu_times, imu_rng),
        motion=motion,
    )
    nav_path = out / "nav.tlog"
    counts = write_tlog(nav_path, s, site, streams, start, end, _rng(seed, "tlog"))

    seabed_section = writer.write_seabed(out, seabed, site)
    mean_altitude = float(np.mean(at["altitude"])) if len(poses) else s.water_depth_m - 0.2
    config_path = out / "site.toml"
    writer.write_site_config(config_path, writer.site_config(s, mean_altitude), s)
    ping_truth = PingTruth(plan.ids, plan.acquisition, plan.receive, assist, at)
    truth = build_truth(
        s, seed, overrides, site, survey_path, seabed, model, ping_truth, streams,
        (start, end), seabed_section,
    )  # fmt: skip
    truth_path = out / "truth.json"
    write_truth(truth_path, truth)

    h, w = seabed.shape
    return SimulationSummary(
        scenario=s.name,
        seed=seed,
        out=out,
        sonar_path=sonar_path,
        nav_path=nav_path,
        truth_path=truth_path,
        seabed_path=out / "seabed.tif",
        config_path=config_path,
        ping_count=len(poses),
        duration_s=end - start,
        area_m2=h * w * seabed.resolution**2,
        survey_area_m2=s.lane_length_m * s.lane_spacing_m * s.n_lanes,
        nav_message_counts=counts,
        elapsed_s=wallclock.perf_counter() - started,
    )
