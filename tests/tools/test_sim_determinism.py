"""The same scenario and seed give byte-identical files; another seed gives other files."""

from __future__ import annotations

from pathlib import Path

import pytest

from drivers.errors import SeamapError
from tools.sim import SCENARIOS, parse_overrides, simulate

FILES = (
    "sonar.oculus",
    "nav.tlog",
    "truth.json",
    "seabed.tif",
    "seabed_height.tif",
    "site.toml",
)
SMALL = {"max_pings": 20, "n_beams": 128}


def test_scenarios_are_the_documented_ones():
    assert set(SCENARIOS) == {
        "quadrats", "farm", "quadrats-current", "hectare", "shore", "mud", "deep", "rtk", "field",
    }  # fmt: skip


def test_same_seed_same_bytes_other_seed_other_bytes(tmp_path: Path):
    a = simulate("quadrats", 7, tmp_path / "a", **SMALL)
    b = simulate("quadrats", 7, tmp_path / "b", **SMALL)
    c = simulate("quadrats", 8, tmp_path / "c", **SMALL)
    assert a.ping_count == b.ping_count == 20
    assert "20 pings" in a.describe() and "RAW_IMU" in a.describe()
    for name in FILES:
        assert (a.out / name).read_bytes() == (b.out / name).read_bytes(), name
    for name in ("sonar.oculus", "nav.tlog", "truth.json", "seabed.tif"):
        assert (a.out / name).read_bytes() != (c.out / name).read_bytes(), name


def test_cutting_a_survey_short_keeps_the_site(tmp_path: Path):
    """The seabed of a site and seed does not depend on how much of the survey is run."""
    a = simulate("quadrats", 7, tmp_path / "a", max_pings=5, n_beams=32)
    b = simulate("quadrats", 7, tmp_path / "b", duration_s=3.0, n_beams=32)
    assert (a.out / "seabed.tif").read_bytes() == (b.out / "seabed.tif").read_bytes()
    assert b.duration_s == pytest.approx(3.0)


@pytest.mark.parametrize(
    ("scenario", "overrides", "words"),
    [
        ("nowhere", {}, "unknown scenario"),
        ("quadrats", {"n_beamz": 3}, "unknown override"),
        ("quadrats", {"flavour": "inav"}, "flavour"),
        ("quadrats", {"n_beams": "many"}, "n_beams"),
    ],
)
def test_bad_input_is_a_one_line_error(tmp_path: Path, scenario, overrides, words):
    with pytest.raises(SeamapError, match=words):
        simulate(scenario, 1, tmp_path, **overrides)


def test_command_line_overrides_are_typed_by_the_scenario():
    parsed = parse_overrides(
        {"n_beams": "128", "flavour": "px4", "current_mps": "0.1", "max_pings": "none"}
    )
    assert parsed == {"n_beams": 128, "flavour": "px4", "current_mps": 0.1, "max_pings": None}
    with pytest.raises(SeamapError, match="n_beams"):
        parse_overrides({"n_beams": "lots"})
    with pytest.raises(SeamapError, match="unknown override"):
        parse_overrides({"beams": "3"})
