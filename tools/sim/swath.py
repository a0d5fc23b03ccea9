"""What the sonar can see from a given altitude: its ground swath, the range resolution the
M1200d uses at a range, and the lawnmower that overlaps its lanes.

Plain geometry of the line array (``sonar`` module doc) over a flat bed, in metres and
degrees; no scenario here, so that ``scenarios`` (the named surveys) and ``fieldday`` (the
wide draw) size their lawnmowers by the same rule.

- Range resolution: the M1200d sends a ping of a few hundred to about a thousand range
  lines, whatever the range (its range resolution grows with the range set: about
  ``range / 600``), and at 1.2 MHz the pulse never resolves much below a centimetre at
  the ranges a survey uses, so the simulator keeps ``max(0.01, range / 600)`` rounded to
  a tenth of a millimetre: 0.01 m up to 6 m (300-600 lines), 0.0167 m at 10 m, 0.0333 m
  at 20 m (600 lines). The 5 m default keeps today's 0.01 m (500 lines).
- Ground swath: the fan is ``fan_deg`` wide about the boresight, and the echo is strong
  within the vertical beam's -3 dB half-aperture of the boresight (``tilt`` down). The
  useful slant range is the range set, or less when the beam's upper -3 dB edge (at
  ``tilt - aperture / 2`` below the horizontal) meets the bed sooner: ``R_u =
  min(range, h / sin(tilt - aperture / 2))`` (no limit when that edge is level or above).
  The fan then covers ``2 sqrt(R_u^2 - h^2) sin(fan / 2)`` across the track at that
  range (the beams at the fan's edges reach ``sin(fan / 2)`` of the ground range
  sideways).
- Lane spacing: ``LANE_SPACING_FRACTION`` (0.45) of that swath, so that each stripe of
  seabed is seen from two neighbouring lanes with a good margin (the quadrats survey's 4 m
  at 5 m range, 1 m altitude, 15 degrees tilt is 0.45 of its 8.9 m swath), rounded to
  0.1 m and at least 1 m.
"""

from __future__ import annotations

import math

LANE_SPACING_FRACTION = 0.45
"""Lane spacing over the ground swath (see the module doc)."""
MIN_RANGE_RESOLUTION_M = 0.01
RANGE_LINES = 600
"""Range lines of a ping at ranges beyond 6 m (the M1200d keeps about 500-1000)."""


def range_resolution_for(range_m: float) -> float:
    """The range resolution (m) the simulated M1200d uses at ``range_m`` (module doc)."""
    return round(max(MIN_RANGE_RESOLUTION_M, range_m / RANGE_LINES), 4)


def useful_range_m(
    range_m: float, altitude_m: float, tilt_deg: float, aperture_deg: float
) -> float:
    """The slant range (m) out to which the vertical beam's -3 dB lobe still meets the bed
    (the range set, or less: module doc)."""
    upper = math.radians(tilt_deg - aperture_deg / 2.0)
    if upper <= 0.0:
        return range_m
    return min(range_m, altitude_m / math.sin(upper))


def ground_swath_m(
    range_m: float, altitude_m: float, tilt_deg: float, fan_deg: float, aperture_deg: float
) -> float:
    """Width across the track (m) of the seabed the fan sees well from ``altitude_m``
    (module doc); 0 when the bed is out of reach."""
    reach = useful_range_m(range_m, altitude_m, tilt_deg, aperture_deg)
    ground = math.sqrt(max(reach * reach - altitude_m * altitude_m, 0.0))
    return 2.0 * ground * math.sin(math.radians(fan_deg / 2.0))


def lane_spacing_for(
    range_m: float, altitude_m: float, tilt_deg: float, fan_deg: float, aperture_deg: float
) -> float:
    """Lane spacing (m): ``LANE_SPACING_FRACTION`` of the swath, to 0.1 m, at least 1 m."""
    swath = ground_swath_m(range_m, altitude_m, tilt_deg, fan_deg, aperture_deg)
    return max(1.0, round(LANE_SPACING_FRACTION * swath, 1))
