"""Each seed is a new field day: drawn within realistic ranges, recorded in truth.json,
an explicit override always wins, and ``randomise=False`` keeps the defaults."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from tools.sim import SCENARIOS, resolve_scenario, simulate
from tools.sim.fieldday import FIELD_DAY, draw_field_day
from tools.sim.survey import component_rng, prepare_survey

TINY = {"max_pings": 3, "n_beams": 16, "range_resolution_m": 0.1}


def day(name: str, seed: int, **overrides: object):
    s = resolve_scenario(name, **overrides)
    return draw_field_day(s, component_rng(seed, "field_day"))


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_two_seeds_are_two_field_days_within_the_ranges(name: str):
    a, record_a = day(name, 1)
    b, _ = day(name, 2)
    pinned = set(SCENARIOS[name].explicit)  # a named scenario may pin a field (rtk's compass)
    drawn = {d.field for d in FIELD_DAY} - pinned
    assert record_a["randomised"] and drawn <= set(record_a["drawn"])
    for d in FIELD_DAY:
        if d.field in pinned:
            continue
        va, vb = getattr(a, d.field), getattr(b, d.field)
        assert va != vb, d.field
        for v in (va, vb):
            magnitude = abs(v) if d.signed else v
            assert d.low <= magnitude <= d.high, (d.field, v)
        assert record_a["drawn"][d.field] == va
        assert record_a["ranges"][d.field][:2] == [d.low, d.high]
    # Same seed, same day.
    assert day(name, 1)[0] == a


def test_an_explicit_override_wins_and_leaves_the_other_draws_alone():
    free, _ = day("quadrats", 5)
    pinned, record = day("quadrats", 5, gps_lag_s=0.3, compass_bias_deg=0.0)
    assert pinned.gps_lag_s == 0.3 and pinned.compass_bias_deg == 0.0
    assert "gps_lag_s" not in record["drawn"] and "gps_lag_s" in record["explicit"]
    for d in FIELD_DAY:
        if d.field not in ("gps_lag_s", "compass_bias_deg"):
            assert getattr(pinned, d.field) == getattr(free, d.field), d.field
    # An override equal to the default still wins.
    same, _ = day("quadrats", 5, roll_deg=SCENARIOS["quadrats"].roll_deg)
    assert same.roll_deg == SCENARIOS["quadrats"].roll_deg != free.roll_deg


def test_without_randomise_the_defaults_are_used_exactly():
    s, record = day("farm", 9, randomise=False)
    base = SCENARIOS["farm"]
    assert dataclasses.replace(s, explicit=()) == dataclasses.replace(base, randomise=False)
    assert record == {**record, "randomised": False, "drawn": {}}
    # The survey is then the scenario's, whatever the seed.
    setup = prepare_survey(resolve_scenario("quadrats", randomise=False), 3)
    assert setup.scenario.gps_bias_tau_s == SCENARIOS["quadrats"].gps_bias_tau_s


def test_truth_records_the_field_day(tmp_path: Path):
    simulate("quadrats", 6, tmp_path / "a", **TINY, ripple_bend_deg=9.0)
    truth = json.loads((tmp_path / "a" / "truth.json").read_text())
    record, params = truth["field_day"], truth["parameters"]
    assert record["randomised"] is True
    assert "ripple_bend_deg" in record["explicit"] and params["ripple_bend_deg"] == 9.0
    for field, value in record["drawn"].items():
        assert params[field] == pytest.approx(value, abs=1e-6), field
    # The sections of truth.json carry the values of the day too.
    sensors = truth["sensors"]
    assert sensors["gps"]["bias_tau_s"] == pytest.approx(
        record["drawn"]["gps_bias_tau_s"], abs=1e-6
    )
    assert sensors["gps"]["lag_s"] == pytest.approx(record["drawn"]["gps_lag_s"], abs=1e-6)
    assert sensors["compass"]["bias_deg"] == pytest.approx(
        record["drawn"]["compass_bias_deg"], abs=1e-6
    )
    gyro = [record["drawn"][f"gyro_bias_{axis}_dps"] for axis in "xyz"]
    np.testing.assert_allclose(sensors["imu"]["gyro_bias_dps"], gyro, atol=1e-6)
    assert truth["sonar"]["latency_s"] == pytest.approx(
        record["drawn"]["sonar_latency_s"], abs=1e-6
    )
    assert truth["vehicle"]["motion"]["roll_deg"] == pytest.approx(
        record["drawn"]["roll_deg"], abs=1e-6
    )
    train = truth["features"]["ripples"]["trains"][0]
    assert train["wavelength_m"] == pytest.approx(record["drawn"]["ripple_wavelength_m"], abs=1e-6)
    assert train["bend_deg"] == pytest.approx(9.0, abs=1e-6)
