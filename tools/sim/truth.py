"""truth.json: what really happened in a simulated survey, for later stages to score.

truth.json (format "seamap-sim-truth", version 1) — everything later stages need to
score a trajectory or a mosaic. Units: metres, seconds (UNIX, the boat computer's clock),
degrees where the key says ``_deg``. "UTM" = the site's UTM zone (``site.epsg``);
"local" = metres east/north of the UTM origin point ``site.utm_origin_east/north``
(grid-aligned, so ``east = utm_origin_east + local_east``). Headings are from TRUE north
(``heading_deg``) unless the key says ``grid_`` (from UTM grid north):
``grid_heading_deg = heading_deg - site.meridian_convergence_deg``.

- ``format``, ``version``, ``generator``, ``scenario``, ``seed``, ``description``,
  ``overrides`` (the keyword overrides given), ``parameters`` (every scenario value).
- ``files``: names of the other files in the folder.
- ``site``: ``origin_lat_deg``, ``origin_lon_deg`` (the scenario's origin), ``epsg``,
  ``utm_origin_east``, ``utm_origin_north``, ``local_frame`` (text),
  ``meridian_convergence_deg``, ``magnetic`` (``declination_deg`` east of true north,
  ``inclination_deg`` down, ``field_mgauss``), ``seabed_plane`` (``depth_at_origin_m``
  below the still water surface at the local origin, ``slope_east``/``slope_north`` in
  m of depth per m), ``water_surface`` (text).
- ``time``: ``start_time``, ``end_time`` (the nav log's span), ``first_ping_time``,
  ``last_ping_time``, ``autopilot_boot_time`` (time_boot_ms = 0), ``sonar_power_on_time``
  (pingStartTime = 0), ``duration_s``.
- ``vehicle``: ``reference_point`` ("GPS antenna"), ``antenna_height_m`` above the
  waterline, survey ``speed_mps``, ``turn_radius_m``, ``lane_spacing_m``, ``lanes``
  (UTM start/end of each lane as planned), ``current`` (``speed_mps``, ``toward_deg``
  grid), ``motion`` (wobble, roll, pitch, heave, wave period, trim).
- ``sonar``: ``device``, ``master_mode``, ``frequency_hz``, ``fan_deg``, ``n_beams``,
  ``n_ranges``, ``range_m``, ``range_resolution_m``, ``range_of_bin`` (text: the range of
  bin i), ``ping_rate_hz``, ``latency_s`` (receive time - acquisition time), the mount
  (``mount_x_m``, ``mount_y_m``, ``mount_z_m`` body FRD from the antenna, ``mount_yaw_deg``
  clockwise, ``tilt_deg`` down), ``vertical_aperture_deg``, ``horizontal_beamwidth_deg``,
  ``bearings_deg`` (the table sent in every ping), ``gamma``, ``gain_percent``,
  ``speed_of_sound_mps``, ``gain_word`` (text: what the per-row gain words mean),
  ``model`` (the image model's parameters).
- ``sensors``: ``flavour``, ``clock`` (text), ``stamps`` (link delay model), ``gps``
  (rate, bias model and parameters, and per fix: ``time`` (sample time), ``bias_east_m``,
  ``bias_north_m``, ``error_east_m``, ``error_north_m`` in grid east/north), ``compass``
  (rate, ``bias_deg`` constant part, wander, noise, per sample ``time`` and ``bias_deg``),
  ``imu`` (rate, noise, constant biases ``accel_bias_mps2`` / ``gyro_bias_dps`` FRD,
  wander, ``mag_noise_mgauss``, ``mag_misalignment_deg``).
- ``pings``: one object per ping in log order: ``ping_id``, ``time`` (the .oculus item
  time = receive time), ``acquisition_time`` (when the ping was taken; the pose below is
  the true pose then), ``east``/``north`` (UTM, antenna), ``local_east``/``local_north``,
  ``lat``/``lon``, ``heading_deg`` (true), ``grid_heading_deg``, ``course_deg`` (true
  course over ground), ``roll_deg``, ``pitch_deg`` (FRD), ``heave_m``, ``sonar_east``/
  ``sonar_north`` (UTM of the sonar head), ``sonar_depth_m`` (below the still water),
  ``altitude_m`` (sonar head above the seabed's mean plane, vertically),
  ``gain_assist_db``.
- ``features``: ``quadrat_layout`` (the paper's numbers: ``aluminium_side_m`` 0.43,
  ``pvc_side_m`` 0.62, ``row_gap_m`` 1.52 between the rows' nearest sides,
  ``frame_spacing_m`` 1.0 centre to centre, ``row_centre_distance_m``, grid
  ``row_bearing_deg``, ``centre_east``/``centre_north`` UTM), ``quadrats`` (per frame:
  ``row`` 0 aluminium / 1 PVC, ``index`` 0..3 along the row bearing, ``material``
  "aluminium"/"pvc", ``side_m`` between bar centre lines, ``bar_width_m``,
  ``bar_height_m``, ``centre_east``/``centre_north`` UTM, ``centre_local_east``/
  ``centre_local_north``, ``corners`` four [east, north] UTM of the bar centre lines,
  ``oysters`` inside), ``oysters`` (columns: ``east``, ``north`` UTM, ``length_m``,
  ``width_m``, ``height_m``, ``bearing_deg`` grid, ``clump``, ``quadrat``),
  ``shell_patches`` (UTM centre, radius), ``ripples``.
- ``seabed``: ``file``/``height_file``, ``height_scale_m``, ``resolution_m``, UTM
  ``west``/``north``/``east``/``south`` edges, ``width_px``, ``height_px``,
  ``reflectivity_scale`` (text).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from tools.sim.scenarios import Scenario, scenario_dict
from tools.sim.seabed import (
    ALUMINIUM_SIDE_M,
    FRAME_SPACING_M,
    PVC_SIDE_M,
    ROW_CENTRE_DISTANCE_M,
    ROW_GAP_M,
    Seabed,
)
from tools.sim.site import SiteFrame
from tools.sim.sonar import SonarModel
from tools.sim.tlog import NavStreams
from tools.sim.trajectory import SurveyPath

FloatArray = npt.NDArray[np.float64]

TRUTH_FORMAT = "seamap-sim-truth"
TRUTH_VERSION = 1


@dataclass(frozen=True)
class PingTruth:
    """Per ping: the sonar's id, acquisition and receive times (UNIX s), the gain-assist
    level (dB) and the true state at acquisition (``Motion.at`` fields plus
    ``sonar_north``/``sonar_east``/``sonar_depth`` and ``altitude``, local metres)."""

    ids: npt.NDArray[np.int64]
    acquisition: FloatArray
    receive: FloatArray
    assist_db: FloatArray
    state: dict[str, FloatArray]


def round_json(x: Any, digits: int = 6) -> Any:
    """Round floats (in lists and dicts too) for a compact, stable JSON."""
    if isinstance(x, dict):
        return {k: round_json(v, digits) for k, v in x.items()}
    if isinstance(x, np.ndarray):
        return [round_json(v, digits) for v in x.tolist()]
    if isinstance(x, list | tuple):
        return [round_json(v, digits) for v in x]
    if isinstance(x, float | np.floating):
        return round(float(x), digits)
    if isinstance(x, np.integer):
        return int(x)
    return x


def write_truth(path: Path, truth: dict[str, Any]) -> None:
    path.write_text(json.dumps(truth, indent=1, sort_keys=False) + "\n", encoding="utf-8")


def _lanes_utm(path: SurveyPath, site: SiteFrame) -> list[dict[str, float]]:
    return [
        {
            "start_east": round(e0 + site.utm_east0, 3),
            "start_north": round(n0 + site.utm_north0, 3),
            "end_east": round(e1 + site.utm_east0, 3),
            "end_north": round(n1 + site.utm_north0, 3),
        }
        for e0, n0, e1, n1 in path.lanes
    ]


def build_truth(
    s: Scenario,
    seed: int,
    overrides: dict[str, Any],
    site: SiteFrame,
    survey_path: SurveyPath,
    seabed: Seabed,
    model: SonarModel,
    plan: PingTruth,
    streams: NavStreams,
    span: tuple[float, float],
    seabed_section: dict[str, Any],
) -> dict[str, Any]:
    """The truth.json document (see the module doc); ``span``: the logs' (start, end)."""
    r = round_json
    at = plan.state
    start, end = span
    e0, n0 = site.utm_east0, site.utm_north0
    true_heading = np.degrees(site.grid_to_true(at["heading"])) % 360.0
    grid_heading = np.degrees(at["heading"]) % 360.0
    vn, ve = site.rotate_grid_to_true(at["vel_north"], at["vel_east"])
    course = np.degrees(np.arctan2(ve, vn)) % 360.0
    lat, lon = site.to_latlon(at["east"], at["north"])
    pings = [
        {
            "ping_id": int(plan.ids[k]),
            "time": r(plan.receive[k]),
            "acquisition_time": r(plan.acquisition[k]),
            "east": r(at["east"][k] + e0, 4),
            "north": r(at["north"][k] + n0, 4),
            "local_east": r(at["east"][k], 4),
            "local_north": r(at["north"][k], 4),
            "lat": r(lat[k], 9),
            "lon": r(lon[k], 9),
            "heading_deg": r(true_heading[k], 4),
            "grid_heading_deg": r(grid_heading[k], 4),
            "course_deg": r(course[k], 3),
            "roll_deg": r(math.degrees(at["roll"][k]), 4),
            "pitch_deg": r(math.degrees(at["pitch"][k]), 4),
            "heave_m": r(at["up"][k] - s.antenna_height_m, 4),
            "sonar_east": r(at["sonar_east"][k] + e0, 4),
            "sonar_north": r(at["sonar_north"][k] + n0, 4),
            "sonar_depth_m": r(at["sonar_depth"][k], 4),
            "altitude_m": r(at["altitude"][k], 4),
            "gain_assist_db": r(plan.assist_db[k], 3),
        }
        for k in range(len(plan.acquisition))
    ]
    gps, hd, imu = streams.gps, streams.heading, streams.imu
    gps_sel = (gps.time >= start) & (gps.time < end)
    hd_sel = (hd.time >= start) & (hd.time < end)
    return {
        "format": TRUTH_FORMAT,
        "version": TRUTH_VERSION,
        "generator": "tools.sim",
        "scenario": s.name,
        "seed": seed,
        "description": s.description,
        "overrides": {k: v for k, v in sorted(overrides.items())},
        "files": {
            "sonar": "sonar.oculus",
            "nav": "nav.tlog",
            "seabed": "seabed.tif",
            "seabed_height": "seabed_height.tif",
            "config": "site.toml",
        },
        "site": {
            "origin_lat_deg": s.origin_lat_deg,
            "origin_lon_deg": s.origin_lon_deg,
            "epsg": site.epsg,
            "utm_origin_east": e0,
            "utm_origin_north": n0,
            "local_frame": "metres east/north of (utm_origin_east, utm_origin_north), UTM "
            "grid-aligned: east = utm_origin_east + local_east",
            "meridian_convergence_deg": r(site.convergence_deg, 8),
            "magnetic": {
                "declination_deg": s.declination_deg,
                "inclination_deg": s.inclination_deg,
                "field_mgauss": s.field_mgauss,
            },
            "seabed_plane": {
                "depth_at_origin_m": s.water_depth_m,
                "slope_east": s.seabed_slope_east,
                "slope_north": s.seabed_slope_north,
                "depth": "depth_at_origin_m + slope_east * local_east + slope_north * "
                "local_north, metres below the still water surface",
            },
            "water_surface": "still water at 0 m; no tide",
        },
        "time": {
            "start_time": r(start),
            "end_time": r(end),
            "first_ping_time": r(plan.receive[0]) if len(pings) else None,
            "last_ping_time": r(plan.receive[-1]) if len(pings) else None,
            "autopilot_boot_time": r(s.start_time - s.autopilot_uptime_s),
            "sonar_power_on_time": r(s.start_time - s.sonar_uptime_s),
            "duration_s": r(end - start),
        },
        "vehicle": {
            "reference_point": "GPS antenna",
            "antenna_height_m": s.antenna_height_m,
            "speed_mps": s.speed_mps,
            "turn_radius_m": min(s.turn_radius_m, s.lane_spacing_m / 2),
            "lane_spacing_m": s.lane_spacing_m,
            "lanes": _lanes_utm(survey_path, site),
            "current": {"speed_mps": s.current_mps, "toward_deg": s.current_toward_deg},
            "motion": {
                "yaw_wobble_deg": s.yaw_wobble_deg,
                "roll_deg": s.roll_deg,
                "pitch_deg": s.pitch_deg,
                "trim_deg": s.trim_deg,
                "heave_m": s.heave_m,
                "wave_period_s": s.wave_period_s,
                "cross_track_m": s.cross_track_m,
            },
        },
        "sonar": {
            "device": "Oculus M1200d (simulated, low-frequency mode)",
            "master_mode": s.master_mode,
            "frequency_hz": s.frequency_hz,
            "fan_deg": s.fan_deg,
            "n_beams": model.n_beams,
            "n_ranges": model.n_ranges,
            "range_m": s.range_m,
            "range_resolution_m": s.range_resolution_m,
            "range_of_bin": "(i + 0.5) * range_resolution_m",
            "ping_rate_hz": s.ping_rate_hz,
            "latency_s": s.sonar_latency_s,
            "mount_x_m": s.mount_x_m,
            "mount_y_m": s.mount_y_m,
            "mount_z_m": s.mount_z_m,
            "mount_yaw_deg": s.mount_yaw_deg,
            "tilt_deg": s.tilt_deg,
            "vertical_aperture_deg": s.vertical_aperture_deg,
            "horizontal_beamwidth_deg": s.horizontal_beamwidth_deg,
            "bearings_deg": r(np.degrees(model.bearings_rad), 2),
            "gamma": s.gamma,
            "gain_percent": s.gain_percent,
            "speed_of_sound_mps": s.speed_of_sound_mps,
            "gain_word": "round(65536 * g): g = linear intensity gain applied to the row "
            "relative to the nominal TVG (steps, per-row error, gain assist)",
            "model": {
                "full_scale": s.full_scale,
                "noise_floor": s.noise_floor,
                "speckle_shape": s.speckle_shape,
                "tvg_residual_exponent": s.tvg_residual_exponent,
                "tvg_step_db": s.tvg_step_db,
                "row_gain_jitter_db": s.row_gain_jitter_db,
                "gain_assist_db": s.gain_assist_db,
                "backscatter": "reflectivity * sin^2(local grazing) (Lambert)",
                "vertical_pattern": "exp(-4 ln2 (elevation / vertical_aperture)^2) + 0.002",
            },
        },
        "sensors": {
            "flavour": s.flavour,
            "clock": "all stamps and sample times are UNIX seconds of the boat computer; the "
            "autopilot clock is synchronous with it (time_boot_ms counts from "
            "autopilot_boot_time)",
            "stamps": {
                "delay_s": s.stamp_delay_s,
                "jitter_mean_s": s.stamp_jitter_s,
                "model": "receive stamp = sample time + delay_s + exponential(jitter_mean_s)",
            },
            "gps": {
                "rate_hz": s.gps_rate_hz,
                "bias_model": "first-order Gauss-Markov per axis (grid east/north), stationary",
                "bias_sigma_m": s.gps_bias_sigma_m,
                "bias_tau_s": s.gps_bias_tau_s,
                "noise_m": s.gps_noise_m,
                "vertical_sigma_m": s.gps_vertical_sigma_m,
                "fixes": {
                    "time": r(gps.time[gps_sel]),
                    "bias_east_m": r(gps.bias_east[gps_sel], 4),
                    "bias_north_m": r(gps.bias_north[gps_sel], 4),
                    "error_east_m": r(gps.error_east[gps_sel], 4),
                    "error_north_m": r(gps.error_north[gps_sel], 4),
                },
            },
            "compass": {
                "rate_hz": s.heading_rate_hz,
                "messages": ["ATTITUDE.yaw", "GLOBAL_POSITION_INT.hdg", "VFR_HUD.heading"],
                "bias_deg": s.compass_bias_deg,
                "bias_wander_deg": s.compass_bias_wander_deg,
                "bias_tau_s": s.compass_bias_tau_s,
                "noise_deg": s.compass_noise_deg,
                "samples": {
                    "time": r(hd.time[hd_sel]),
                    "bias_deg": r(np.degrees(hd.bias[hd_sel]), 4),
                },
            },
            "imu": {
                "rate_hz": s.imu_rate_hz,
                "message": "HIGHRES_IMU" if s.flavour == "px4" else "RAW_IMU",
                "position": "at the GPS antenna (no lever arm)",
                "accel_noise_mps2": s.accel_noise_mps2,
                "accel_bias_mps2": r(imu.accel_bias_const),
                "gyro_noise_dps": s.gyro_noise_dps,
                "gyro_bias_dps": r(np.degrees(imu.gyro_bias_const)),
                "bias_wander": "Gauss-Markov, sigma = imu_bias_wander * bias sigma, 300 s",
                "imu_bias_wander": s.imu_bias_wander,
                "mag_noise_mgauss": s.mag_noise_mgauss,
                "mag_misalignment_deg": s.compass_bias_deg,
            },
        },
        "pings": pings,
        "features": features_section(seabed, site, s),
        "seabed": seabed_section,
        "parameters": round_json(scenario_dict(s)),
    }


def features_section(seabed: Seabed, site: SiteFrame, s: Scenario) -> dict[str, Any]:
    """The truth's ``features``: quadrats, oysters, shell patches, ripples (UTM)."""
    e0, n0 = site.utm_east0, site.utm_north0
    oysters = seabed.oysters
    in_quadrat = np.bincount(oysters.quadrat[oysters.quadrat >= 0], minlength=len(seabed.quadrats))
    quadrats = []
    for qi, q in enumerate(seabed.quadrats):
        corners = q.corners() + np.array([e0, n0])
        quadrats.append(
            {
                "row": q.row,
                "index": q.index,
                "material": q.material,
                "side_m": q.side_m,
                "bar_width_m": q.bar_width_m,
                "bar_height_m": q.bar_height_m,
                "centre_east": round_json(q.centre_east + e0),
                "centre_north": round_json(q.centre_north + n0),
                "centre_local_east": round_json(q.centre_east),
                "centre_local_north": round_json(q.centre_north),
                "corners": round_json(corners),
                "oysters": int(in_quadrat[qi]),
            }
        )
    return {
        "quadrat_layout": {
            "aluminium_side_m": ALUMINIUM_SIDE_M,
            "pvc_side_m": PVC_SIDE_M,
            "row_gap_m": ROW_GAP_M,
            "frame_spacing_m": FRAME_SPACING_M,
            "row_centre_distance_m": round_json(ROW_CENTRE_DISTANCE_M),
            "row_bearing_deg": s.quadrat_row_bearing_deg,
            "centre_east": round_json(s.quadrat_centre_east_m + e0),
            "centre_north": round_json(s.quadrat_centre_north_m + n0),
            "sides": "side_m is measured between bar centre lines; row_gap_m between the "
            "centre lines of the rows' nearest sides",
        },
        "quadrats": quadrats,
        "oysters": {
            "count": len(oysters),
            "east": round_json(oysters.east + e0, 3),
            "north": round_json(oysters.north + n0, 3),
            "length_m": round_json(oysters.length, 3),
            "width_m": round_json(oysters.width, 3),
            "height_m": round_json(oysters.height, 3),
            "bearing_deg": round_json(np.degrees(oysters.bearing) % 360.0, 1),
            "clump": oysters.clump.tolist(),
            "quadrat": oysters.quadrat.tolist(),
        },
        "shell_patches": [
            {
                "east": round_json(p.centre_east + e0, 3),
                "north": round_json(p.centre_north + n0, 3),
                "radius_m": round_json(p.radius_m, 3),
            }
            for p in seabed.shell_patches
        ],
        "ripples": {
            "wavelength_m": s.ripple_wavelength_m,
            "amplitude_m": s.ripple_amplitude_m,
            "bearing_deg": s.ripple_bearing_deg,
        },
    }
