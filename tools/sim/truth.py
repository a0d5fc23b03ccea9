"""truth.json: what really happened in a simulated survey, for later stages to score.

truth.json (format "seamap-sim-truth", version 1) — everything later stages need to
score a trajectory or a mosaic. Units: metres, seconds (UNIX, the boat computer's clock),
degrees where the key says ``_deg``. "UTM" = the site's UTM zone (``site.epsg``);
"local" = metres east/north of the UTM origin point ``site.utm_origin_east/north``
(grid-aligned, so ``east = utm_origin_east + local_east``). Headings are from TRUE north
(``heading_deg``) unless the key says ``grid_`` (from UTM grid north):
``grid_heading_deg = heading_deg - site.meridian_convergence_deg``.

- ``format``, ``version``, ``generator``, ``scenario``, ``seed``, ``description``,
  ``overrides`` (the keyword overrides given), ``parameters`` (every scenario value as
  simulated: the field day's draws in place), ``field_day`` (``randomised``, ``explicit``
  fields the caller pinned, ``drawn``: each drawn value, ``ranges``: [low, high, kind]).
- ``files``: names of the other files in the folder.
- ``site``: ``origin_lat_deg``, ``origin_lon_deg`` (the scenario's origin), ``epsg``,
  ``utm_origin_east``, ``utm_origin_north``, ``local_frame`` (text),
  ``meridian_convergence_deg``, ``magnetic`` (``declination_deg`` east of true north,
  ``inclination_deg`` down, ``field_mgauss``), ``seabed_plane`` (``depth_at_origin_m``
  below the still water surface at the local origin, ``slope_east``/``slope_north`` in
  m of depth per m, ``seabed_type``, ``undulation``: its plane waves or null),
  ``water_surface`` (text), ``tide`` (``rate_mps``, ``rate_m_per_h``).
- ``time``: ``start_time``, ``end_time`` (the nav log's span), ``first_ping_time``,
  ``last_ping_time``, ``autopilot_boot_time`` (time_boot_ms = 0), ``sonar_power_on_time``
  (pingStartTime = 0), ``duration_s``.
- ``vehicle``: ``reference_point`` ("GPS antenna"), ``antenna_height_m`` above the
  waterline, survey ``speed_mps``, ``turn_radius_m``, ``lane_spacing_m``, ``lanes``
  (UTM start/end of each lane as planned), ``current`` (``speed_mps``, ``toward_deg``
  grid), ``motion`` (wobble, roll, pitch, heave, wave period and the component
  ``wave_periods_s``, trim).
- ``sonar``: ``device``, ``master_mode``, ``frequency_hz``, ``fan_deg``, ``n_beams``,
  ``n_ranges``, ``range_m``, ``range_resolution_m``, ``range_of_bin`` (text: the range of
  bin i), ``ping_rate_hz``, ``latency_s`` (the fixed part of receive time - acquisition
  time) and ``latency_jitter_mean_s`` (mean of its exponential tail), ``beam_geometry``
  (text: the line array's cones), the mount
  (``mount_x_m``, ``mount_y_m``, ``mount_z_m`` body FRD from the antenna, ``mount_yaw_deg``
  clockwise, ``tilt_deg`` down), ``vertical_aperture_deg``, ``horizontal_beamwidth_deg``,
  ``bearings_deg`` (the table sent in every ping), ``gamma``, ``gain_percent``,
  ``speed_of_sound_mps``, ``gain_word`` (text: what the per-row gain words mean),
  ``model`` (the image model's parameters).
- ``sensors``: ``flavour``, ``clock`` (text), ``stamps`` (link delay model), ``gps``
  (rate, bias model and parameters, ``lag_s``, ``outage`` (``start_time``/``end_time`` or
  null), and per fix: ``time`` (the stamp), ``antenna_time`` (time - lag: when the antenna
  was where the fix says), ``antenna_east``/``antenna_north`` (UTM of the antenna then),
  ``bias_east_m``, ``bias_north_m``, ``error_east_m``, ``error_north_m`` (grid east/north:
  reported minus the antenna at antenna_time), ``stamp_error_east_m``/``_north_m``
  (reported minus the antenna at the stamp: what the lag adds), ``h_acc_m``,
  ``fix_type``; ``kind`` "m8n" or "rtk", ``rtk`` its parameters or null), ``echosounder``
  (null, or the mount, rate, cone, noise, dropout and false-return rates, and per
  sounding ``time``, ``ping_time``, ``transducer_east``/``_north`` UTM,
  ``transducer_depth_m``, ``vertical_m`` (straight down to the bed), ``nearest_m`` (the
  nearest bottom in the cone), ``reported_m`` (null: no message), ``signal_quality``,
  ``kind``), ``compass`` (rate, ``bias_deg`` constant part, wander, the deviation's
  amplitudes, phases and ``deviation_coefficients`` A..D of ``A sin psi + B cos psi + C
  sin 2 psi + D cos 2 psi`` (psi magnetic heading), the correlated noise, white
  ``noise_deg``, and per sample ``time``, ``heading_deg`` (the true heading then),
  ``bias_deg`` (constant + wander),
  ``deviation_deg``, ``noise_deg`` (correlated + white), ``error_deg`` (the total heading
  error: reported minus true)), ``imu`` (rate, noise, constant biases
  ``accel_bias_mps2`` / ``gyro_bias_dps`` FRD, wander, ``mag_noise_mgauss``,
  ``mag_misalignment_deg`` (the constant part of the magnetometer's heading error; it
  also carries the wander and the deviation: ``mag_error``)).
- ``pings``: one object per ping in log order: ``ping_id``, ``time`` (the .oculus item
  time = receive time), ``acquisition_time`` (when the ping was taken; the pose below is
  the true pose then), ``east``/``north`` (UTM, antenna), ``local_east``/``local_north``,
  ``lat``/``lon``, ``heading_deg`` (true), ``grid_heading_deg``, ``course_deg`` (true
  course over ground), ``roll_deg``, ``pitch_deg`` (FRD), ``heave_m``, ``sonar_east``/
  ``sonar_north`` (UTM of the sonar head), ``sonar_depth_m`` (below the still water),
  ``altitude_m`` (sonar head above the bed's smooth surface, the mean plane raised by any
  undulation, vertically: tide, heave, slope and undulation in it), ``altitude_normal_m``
  (the same along the surface's normal), ``water_level_m`` (the tide's rise since
  start_time), ``gain_assist_db``.
- ``features``: ``quadrat_layout`` (the paper's numbers: ``aluminium_side_m`` 0.43,
  ``pvc_side_m`` 0.62, ``row_gap_m`` 1.52 between the rows' nearest sides,
  ``frame_spacing_m`` 1.0 centre to centre, ``row_centre_distance_m``, grid
  ``row_bearing_deg``, ``centre_east``/``centre_north`` UTM), ``quadrats`` (per frame:
  ``row`` 0 aluminium / 1 PVC, ``index`` 0..3 along the row bearing, ``material``
  "aluminium"/"pvc", ``side_m`` between bar centre lines, ``bar_width_m``,
  ``bar_height_m``, ``centre_east``/``centre_north`` UTM, ``centre_local_east``/
  ``centre_local_north``, ``corners`` four [east, north] UTM of the bar centre lines,
  ``oysters`` inside, ``array`` the array it belongs to), ``quadrat_arrays`` (per array:
  ``array``, UTM ``centre_east``/``centre_north``, ``row_bearing_deg``), ``racks`` (per
  rack: its parameters and ``bars``, [east0, north0, east1, north1] UTM of each bar's
  centre line), ``oysters`` (columns: ``east``, ``north`` UTM, ``length_m``, ``width_m``,
  ``height_m``, ``bearing_deg`` grid, ``clump``, ``quadrat``), ``shell_patches`` and
  ``mud_patches`` (UTM centre, radius), ``ripples`` (the main train's ``wavelength_m``,
  ``amplitude_m``, ``bearing_deg``, and ``trains``: per train its mean values, ``bend_deg``
  and the warp's plane waves, from which the local wave vector anywhere is
  ``2 pi / wavelength_m (u + sum_j a_j cos(k_j . x + c_j) k_j)``, x local metres).
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

from tools.sim.features import features_section
from tools.sim.jsonround import round_json
from tools.sim.scenarios import Scenario, scenario_dict
from tools.sim.seabed import Seabed
from tools.sim.site import SiteFrame
from tools.sim.sonar import SonarModel
from tools.sim.tlog import NavStreams
from tools.sim.trajectory import SurveyPath, wave_components

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
    field_day: dict[str, Any] | None = None,
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
            "altitude_normal_m": r(at["altitude_normal"][k], 4),
            "water_level_m": r(at["water_level"][k], 5),
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
                "local_north - undulation(local), metres below the still water surface at "
                "the survey's start",
                "seabed_type": s.seabed_type,
                "undulation": _undulation(seabed),
            },
            "water_surface": "still water at 0 m at start_time; it rises at tide.rate_mps "
            "(the boat floats on it: every depth here is below the start's surface)",
            "tide": {
                "rate_mps": s.tide_rate_mps,
                "rate_m_per_h": r(s.tide_rate_mps * 3600.0, 6),
                "level": "rate_mps * (time - start_time), metres above the start's level",
            },
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
                "wave_periods_s": r(wave_components(s), 4),
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
            "latency_jitter_mean_s": s.sonar_latency_jitter_s,
            "beam_geometry": "line array along the sonar's y axis: beam theta is the cone "
            "sin(theta) = p_y / |p| (p in the sonar frame: x boresight, y starboard, z down "
            "when level), p = r (cos theta cos psi, sin theta, cos theta sin psi)",
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
                "vertical_pattern": "exp(-4 ln2 (psi / vertical_aperture)^2) + 0.002, psi the "
                "angle about the array axis",
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
            "gps": _gps_section(s, streams, gps_sel, e0, n0),
            "compass": _compass_section(s, streams, hd_sel),
            "echosounder": _echosounder_section(s, streams, (start, end), e0, n0),
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
                "mag_error": "the field is seen from the attitude with the heading turned by "
                "the compass bias, its wander and the deviation (not its correlated or white "
                "heading noise)",
            },
        },
        "pings": pings,
        "features": features_section(seabed, site, s),
        "seabed": seabed_section,
        "parameters": round_json(scenario_dict(s)),
        "field_day": round_json(field_day or {}),
    }


def _gps_section(
    s: Scenario, streams: NavStreams, sel: npt.NDArray[np.bool_], e0: float, n0: float
) -> dict[str, Any]:
    """truth.json's ``sensors.gps`` (see the module doc)."""
    r = round_json
    gps = streams.gps
    at_stamp = streams.motion.at(gps.time[sel])
    reported_e = gps.antenna_east[sel] + gps.error_east[sel]
    reported_n = gps.antenna_north[sel] + gps.error_north[sel]
    outage = None
    if s.gps_outage_start_s is not None:
        begin = streams.motion.start + s.gps_outage_start_s
        outage = {"start_time": r(begin), "end_time": r(begin + s.gps_outage_duration_s)}
    rtk = None
    if s.gnss_kind == "rtk":
        rtk = {
            "noise_m": s.rtk_noise_m,
            "bias_sigma_m": s.rtk_bias_sigma_m,
            "bias_tau_s": s.rtk_bias_tau_s,
            "vertical_sigma_m": s.rtk_vertical_sigma_m,
            "lag_s": s.rtk_lag_s,
            "float_interval_s": s.rtk_float_interval_s,
            "float_duration_s": s.rtk_float_duration_s,
            "float_sigma_m": s.rtk_float_sigma_m,
            "model": "fix_type 6: Gauss-Markov bias_sigma_m / bias_tau_s plus white noise_m "
            "per axis, h_acc hypot of the two +-15 % within 10-20 mm; fix_type 5 (float) "
            "episodes: plus a 10 s Gauss-Markov error of float_sigma_m, 3 x the noise; "
            "the M8N fields above are not used",
        }
    return {
        "kind": s.gnss_kind,
        "rtk": rtk,
        "rate_hz": s.gps_rate_hz,
        "bias_model": "first-order Gauss-Markov per axis (grid east/north), stationary",
        "bias_sigma_m": s.gps_bias_sigma_m,
        "bias_tau_s": s.gps_bias_tau_s,
        "noise_m": s.gps_noise_m,
        "vertical_sigma_m": s.gps_vertical_sigma_m,
        "lag_s": s.gps_lag_s,
        "lag": "a fix stamped t reports the antenna where it was at t - lag_s",
        "h_acc": "reported 1-sigma per axis: hypot(bias_sigma_m, noise_m), +-15 % wobble",
        "outage": outage,
        "fixes": {
            "time": r(gps.time[sel]),
            "antenna_time": r(gps.antenna_time[sel]),
            "antenna_east": r(gps.antenna_east[sel] + e0, 4),
            "antenna_north": r(gps.antenna_north[sel] + n0, 4),
            "bias_east_m": r(gps.bias_east[sel], 4),
            "bias_north_m": r(gps.bias_north[sel], 4),
            "error_east_m": r(gps.error_east[sel], 4),
            "error_north_m": r(gps.error_north[sel], 4),
            "stamp_error_east_m": r(reported_e - at_stamp["east"], 4),
            "stamp_error_north_m": r(reported_n - at_stamp["north"], 4),
            "h_acc_m": r(gps.h_acc[sel], 3),
            "fix_type": gps.fix_type[sel].tolist(),
        },
    }


def _compass_section(
    s: Scenario, streams: NavStreams, sel: npt.NDArray[np.bool_]
) -> dict[str, Any]:
    """truth.json's ``sensors.compass`` (see the module doc)."""
    r = round_json
    hd = streams.heading
    return {
        "rate_hz": s.heading_rate_hz,
        "messages": ["ATTITUDE.yaw", "GLOBAL_POSITION_INT.hdg", "VFR_HUD.heading"],
        "bias_deg": s.compass_bias_deg,
        "bias_wander_deg": s.compass_bias_wander_deg,
        "bias_tau_s": s.compass_bias_tau_s,
        "deviation_1_deg": s.compass_deviation_1_deg,
        "deviation_1_phase_deg": s.compass_deviation_1_phase_deg,
        "deviation_2_deg": s.compass_deviation_2_deg,
        "deviation_2_phase_deg": s.compass_deviation_2_phase_deg,
        "deviation": "d1 sin(psi + p1) + d2 sin(2 psi + p2), psi = true heading - declination",
        "deviation_coefficients": r(streams.compass.coefficients_deg()),
        "gm_sigma_deg": s.compass_gm_sigma_deg,
        "gm_tau_s": s.compass_gm_tau_s,
        "noise_deg": s.compass_noise_deg,
        "error": "reported = true heading + bias (constant + wander) + deviation + noise "
        "(Gauss-Markov gm_sigma_deg, gm_tau_s, plus white noise_deg)",
        "samples": {
            "time": r(hd.time[sel]),
            "heading_deg": r(np.degrees(np.mod(hd.heading_true - hd.error, 2 * np.pi))[sel], 4),
            "bias_deg": r(np.degrees(hd.bias[sel]), 4),
            "deviation_deg": r(np.degrees(hd.deviation[sel]), 4),
            "noise_deg": r(np.degrees(hd.noise[sel]), 4),
            "error_deg": r(np.degrees(hd.error[sel]), 4),
        },
    }


def _undulation(seabed: Seabed) -> dict[str, Any] | None:
    """The bed's undulation (``bathymetry``) as its plane waves, or None."""
    und = seabed.undulation
    if und is None:
        return None
    return {
        "height": "sum_j amplitude_m_j sin(k_east_j local_east + k_north_j local_north + "
        "phase_j), metres above the plane (the bed that much shallower)",
        "k_east_rad_per_m": round_json(und.k_east),
        "k_north_rad_per_m": round_json(und.k_north),
        "amplitude_m": round_json(und.amplitude_m),
        "phase_rad": round_json(und.phase),
    }


def _echosounder_section(
    s: Scenario, streams: NavStreams, span: tuple[float, float], e0: float, n0: float
) -> dict[str, Any] | None:
    """truth.json's ``sensors.echosounder`` (None without one): the device and, per
    sounding in the log's span, the truth and what was reported."""
    sounding = streams.echosounder
    if sounding is None:
        return None
    r = round_json
    sel = (sounding.time >= span[0]) & (sounding.time < span[1])
    reported = [None if not math.isfinite(v) else round(v, 4) for v in sounding.reported_m[sel]]
    return {
        "messages": ["DISTANCE_SENSOR"] + ([] if s.flavour == "px4" else ["RANGEFINDER"]),
        "mount_x_m": s.echosounder_x_m,
        "mount_y_m": s.echosounder_y_m,
        "mount_z_m": s.echosounder_z_m,
        "mount": "body FRD from the GPS antenna; the beam looks along body z (down)",
        "rate_hz": s.echosounder_rate_hz,
        "beam_deg": s.echosounder_beam_deg,
        "noise": "noise_m + noise_fraction * range (1 sigma)",
        "noise_m": s.echosounder_noise_m,
        "noise_fraction": s.echosounder_noise_fraction,
        "dropout": s.echosounder_dropout,
        "false_rate": s.echosounder_false_rate,
        "lag_s": s.echosounder_lag_s,
        "soundings": {
            "time": r(sounding.time[sel]),
            "ping_time": r(sounding.ping_time[sel]),
            "transducer_east": r(sounding.east[sel] + e0, 4),
            "transducer_north": r(sounding.north[sel] + n0, 4),
            "transducer_depth_m": r(sounding.depth[sel], 4),
            "vertical_m": r(sounding.vertical_m[sel], 4),
            "nearest_m": r(sounding.nearest_m[sel], 4),
            "reported_m": reported,
            "signal_quality": sounding.quality[sel].tolist(),
            "kind": [k for k, keep in zip(sounding.kind, sel.tolist(), strict=True) if keep],
            "meaning": "time: the message's time_boot (UNIX s); ping_time: when it pinged; "
            "vertical_m: transducer to the bed straight down (relief in); nearest_m: the "
            "nearest bottom in the cone (a perfect device's reading); reported_m: the "
            "message's distance (null: no message); kind: ok, low_signal (flagged, quality "
            "1-10, the last distance held), missing (no message), false_return (weed/fish)",
        },
    }
