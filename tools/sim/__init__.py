"""The survey simulator: a boat with an Oculus M1200d and a Pixhawk over a seabed.

``simulate(scenario, seed, out, **overrides)`` writes a survey folder (sonar.oculus,
nav.tlog, truth.json, seabed.tif, seabed_height.tif, site.toml) and returns a
``SimulationSummary``; ``SCENARIOS`` names the scenarios (``quadrats``, ``farm``,
``quadrats-current``, ``hectare``; see ``tools.sim.stream`` for streaming a survey in
memory without files). Each seed is a new field day (``fieldday``: the GNSS, compass and
gyro errors, latencies, waves and bedforms drawn within realistic ranges; an explicit
override always wins, ``randomise=False`` keeps the defaults). See ``tools.sim.truth``
for the truth's schema and the modules for the physics, written here independently of
``mapping/``: ``seabed`` with ``bedforms`` (sand, ripple trains, mud) and ``structures``
(quadrat arrays, racks, oysters), ``trajectory`` (lawnmower and boat motion, waves),
``sonar`` (the line array's ping forward model), ``sensors`` (GPS, compass, IMU),
``pings`` (ping times and latency), ``tlog``.
"""

from tools.sim.scenarios import SCENARIOS, Scenario, parse_overrides, resolve_scenario
from tools.sim.survey import SimulationSummary, simulate

__all__ = [
    "SCENARIOS",
    "Scenario",
    "SimulationSummary",
    "parse_overrides",
    "resolve_scenario",
    "simulate",
]
