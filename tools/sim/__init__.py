"""The survey simulator: a boat with an Oculus M1200d and a Pixhawk over a seabed.

``simulate(scenario, seed, out, **overrides)`` writes a survey folder (sonar.oculus,
nav.tlog, truth.json, seabed.tif, seabed_height.tif, site.toml) and returns a
``SimulationSummary``; ``SCENARIOS`` names the scenarios (``quadrats``, ``farm``,
``quadrats-current``, ``hectare``; see ``tools.sim.stream`` for streaming a survey in
memory without files). See ``tools.sim.writer`` for the truth's schema and the modules
for the physics: ``seabed`` (reflectivity and relief), ``trajectory`` (lawnmower and boat
motion), ``sonar`` (ping forward model), ``sensors`` (GPS, compass, IMU), ``tlog``.
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
