"""``simulate``: one simulated survey, from a scenario and a seed to an output folder.

Order of work: the field day (the seed's draws of the sensor errors, waves, bedforms:
``fieldday``); the site frame; the boat's true motion; the ping times and the time span
of the logs (cut by ``duration_s`` / ``max_pings``); the seabed under everything the sonar
can reach; the sensor tracks; then the files (see ``truth.py`` for truth.json).
``prepare_survey`` does everything before the files and gives a ``SurveySetup``, which
renders the pings (``pings.PingSource``) and plans the tlog (``tlog.plan_tlog``): the file
writer here and the in-process stream (``stream.survey_events``) share that one path.

Randomness: every component draws from its own ``numpy.random.Generator`` seeded with
``[seed, component]``, and no file carries the wall clock, so the same scenario, seed and
overrides give byte-identical files.
"""

from __future__ import annotations

import dataclasses
import math
import time as wallclock
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from drivers.errors import SeamapError
from drivers.oculus.logfile import OculusLogWriter
from tools.sim import writer
from tools.sim.echosounder import simulate_echosounder
from tools.sim.fieldday import draw_field_day
from tools.sim.pings import (
    PingFrames,
    PingPlan,
    PingSource,
    gain_assist,
    mean_altitude,
    ping_frames,
    plan_pings,
)
from tools.sim.scenarios import STREAM_ONLY, Scenario, resolve_scenario
from tools.sim.seabed import Seabed, generate_seabed
from tools.sim.sensors import compass_errors, simulate_gps, simulate_heading, simulate_imu
from tools.sim.site import SiteFrame
from tools.sim.sonar import SonarModel
from tools.sim.tlog import NavStreams, TlogPlan, plan_tlog, write_tlog
from tools.sim.trajectory import Motion, SurveyPath, simulate_motion
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
    "field_day": 11,
    "compass": 12,
    "echosounder": 13,
    "bathymetry": 14,
}


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


def component_rng(seed: int, component: str) -> np.random.Generator:
    """The generator of one component (``_STREAMS``) for ``seed``."""
    return np.random.default_rng([seed, _STREAMS[component]])


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


@dataclass(frozen=True)
class SurveySetup:
    """A survey before any file: the scenario of the field day (the drawn values in
    place), the site frame, the boat's true motion, the ping plan, the seabed, the sonar
    model and the true frames at the pings; ``field_day`` records the draws (truth.json's
    section). ``start`` and ``end`` bound the logs (UNIX s)."""

    scenario: Scenario
    seed: int
    site: SiteFrame
    survey_path: SurveyPath
    motion: Motion
    plan: PingPlan
    seabed: Seabed
    model: SonarModel
    frames: PingFrames
    field_day: dict[str, Any] = field(default_factory=dict)

    @property
    def start(self) -> float:
        return self.motion.start

    @property
    def end(self) -> float:
        return self.plan.end_time

    def ping_source(self) -> PingSource:
        """A fresh renderer of the pings (see ``PingSource``)."""
        s = self.scenario
        return PingSource(
            s,
            self.site,
            self.plan,
            self.frames,
            self.seabed,
            gain_assist(s, len(self.plan), component_rng(self.seed, "pings")),
            component_rng(self.seed, "speckle"),
            component_rng(self.seed, "sonar_attitude"),
        )

    def nav_streams(self) -> NavStreams:
        """The GPS, heading and IMU tracks over the logs' span."""
        s, site, motion, seed = self.scenario, self.site, self.motion, self.seed
        start, end = self.start, self.end
        gps_times = np.arange(start + 0.13, end, 1.0 / s.gps_rate_hz)
        heading_times = np.arange(start + 0.29, end, 1.0 / s.heading_rate_hz)
        imu_rng = component_rng(seed, "imu")
        imu_times = np.arange(start + 0.004, end, 1.0 / s.imu_rate_hz)
        imu_times = imu_times + imu_rng.uniform(-0.0005, 0.0005, len(imu_times))
        compass = compass_errors(s, motion, component_rng(seed, "compass"))
        soundings = None
        if s.echosounder:
            echo_times = np.arange(start + 0.21, end, 1.0 / s.echosounder_rate_hz)
            soundings = simulate_echosounder(
                s, self.seabed, motion, echo_times, component_rng(seed, "echosounder")
            )
        return NavStreams(
            gps=simulate_gps(s, site, motion, gps_times, component_rng(seed, "gps")),
            heading=simulate_heading(
                s, site, motion, heading_times, component_rng(seed, "heading"), compass
            ),
            imu=simulate_imu(s, site, motion, imu_times, imu_rng, compass),
            motion=motion,
            compass=compass,
            echosounder=soundings,
        )

    def tlog_plan(self, streams: NavStreams) -> TlogPlan:
        """The nav.tlog's messages (see ``tlog.plan_tlog``)."""
        rng = component_rng(self.seed, "tlog")
        return plan_tlog(self.scenario, self.site, streams, self.start, self.end, rng)


COARSER_CELLS_M = (0.02, 0.025, 0.04, 0.05)
"""Cell sizes a large site's seabed maps fall back to (each divides a metre, so the cells
stay on a whole-metre UTM grid)."""


def seabed_resolution(s: Scenario, bounds: tuple[float, float, float, float]) -> float:
    """The seabed maps' cell size (m): the scenario's, or the first of
    ``COARSER_CELLS_M`` that keeps the maps within ``s.seabed_max_cells`` (a 20 m range
    and long lanes make a site of several thousand square metres: at 1 cm that would be
    tens of GB while painting), unless the caller pinned ``seabed_resolution_m``. The
    sonar's bins then see a slightly smoother bed, as on the hectare."""
    west, south, east, north = bounds
    res = s.seabed_resolution_m
    if "seabed_resolution_m" in s.explicit:
        return res
    area = (east - west) * (north - south)
    for coarser in COARSER_CELLS_M:
        if area / (res * res) <= s.seabed_max_cells:
            break
        res = max(res, coarser)
    return res


def prepare_survey(s: Scenario, seed: int) -> SurveySetup:
    """Everything before the files: the field day (``s`` with the seed's draws, unless
    ``s.randomise`` is false; fields in ``s.explicit`` keep their values), site, motion,
    ping times, seabed (its cells made coarser on a large site: ``seabed_resolution``),
    sonar, frames."""
    s, field_day = draw_field_day(s, component_rng(seed, "field_day"))
    site = SiteFrame.at(s.origin_lat_deg, s.origin_lon_deg)
    survey_path, motion = simulate_motion(s, component_rng(seed, "motion"))
    plan = plan_pings(s, motion, component_rng(seed, "pings"))
    bounds = _seabed_bounds(s, motion)
    res = seabed_resolution(s, bounds)
    if res != s.seabed_resolution_m:
        s = dataclasses.replace(s, seabed_resolution_m=res)
        field_day = {**field_day, "seabed_resolution_m": res}
    seabed = generate_seabed(
        s, bounds, component_rng(seed, "seabed"), component_rng(seed, "bathymetry")
    )
    model = SonarModel.from_scenario(s, component_rng(seed, "sonar_model"))
    frames = ping_frames(motion, model, seabed, plan, s.tide_rate_mps)
    return SurveySetup(s, seed, site, survey_path, motion, plan, seabed, model, frames, field_day)


def _write_sonar(path: Path, s: Scenario, source: PingSource) -> None:
    """Render every ping and write the Oculus v1 log."""
    with OculusLogWriter(path, start_time=s.start_time, overwrite=True) as log:
        for message, receive in zip(source, source.plan.receive.tolist(), strict=True):
            log.write(message, receive)


def simulate(scenario: str, seed: int, out: Path, **overrides: Any) -> SimulationSummary:
    """Simulate survey ``scenario`` with ``seed`` into folder ``out`` (created if needed).

    Writes sonar.oculus, nav.tlog, truth.json, seabed.tif, seabed_height.tif, site.toml
    and area.geojson (see ``tools.sim.writer`` for what each holds). ``overrides`` replace
    scenario fields, e.g. ``skip_lanes=(1,)``, ``flavour="px4"``, ``max_pings=20``,
    ``duration_s=30``, ``n_beams=128``, ``range_resolution_m``, ``ping_rate_hz``,
    ``current_mps``, ``gps_bias_sigma_m``,
    ``sonar_latency_s``, ``randomise=False``; an override is never redrawn by the field
    day. A bad name, key or value raises SeamapError.
    """
    started = wallclock.perf_counter()
    s = resolve_scenario(scenario, **overrides)
    if s.name in STREAM_ONLY and s.max_pings is None and s.duration_s is None:
        raise SeamapError(
            f"simulate: the whole {s.name} survey would be tens of GB of logs; pass "
            "max_pings or duration_s, or stream it (tools.sim.stream.survey_events)"
        )
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)

    setup = prepare_survey(s, seed)
    s = setup.scenario  # the field day's
    site, seabed, plan, frames = setup.site, setup.seabed, setup.plan, setup.frames
    start, end = setup.start, setup.end
    sonar_path = out / "sonar.oculus"
    source = setup.ping_source()
    _write_sonar(sonar_path, s, source)

    streams = setup.nav_streams()
    nav_path = out / "nav.tlog"
    counts = write_tlog(nav_path, setup.tlog_plan(streams))

    seabed_section = writer.write_seabed(out, seabed, site)
    config_path = out / "site.toml"
    writer.write_site_config(config_path, writer.site_config(s, mean_altitude(s, frames)), s)
    writer.write_area(out / "area.geojson", s, site)
    ping_truth = PingTruth(plan.ids, plan.acquisition, plan.receive, source.assist_db, frames.state)
    truth = build_truth(
        s, seed, overrides, site, setup.survey_path, seabed, setup.model, ping_truth, streams,
        (start, end), seabed_section, setup.field_day,
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
        ping_count=len(plan),
        duration_s=end - start,
        area_m2=h * w * seabed.resolution**2,
        survey_area_m2=s.lane_length_m * s.lane_spacing_m * s.n_lanes,
        nav_message_counts=counts,
        elapsed_s=wallclock.perf_counter() - started,
    )
