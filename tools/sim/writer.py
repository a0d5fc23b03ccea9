"""The survey folder's maps, config and area: seabed.tif, seabed_height.tif, site.toml,
area.geojson.

(``truth.json`` is ``truth.py``'s, ``sonar.oculus`` ``survey.py``'s, ``nav.tlog``
``tlog.py``'s.)

seabed.tif: uint8 GeoTIFF, single band, the site's UTM CRS, north-up, square cells:
255 x the seabed reflectivity the sonar model saw (1..255; 0 = no data).
seabed_height.tif: int16, same grid: height above the seabed's mean plane in units of
``height_scale_m`` (0.1 mm; also the band's GDAL scale).
site.toml: the SiteConfig of the simulated boat (mount, altitude, ping rate, declination,
the IMU message of the flavour, the echosounder's mount when it carries one; without
one, the ``[echosounder]`` defaults, which act only on soundings): what its crew would
know, not the field day's errors. ``[sonar] altitude_m`` is the survey's mean altitude
(tide and slope included).
area.geojson: the area the survey's lanes were planned for (``area_geojson``), what its
crew would give ``seamap replay --area`` or the daemon for the survey's coverage and gaps.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import rasterio
from affine import Affine

from daemon.config import (
    EchosounderConfig,
    MavlinkConfig,
    SiteConfig,
    SonarConfig,
    dump_config,
)
from tools.sim.scenarios import Scenario
from tools.sim.seabed import Seabed
from tools.sim.site import SiteFrame

HEIGHT_STEP_M = 1e-4
_FIRE_RATES_HZ = (2.0, 5.0, 10.0, 15.0, 40.0)


def write_seabed(folder: Path, seabed: Seabed, site: SiteFrame) -> dict[str, Any]:
    """Write seabed.tif and seabed_height.tif; returns the truth's ``seabed`` section."""
    west, north = site.to_utm(np.array(seabed.west), np.array(seabed.north))
    res = seabed.resolution
    transform = Affine(res, 0.0, float(west), 0.0, -res, float(north))
    h, w = seabed.shape
    profile = {
        "driver": "GTiff",
        "width": w,
        "height": h,
        "count": 1,
        "crs": f"EPSG:{site.epsg}",
        "transform": transform,
        "compress": "deflate",
        "tiled": True,
        "blockxsize": 256,
        "blockysize": 256,
    }
    with rasterio.open(folder / "seabed.tif", "w", dtype="uint8", nodata=0, **profile) as dst:
        dst.write(seabed.reflectivity, 1)
    # Heights in 0.1 mm steps as int16: float32 noise would not compress.
    height = np.clip(np.rint(seabed.height / HEIGHT_STEP_M), -32767, 32767).astype(np.int16)
    with rasterio.open(
        folder / "seabed_height.tif", "w", dtype="int16", predictor=2, **profile
    ) as dst:
        dst.write(height, 1)
        dst.scales = (HEIGHT_STEP_M,)
        dst.units = ("m",)
    return {
        "file": "seabed.tif",
        "height_file": "seabed_height.tif",
        "height_scale_m": HEIGHT_STEP_M,
        "resolution_m": seabed.resolution,
        "west": float(west),
        "north": float(north),
        "east": round(float(west) + w * seabed.resolution, 6),
        "south": round(float(north) - h * seabed.resolution, 6),
        "width_px": w,
        "height_px": h,
        "reflectivity_scale": "pixel = round(255 * reflectivity), 1..255; 0 = no data",
    }


AREA_LEAD_IN_M = 3.0
"""How far the lanes run past the survey area at either end, as a planner's lead-in: the
forward-looking fan first sees the seabed about 2.3 m ahead of the boat (1 m altitude,
15 degrees tilt), so a lane that begins 3 m before the area sees it from its edge."""


def area_geojson(s: Scenario, site: SiteFrame) -> dict[str, Any]:
    """The area the survey's lawnmower was planned for, as a GeoJSON Feature (WGS84
    [lon, lat], counterclockwise): every planned lane (skipped ones too) answers for a
    band one lane spacing wide, and the lanes run ``AREA_LEAD_IN_M`` past both ends."""
    beta = math.radians(s.lane_bearing_deg)
    along = np.array([math.sin(beta), math.cos(beta)])
    across = np.array([math.sin(beta + math.pi / 2), math.cos(beta + math.pi / 2)])
    half_across = s.n_lanes * s.lane_spacing_m / 2
    half_along = max(s.lane_length_m / 2 - AREA_LEAD_IN_M, s.lane_length_m / 4)
    centre = np.array([s.survey_centre_east_m, s.survey_centre_north_m])
    corners = [
        centre + a * half_along * along + c * half_across * across
        for a, c in ((-1, -1), (-1, 1), (1, 1), (1, -1))
    ]
    ring = np.array(corners + corners[:1])
    if shoelace(ring) < 0:  # RFC 7946: exterior rings counterclockwise
        ring = ring[::-1]
    lat, lon = site.to_latlon(ring[:, 0], ring[:, 1])
    return {
        "type": "Feature",
        "properties": {
            "name": f"{s.name} survey area",
            "lanes": s.n_lanes,
            "lane_spacing_m": s.lane_spacing_m,
            "skipped_lanes": list(s.skip_lanes),
        },
        "geometry": {
            "type": "Polygon",
            "coordinates": [np.round(np.column_stack([lon, lat]), 9).tolist()],
        },
    }


def shoelace(ring: npt.NDArray[np.float64]) -> float:
    """Signed area (m^2) of a closed ring, positive counterclockwise."""
    x, y = ring[:, 0], ring[:, 1]
    return float(np.sum(x[:-1] * y[1:] - x[1:] * y[:-1]) / 2)


def write_area(path: Path, s: Scenario, site: SiteFrame) -> None:
    path.write_text(json.dumps(area_geojson(s, site), indent=1) + "\n", encoding="utf-8")


def site_config(s: Scenario, altitude_m: float) -> SiteConfig:
    """The SiteConfig matching the simulated boat."""
    base = SiteConfig()
    sonar = replace(
        base.sonar,
        mount_x_m=s.mount_x_m,
        mount_y_m=s.mount_y_m,
        mount_z_m=s.mount_z_m,
        mount_yaw_deg=s.mount_yaw_deg,
        tilt_deg=s.tilt_deg,
        altitude_m=round(altitude_m, 3),
    )
    if s.ping_rate_hz in _FIRE_RATES_HZ:  # the rate the boat fires its sonar at
        sonar = replace(sonar, ping_rate_hz=int(s.ping_rate_hz))
    mav = replace(
        base.mavlink,
        imu_source="highres" if s.flavour == "px4" else "raw",
        declination_deg=s.declination_deg,
    )
    # The echosounder's mount when the boat carries one. Without one the section keeps
    # its defaults (use = true is harmless: it only acts on soundings, and none come),
    # so that the site.toml of a survey without one is what it always was.
    echo = base.echosounder
    if s.echosounder:
        echo = replace(
            echo,
            use=True,
            mount_x_m=s.echosounder_x_m,
            mount_y_m=s.echosounder_y_m,
            mount_z_m=s.echosounder_z_m,
        )
    assert isinstance(sonar, SonarConfig) and isinstance(mav, MavlinkConfig)
    assert isinstance(echo, EchosounderConfig)
    return replace(base, sonar=sonar, mavlink=mav, echosounder=echo)


def write_site_config(path: Path, config: SiteConfig, s: Scenario) -> None:
    header = (
        f"# seamap site configuration of the simulated boat (scenario {s.name}).\n"
        "# Written by tools.sim; the mount and altitude match truth.json.\n\n"
    )
    path.write_text(header + dump_config(config), encoding="utf-8")
