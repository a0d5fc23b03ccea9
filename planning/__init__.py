"""Survey planning: a lawnmower path over a survey area for the boat to drive, and what it
maps.

Frames and units: positions are metres east/north in the survey's local grid frame
(``mapping.geo.LocalFrame``); bearings are radians clockwise from grid north; widths and
distances are metres, areas square metres, durations seconds. No files and no projections
here: ``seamap.plan_files`` reads the area, converts to and from WGS84 and writes the
mission files.

- ``planning.area``: the area (polygons with keep-out holes), its validation;
- ``planning.keepouts``: the keep-outs round the holes and the way round them;
- ``planning.swath``: the sonar's usable swath, which spaces the lanes;
- ``planning.lawnmower``: the lanes over the area and the path (the rules are in its doc);
- ``planning.plan``: the planned path, its length and duration;
- ``planning.coverage``: how much of the area the path maps.

The public names of all six are importable from here.
"""

from planning.lawnmower import *  # noqa: F403
from planning.lawnmower import __all__ as __all__
