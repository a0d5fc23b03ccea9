"""The shore station (``seamap shore``): follow boats' live maps over zenoh.

- ``seamap.shore.station``: the zenoh intake (subscriptions, liveliness, catch-up) and
  the files it keeps on disk;
- ``seamap.shore.state``: what it holds of each vehicle (tiles, coverage, track, status)
  and the file writers;
- ``seamap.shore.web``: the live map page (``--web``), served from its own thread and
  ``static/`` (plain JavaScript).

The zenoh contract itself (keys, payloads) is shared with the boat in ``drivers.zenoh_io``.
"""

from seamap.shore.station import ShoreSettings, ShoreStation, serve, shore_settings

__all__ = ["ShoreSettings", "ShoreStation", "serve", "shore_settings"]
