"""The survey simulator: a boat with an Oculus M1200d and a Pixhawk over a seabed.

``simulate(scenario, seed, out, **overrides)`` writes a survey folder (sonar.oculus,
nav.tlog, truth.json, seabed.tif, seabed_height.tif, site.toml) and returns a
``SimulationSummary``; ``SCENARIOS`` names the scenarios (``quadrats``, ``farm``,
``quadrats-current``, ``hectare``, ``shore``, ``mud``, ``deep``, ``rtk``, ``field``; see
``tools.sim.stream`` for streaming a survey in memory without files). Each seed is a new
field day (``fieldday``: the GNSS, compass and gyro errors, latencies, waves and bedforms
drawn within realistic ranges; an explicit override always wins, ``randomise=False``
keeps the defaults). See ``tools.sim.truth`` for the truth's schema and the modules for
the physics, written here independently of ``mapping/``: ``seabed`` with ``bedforms``
(sand, ripple trains, mud) and ``structures`` (quadrat arrays, racks, oysters),
``trajectory`` (lawnmower and boat motion, waves), ``sonar`` (the line array's ping
forward model), ``sensors`` (GPS, compass, IMU), ``pings`` (ping times and latency),
``tlog``.

The world is wider than rippled sand under a 5 m range: ``seabed_type`` makes the bottom
soft mud (dark, a few percent of texture, no ripples), shell hash, gravel and cobble
patches among the sand, or smooth mud with sparse tyres, blocks and pipes
(``bottoms``); the bed slopes up to 10 % in any direction (``seabed_slope_*``) and may
undulate over 10-40 m (``bathymetry``, seen by the sonar's footprint, its shadows and the
echosounder); the tide lifts the floating boat (``tide_rate_mps``); range 3-20 m with the
M1200d's resolution at it, tilt 10-30 degrees, 0.3-1.2 m/s, 2-15 pings/s, lanes spaced
to the swath (``swath``); a downward Ping2-class echosounder reporting the nearest
bottom in its 30-degree cone as DISTANCE_SENSOR / RANGEFINDER (``echosounder``); an RTK
receiver (``gnss_kind = "rtk"``, ``sensors``). ``wide`` draws all of that per seed from
streams of its own (``fieldday.draw_wide``), so the older scenarios and seeds give the
same bytes as before; the named scenarios ``shore``, ``mud``, ``deep``, ``rtk`` and
``field`` are the conditions users reported. Large sites get 2-5 cm seabed cells
(``survey.seabed_resolution``) so a survey stays within about 1.5 GB.
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
