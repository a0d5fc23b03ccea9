"""The sonar side of a survey: when the pings are taken, where the head is, and the pings.

Shared by the file writer (``survey.simulate`` writes each ping to sonar.oculus) and the
in-process stream (``stream.survey_events`` decodes each one as the driver would), so that
both give the same pings for the same scenario and seed.

Times are UNIX seconds (the boat computer's clock). Positions are in the site's local
grid frame (metres east/north of the UTM origin point, see ``site.py``), depths down from
the still water surface; angles in radians.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from drivers.oculus.ping import build_simple_ping
from drivers.oculus.protocol import PingRate
from mapping.samples import Ping
from tools.sim.scenarios import Scenario
from tools.sim.seabed import Seabed
from tools.sim.site import SiteFrame
from tools.sim.sonar import SonarModel, SonarPose, render_ping, rot_z, sonar_pose
from tools.sim.trajectory import Motion, euler_to_matrix

FloatArray = npt.NDArray[np.float64]

FIRST_PING_DELAY_S = 1.0  # the sonar log starts a little after the telemetry
END_MARGIN_S = 0.5
_SONAR_DEVIATION_DEG = 8.0  # the sonar's own compass is uncalibrated near the thrusters


@dataclass(frozen=True)
class PingPlan:
    """Per ping: acquisition and receive times (UNIX s) and the sonar's ping id; and the
    end of the logs (UNIX s)."""

    acquisition: FloatArray
    receive: FloatArray
    ids: npt.NDArray[np.int64]
    end_time: float

    def __len__(self) -> int:
        return len(self.acquisition)


def plan_pings(s: Scenario, motion: Motion, rng: np.random.Generator) -> PingPlan:
    """Ping acquisition/receive times (UNIX s) and the end of the logs: receive =
    acquisition + ``sonar_latency_s`` + an exponential tail of mean
    ``sonar_latency_jitter_s`` (capped at 10 means or 0.4 ping intervals)."""
    end = motion.end
    if s.duration_s is not None:
        end = min(end, motion.start + s.duration_s)
    first = motion.start + FIRST_PING_DELAY_S
    count = max(0, math.floor((end - END_MARGIN_S - first) * s.ping_rate_hz))
    if s.max_pings is not None:
        count = min(count, s.max_pings)
    k = np.arange(count)
    acquisition = first + k / s.ping_rate_hz + rng.normal(0.0, s.ping_jitter_s, count)
    # The sonar's processing, Ethernet and the driver: a fixed latency and a queueing
    # tail, capped well inside the ping interval so that pings arrive in order.
    tail = rng.exponential(s.sonar_latency_jitter_s, count) if s.sonar_latency_jitter_s else 0.0
    cap = min(10.0 * s.sonar_latency_jitter_s, 0.4 / s.ping_rate_hz)
    receive = acquisition + s.sonar_latency_s + np.minimum(tail, cap)
    if s.max_pings is not None and count == s.max_pings and count > 0:
        end = min(end, float(receive[-1]) + END_MARGIN_S)
    first_id = round(s.sonar_uptime_s * s.ping_rate_hz)
    return PingPlan(acquisition, receive, first_id + k, end)


@dataclass(frozen=True)
class PingFrames:
    """The true state at each ping's acquisition and the sonar head's pose.

    state: ``Motion.at`` fields per ping (local metres, radians) plus ``sonar_north``,
    ``sonar_east``, ``sonar_depth`` (the head, local metres, depth down) and ``altitude``
    (head above the seabed's mean plane, vertically, m). body_to_grid: (n, 3, 3) body FRD
    -> local grid north/east/down rotations. Poses are recomputed per ping on demand
    (``pose``), so a long survey holds arrays, not one object per ping.
    """

    state: dict[str, FloatArray]
    body_to_grid: FloatArray
    model: SonarModel

    def pose(self, k: int) -> SonarPose:
        """The sonar head's pose at ping ``k`` (the same numbers every call)."""
        at = self.state
        antenna = np.array([at["north"][k], at["east"][k], -at["up"][k]])
        return sonar_pose(antenna, self.body_to_grid[k], self.model)


def ping_frames(
    motion: Motion, model: SonarModel, seabed: Seabed, plan: PingPlan, tide: float = 0.0
) -> PingFrames:
    """True poses at the pings' acquisition times (see ``PingFrames``); ``tide`` the water
    level's rate of rise (m/s)."""
    at = motion.at(plan.acquisition)
    frames = PingFrames(at, euler_to_matrix(at["heading"], at["pitch"], at["roll"]), model)
    sonar_ned = np.array([frames.pose(k).position_ned for k in range(len(plan))]).reshape(-1, 3)
    at["sonar_north"] = sonar_ned[:, 0]
    at["sonar_east"] = sonar_ned[:, 1]
    at["sonar_depth"] = sonar_ned[:, 2]
    at["altitude"] = seabed.depth_at(sonar_ned[:, 1], sonar_ned[:, 0]) - sonar_ned[:, 2]
    grad_e, grad_n = seabed.depth_gradient(sonar_ned[:, 1], sonar_ned[:, 0])
    # Perpendicular to the bed's smooth surface under the head (its local tangent plane).
    at["altitude_normal"] = at["altitude"] / np.sqrt(1.0 + grad_e**2 + grad_n**2)
    at["water_level"] = tide * (plan.acquisition - motion.start)
    return frames


def mean_altitude(s: Scenario, frames: PingFrames) -> float:
    """The mean altitude of the sonar head over the pings (m), for site.toml."""
    altitude = frames.state["altitude"]
    return float(np.mean(altitude)) if len(altitude) else s.water_depth_m - 0.2


def gain_assist(s: Scenario, count: int, rng: np.random.Generator) -> FloatArray:
    """Each ping's gain-assist level (dB): a slow AR(1) drift, ~5 s memory at 10 Hz."""
    rho = math.exp(-1.0 / (5.0 * s.ping_rate_hz))
    assist = np.zeros(count)
    drive = rng.normal(0.0, s.gain_assist_db * math.sqrt(1 - rho * rho), count)
    for k in range(1, count):
        assist[k] = rho * assist[k - 1] + drive[k]
    return assist


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


@dataclass(frozen=True)
class PingSource:
    """Everything needed to render a survey's pings in order, one at a time.

    ``speckle_rng`` and ``attitude_rng`` must be fresh generators of their components:
    rendering consumes them, so one ``PingSource`` renders its pings once.
    """

    scenario: Scenario
    site: SiteFrame
    plan: PingPlan
    frames: PingFrames
    seabed: Seabed
    assist_db: FloatArray
    speckle_rng: np.random.Generator
    attitude_rng: np.random.Generator

    @property
    def rate_code(self) -> int:
        """The fire message's rate code nearest the simulated rate (echoed in every ping)."""
        hz = self.scenario.ping_rate_hz
        return int(min((r for r in PingRate if r.hz > 0), key=lambda r: abs(r.hz - hz)))

    def __iter__(self) -> Iterator[bytes]:
        """Each ping's SimplePingResult message (the scenario's ``ping_layout``,
        ``sample_bits`` and ``gain_rows``), in ping order; its receive time is
        ``plan.receive[k]``."""
        s, model = self.scenario, self.frames.model
        power_on = s.start_time - s.sonar_uptime_s
        rate_code = self.rate_code
        for k in range(len(self.plan)):
            pose = self.frames.pose(k)
            assist = float(self.assist_db[k])
            image = render_ping(model, pose, self.seabed, self.speckle_rng, assist, s.sample_bits)
            heading, pitch, roll = _sonar_attitude(s, self.site, pose, self.attitude_rng)
            depth = float(pose.position_ned[2])
            if s.tide_rate_mps:  # below the risen (fallen) surface
                depth += float(self.frames.state["water_level"][k])
            depth_bar = max(0.0, depth) * 0.1005
            ping = Ping(
                time=float(self.plan.receive[k]),
                ping_id=int(self.plan.ids[k]),
                master_mode=s.master_mode,
                frequency_hz=s.frequency_hz,
                range_resolution_m=s.range_resolution_m,
                bearings_rad=model.bearings_rad,
                image=image,
                gains=model.gain_words(assist),
                speed_of_sound_mps=s.speed_of_sound_mps,
                gain_percent=s.gain_percent,
                gamma=s.gamma,
                heading_rad=heading,
                pitch_rad=pitch,
                roll_rad=roll,
                extra={
                    "ping_start_time": float(self.plan.acquisition[k]) - power_on,
                    "temperature_c": s.water_temperature_c,
                    "pressure_bar": 1.01325 + depth_bar,
                    "range_demand": s.range_m,
                    "salinity_ppt": s.salinity_ppt,
                },
            )
            # Older firmware sends v1 pings with msgVersion 0 (the real ones do).
            yield build_simple_ping(
                ping,
                version=s.ping_layout,
                send_gain=s.gain_rows,
                ping_rate=rate_code,
                msg_version=0 if s.ping_layout == 1 else 2,
            )
