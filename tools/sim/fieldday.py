"""The field day: what changes from one survey day to the next, drawn from the seed.

A boat that goes out twice never meets the same GNSS error, compass, gyro bias, chop or
sand ripples: ``draw_field_day(s, rng)`` draws each value of ``FIELD_DAY`` within its
realistic range and returns the scenario of that day with the values drawn, and the
values. A field the caller set explicitly (``Scenario.explicit``) keeps its value, and
``Scenario.randomise = False`` keeps every default; either way every value is drawn, in
the table's order, so pinning one field never changes the others.

Ranges (units as in the field names; "signed": a magnitude uniform in the range, either
sign):

- GNSS, a u-blox M8N with a patch antenna over water, open sky: a Gauss-Markov error of
  1.0-1.5 m per axis with a 20-90 s correlation time (multipath off the water and the
  hull, ionosphere and orbit residuals of an SBAS-less single-frequency fix), white noise
  0.5-0.8 m, the fix 0.1-0.2 s old at its stamp (navigation solution and UART).
- Compass (the autopilot's magnetometer near motors and batteries, calibrated on land):
  a constant error of 1-5 degrees either way, one- and two-cycle deviations of 0.5-2
  degrees with random phases, correlated fused-heading noise 0.5-1.5 degrees over 2-20 s,
  white noise 0.1-0.3 degrees.
- Gyro: 0.05-0.3 degrees/s per axis either way left after the boot calibration (MEMS
  gyros drift with temperature after it).
- Sonar: 0.03-0.12 s from acquisition to the boat computer's receive stamp.
- Boat: a light chop, roll and pitch 2-3 degrees RMS, heave 2-5 cm, dominant period
  2-3 s; yaw wobble 1-3 degrees; cross-track error 4-15 cm.
- Seabed: ripples 0.22-0.45 m (amplitude 4-12 mm) in any direction, crests bending
  6-20 degrees across the site; a second train 0.5-1.2 m (2-6 mm) in any direction.

Two more tables come from child streams of the same generator (``SeedSequence`` children
of its seed, so drawing them leaves the table above, and so every existing survey,
exactly as it was):

- ``SENSOR_DAY`` (child 2), used where the boat carries the sensor: an RTK receiver's
  white noise 1-2 cm, wandering error 5-12 mm over 60-300 s, fixes 20-50 ms old, drops to
  RTK float every 90-300 s on average lasting 3-10 s; an echosounder losing the bottom
  1-6 % of the time and locking on weed or fish in 0.2-1 % of its soundings.
- ``wide`` scenarios (``Scenario.wide``; child 1, ``draw_wide``): the site and the set-up
  a survey crew meets. Seabed type (sand, mud, shell, gravel, objects: equal odds); a
  slope of 0-10 % toward any bearing, limited so that the bed under the lanes stays at
  least 0.5 m deep (the sonar head rides 0.2 m under the surface: ``MIN_DEPTH_M``); half
  the days a long undulation of 10-40 m wavelength and 2 cm to ``wavelength / 160``
  (at most 0.2 m: slopes of at most 4 % on top of the plane); a tide of -0.3..0.3 m/h;
  0.8-6 m of water at the survey centre; tilt 10-30 degrees, steepened when the water is
  deep so that the boresight meets the bed within 1/1.2 of the longest range (20 m);
  the range set by the crew so the boresight's bed lies well inside it, and not so far
  that the image is mostly beyond the beam: uniform between ``1.2 b`` (at least 3 m) and
  ``4 b`` (at least 2 m more; at most 20 m), ``b = h / sin(tilt)`` the slant range where
  the boresight meets the bed, with the M1200d's range resolution at that range
  (``swath.range_resolution_for``); 0.3-1.2 m/s; the Oculus' ping rates 2,
  5, 10 or 15 Hz; an echosounder half the days (forward -0.5..0.5 m, starboard
  -0.3..0.3 m, down 0.2-0.4 m from the antenna, 5-10 Hz); an RTK receiver a third of
  the days (fixes at 5 or 10 Hz). Three lanes spaced by ``swath.lane_spacing_for`` at
  the survey's altitude, as long as ``clip(max(16 m, 2 swaths, 50 s of travel), 16 m,
  60 m)``, so that a neighbouring lane sees the same seabed and the survey takes about
  3-5 minutes. A field the caller pins keeps its value and the derived fields follow it.
- ``wide`` scenarios' receiver (child 3, ``draw_receiver``): how the sonar sends its
  pings, as the units in the field do: SimplePingResult v1 (older firmware, msgVersion 0,
  no attitude) a third of the days, 16-bit samples a third, no gain rows a third.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from tools.sim.rngs import child_rng
from tools.sim.scenarios import SEABED_TYPES, Scenario
from tools.sim.swath import ground_swath_m, lane_spacing_for, range_resolution_for


@dataclass(frozen=True)
class Draw:
    """One drawn field: uniform in [low, high]; ``signed``: the magnitude uniform in
    [low, high] and either sign with equal odds."""

    field: str
    low: float
    high: float
    signed: bool = False

    def sample(self, rng: np.random.Generator) -> float:
        value = float(rng.uniform(self.low, self.high))
        sign = 1.0 if rng.random() < 0.5 else -1.0
        return sign * value if self.signed else value


FIELD_DAY: tuple[Draw, ...] = (
    Draw("gps_bias_sigma_m", 1.0, 1.5),
    Draw("gps_bias_tau_s", 20.0, 90.0),
    Draw("gps_noise_m", 0.5, 0.8),
    Draw("gps_lag_s", 0.1, 0.2),
    Draw("compass_bias_deg", 1.0, 5.0, signed=True),
    Draw("compass_deviation_1_deg", 0.5, 2.0),
    Draw("compass_deviation_1_phase_deg", 0.0, 360.0),
    Draw("compass_deviation_2_deg", 0.5, 2.0),
    Draw("compass_deviation_2_phase_deg", 0.0, 360.0),
    Draw("compass_gm_sigma_deg", 0.5, 1.5),
    Draw("compass_gm_tau_s", 2.0, 20.0),
    Draw("compass_noise_deg", 0.1, 0.3),
    Draw("gyro_bias_x_dps", 0.05, 0.3, signed=True),
    Draw("gyro_bias_y_dps", 0.05, 0.3, signed=True),
    Draw("gyro_bias_z_dps", 0.05, 0.3, signed=True),
    Draw("sonar_latency_s", 0.03, 0.12),
    Draw("roll_deg", 2.0, 3.0),
    Draw("pitch_deg", 2.0, 3.0),
    Draw("heave_m", 0.02, 0.05),
    Draw("wave_period_s", 2.0, 3.0),
    Draw("yaw_wobble_deg", 1.0, 3.0),
    Draw("cross_track_m", 0.04, 0.15),
    Draw("ripple_wavelength_m", 0.22, 0.45),
    Draw("ripple_amplitude_m", 0.004, 0.012),
    Draw("ripple_bearing_deg", 0.0, 180.0),
    Draw("ripple_bend_deg", 6.0, 20.0),
    Draw("ripple2_wavelength_m", 0.5, 1.2),
    Draw("ripple2_amplitude_m", 0.002, 0.006),
    Draw("ripple2_bearing_deg", 0.0, 180.0),
)
"""The drawn fields, in drawing order (append new ones at the end: earlier draws stay)."""


SENSOR_DAY: tuple[Draw, ...] = (
    Draw("rtk_noise_m", 0.01, 0.02),
    Draw("rtk_bias_sigma_m", 0.005, 0.012),
    Draw("rtk_bias_tau_s", 60.0, 300.0),
    Draw("rtk_lag_s", 0.02, 0.05),
    Draw("rtk_float_interval_s", 90.0, 300.0),
    Draw("rtk_float_duration_s", 3.0, 10.0),
    Draw("echosounder_dropout", 0.01, 0.06),
    Draw("echosounder_false_rate", 0.002, 0.01),
)
"""Sensor errors of the receivers and echosounders a boat may carry (child stream 2)."""

MIN_DEPTH_M = 0.5
"""Shallowest bed under the lanes a wide day allows (m): the sonar head rides 0.2 m under
the surface, and a crew keeps a few decimetres of water under it."""
OCULUS_RATES_HZ = (2.0, 5.0, 10.0, 15.0)
"""The M1200d's ping rates a survey uses (lowest, low, normal, high)."""
_HEAD_BELOW_SURFACE_M = 0.2  # the default mount: 0.3 m under an antenna 0.1 m above water
_LONGEST_RANGE_M = 20.0
_SURVEY_MARGIN_S = 600.0  # how long a tide can fall while a wide survey runs (s)

_WIDE_RANGES: dict[str, list[Any]] = {
    "seabed_type": list(SEABED_TYPES),
    "slope": [0.0, 0.10, "uniform magnitude, bearing 0-360 deg, limited by MIN_DEPTH_M"],
    "undulation_amplitude_m": [0.02, 0.2, "half the days; at most wavelength / 160"],
    "undulation_wavelength_m": [10.0, 40.0, "uniform"],
    "tide_rate_m_per_h": [-0.3, 0.3, "uniform"],
    "water_depth_m": [0.8, 6.0, "uniform"],
    "tilt_deg": [10.0, 30.0, "uniform, steepened in deep water"],
    "range_m": [3.0, 20.0, "uniform in [1.2 b, 4 b], b = h / sin(tilt)"],
    "speed_mps": [0.3, 1.2, "uniform"],
    "ping_rate_hz": list(OCULUS_RATES_HZ),
    "echosounder": [0.5, "odds"],
    "gnss_kind": ["rtk", 1.0 / 3.0, "odds"],
}


def draw_wide(s: Scenario, rng: np.random.Generator) -> tuple[dict[str, Any], dict[str, Any]]:
    """The wide day's raw draws (every value, in a fixed order) and the scenario fields
    they give (module doc), the pinned fields (``s.explicit``) left out and the derived
    fields computed from the values the survey will have."""
    raw: dict[str, Any] = {
        "seabed_type": SEABED_TYPES[int(rng.integers(len(SEABED_TYPES)))],
        "slope": float(rng.uniform(0.0, 0.10)),
        "slope_toward_deg": float(rng.uniform(0.0, 360.0)),
        "undulating": bool(rng.random() < 0.5),
        "undulation_wavelength_m": float(rng.uniform(10.0, 40.0)),
        "undulation_fraction": float(rng.random()),
        "undulation_bearing_deg": float(rng.uniform(0.0, 180.0)),
        "tide_rate_m_per_h": float(rng.uniform(-0.3, 0.3)),
        "water_depth_m": float(rng.uniform(0.8, 6.0)),
        "tilt_deg": float(rng.uniform(10.0, 30.0)),
        "range_fraction": float(rng.random()),
        "speed_mps": float(rng.uniform(0.3, 1.2)),
        "ping_rate_hz": OCULUS_RATES_HZ[int(rng.integers(len(OCULUS_RATES_HZ)))],
        "echosounder": bool(rng.random() < 0.5),
        "echosounder_x_m": float(rng.uniform(-0.5, 0.5)),
        "echosounder_y_m": float(rng.uniform(-0.3, 0.3)),
        "echosounder_z_m": float(rng.uniform(0.2, 0.4)),
        "echosounder_rate_hz": float(rng.uniform(5.0, 10.0)),
        "rtk": bool(rng.random() < 1.0 / 3.0),
        "rtk_rate_hz": (5.0, 10.0)[int(rng.integers(2))],
    }
    pinned = set(s.explicit)
    out: dict[str, Any] = {}

    def take(name: str, value: Any) -> Any:
        """The field's value on the day: drawn, or the caller's."""
        if name in pinned:
            return getattr(s, name)
        out[name] = value
        return value

    take("seabed_type", raw["seabed_type"])
    depth = take("water_depth_m", raw["water_depth_m"])
    altitude = max(depth - _HEAD_BELOW_SURFACE_M, 0.3)
    steepest = math.degrees(math.asin(min(1.0, 1.2 * altitude / _LONGEST_RANGE_M)))
    tilt = take("tilt_deg", max(raw["tilt_deg"], steepest))
    boresight = altitude / math.sin(math.radians(tilt))  # where the boresight meets the bed
    low = min(max(3.0, 1.2 * boresight), _LONGEST_RANGE_M)
    high = min(max(low + 2.0, 4.0 * boresight), _LONGEST_RANGE_M)
    reach = take("range_m", low + raw["range_fraction"] * (high - low))
    take("range_resolution_m", range_resolution_for(reach))
    speed = take("speed_mps", raw["speed_mps"])
    take("ping_rate_hz", raw["ping_rate_hz"])
    swath = ground_swath_m(reach, altitude, tilt, s.fan_deg, s.vertical_aperture_deg)
    spacing = take(
        "lane_spacing_m",
        lane_spacing_for(reach, altitude, tilt, s.fan_deg, s.vertical_aperture_deg),
    )
    length = take("lane_length_m", float(round(min(max(16.0, 2 * swath, 50.0 * speed), 60.0))))
    tide = take("tide_rate_mps", raw["tide_rate_m_per_h"] / 3600.0)
    wavelength = raw["undulation_wavelength_m"]
    amplitude = 0.0
    if raw["undulating"]:
        top = min(0.2, wavelength / 160.0)
        amplitude = 0.02 + raw["undulation_fraction"] * (top - 0.02)
    amplitude = take("undulation_amplitude_m", amplitude)
    take("undulation_wavelength_m", wavelength)
    take("undulation_bearing_deg", raw["undulation_bearing_deg"])

    # The slope, limited so the lanes keep MIN_DEPTH_M of water (the tide falling for
    # _SURVEY_MARGIN_S and the undulation's troughs counted against it).
    toward = math.radians(raw["slope_toward_deg"])
    lanes = math.radians(s.lane_bearing_deg)
    half_along = length / 2 + s.run_in_m
    half_across = (s.n_lanes - 1) / 2 * spacing + min(s.turn_radius_m, spacing / 2)
    extent = half_along * abs(math.cos(toward - lanes)) + half_across * abs(
        math.sin(toward - lanes)
    )
    spare = depth - MIN_DEPTH_M - amplitude - max(0.0, -tide) * _SURVEY_MARGIN_S
    slope = min(raw["slope"], max(spare, 0.0) / max(extent, 1e-6))
    # Depth increases along ``toward``: d depth / d east = slope sin, / d north = slope cos.
    take("seabed_slope_east", slope * math.sin(toward))
    take("seabed_slope_north", slope * math.cos(toward))

    echo = take("echosounder", raw["echosounder"])
    if echo:
        for name in (
            "echosounder_x_m",
            "echosounder_y_m",
            "echosounder_z_m",
            "echosounder_rate_hz",
        ):
            take(name, raw[name])
    if take("gnss_kind", "rtk" if raw["rtk"] else "m8n") == "rtk":
        take("gps_rate_hz", raw["rtk_rate_hz"])
    return raw, out


def draw_receiver(s: Scenario, rng: np.random.Generator) -> tuple[dict[str, Any], dict[str, Any]]:
    """How the wide day's sonar sends its pings (child 3, module doc): its raw draws and
    the scenario fields they give, the pinned ones left out."""
    raw = {
        "ping_layout": 1 if rng.random() < 1.0 / 3.0 else 2,
        "sample_bits": 16 if rng.random() < 1.0 / 3.0 else 8,
        "gain_rows": bool(rng.random() >= 1.0 / 3.0),
    }
    return raw, {k: v for k, v in raw.items() if k not in s.explicit}


def draw_field_day(s: Scenario, rng: np.random.Generator) -> tuple[Scenario, dict[str, Any]]:
    """The scenario of the day and the ``field_day`` record of truth.json: ``randomised``,
    ``explicit`` (the fields the caller pinned), ``drawn`` (each drawn field's value as
    used) and ``ranges`` ([low, high, "signed" | "uniform"] per field); a wide day adds
    ``wide`` (``draws``: every raw draw of ``draw_wide``, ``ranges``)."""
    values = {d.field: d.sample(rng) for d in FIELD_DAY}
    pinned = set(s.explicit)
    applied: dict[str, Any] = {k: v for k, v in values.items() if s.randomise and k not in pinned}
    wide_raw: dict[str, Any] | None = None
    if s.wide and s.randomise:
        wide_raw, wide_fields = draw_wide(s, child_rng(rng, 1))
        applied.update(wide_fields)
        receiver_raw, receiver_fields = draw_receiver(s, child_rng(rng, 3))
        wide_raw.update(receiver_raw)
        applied.update(receiver_fields)
    sensor_rng = child_rng(rng, 2)
    sensor = {d.field: d.sample(sensor_rng) for d in SENSOR_DAY}
    day = dataclasses.replace(s, **applied)
    extra = []
    if s.randomise:
        for d in SENSOR_DAY:
            used = (d.field.startswith("rtk_") and day.gnss_kind == "rtk") or (
                d.field.startswith("echosounder_") and day.echosounder
            )
            if used and d.field not in pinned:
                applied[d.field] = sensor[d.field]
                extra.append(d)
        day = dataclasses.replace(s, **applied)
    tables = (*FIELD_DAY, *extra)
    record: dict[str, Any] = {
        "randomised": s.randomise,
        "explicit": sorted(pinned),
        "drawn": {
            **{d.field: getattr(day, d.field) for d in tables if d.field in applied},
            **{k: getattr(day, k) for k in applied if k not in {d.field for d in tables}},
        },
        "ranges": {d.field: [d.low, d.high, "signed" if d.signed else "uniform"] for d in tables},
    }
    if wide_raw is not None:
        record["wide"] = {"draws": wide_raw, "ranges": _WIDE_RANGES}
    return day, record
