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
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from tools.sim.scenarios import Scenario


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


def draw_field_day(s: Scenario, rng: np.random.Generator) -> tuple[Scenario, dict[str, Any]]:
    """The scenario of the day and the ``field_day`` record of truth.json: ``randomised``,
    ``explicit`` (the fields the caller pinned), ``drawn`` (each drawn field's value as
    used) and ``ranges`` ([low, high, "signed" | "uniform"] per field)."""
    values = {d.field: d.sample(rng) for d in FIELD_DAY}
    pinned = set(s.explicit)
    applied: dict[str, Any] = {k: v for k, v in values.items() if s.randomise and k not in pinned}
    day = dataclasses.replace(s, **applied)
    record = {
        "randomised": s.randomise,
        "explicit": sorted(pinned),
        "drawn": {d.field: getattr(day, d.field) for d in FIELD_DAY if d.field in applied},
        "ranges": {
            d.field: [d.low, d.high, "signed" if d.signed else "uniform"] for d in FIELD_DAY
        },
    }
    return day, record
