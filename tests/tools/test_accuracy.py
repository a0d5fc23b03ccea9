"""The accuracy matrix's machinery on one tiny survey in one mode: the files, their keys,
a failing survey skipped in one line, a finished survey resumed."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

from tools.accuracy import MODES, SURVEYS, Survey, main, run_matrix, select
from tools.sim.scenarios import Scenario


def test_the_table_is_a_matrix_of_existing_scenarios_and_fields() -> None:
    from tools.sim.scenarios import SCENARIOS

    assert len(SURVEYS) >= 20
    assert len({row.name for row in SURVEYS}) == len(SURVEYS)
    assert len(select(quick=True, names=None)) == 4
    fields = set(Scenario.__dataclass_fields__)
    for row in SURVEYS:
        assert row.scenario in SCENARIOS
        assert set(row.overrides) <= fields, row.name


def test_one_tiny_survey_in_one_mode(tmp_path: Path) -> None:
    tiny = Survey("quadrats", 1, {"max_pings": 60, "n_beams": 128})
    broken = Survey("quadrats", 1, {"no_such_field": 1.0})
    lines: list[str] = []
    run_matrix([tiny, broken], ["gps-only"], tmp_path, log=lines.append)
    matrix = json.loads((tmp_path / "matrix.json").read_text())
    assert matrix["modes"] == ["gps-only"]
    scored, skipped = matrix["surveys"]
    assert skipped["name"] == broken.name and "no_such_field" in skipped["error"]
    assert sum(broken.name in line and "skipped" in line for line in lines) == 1
    numbers = scored["modes"]["gps-only"]
    for key in (
        "lanes_rms_m", "lanes_median_m", "lanes_p90_m", "spacing_rmse_m", "array_offset_max_m",
        "rpe_10s_m", "rpe_10s_deg", "ate_m", "frames_read", "frames_mapped",
        "seconds_per_frame",
    ):  # fmt: skip
        assert key in numbers
    assert numbers["frames_read"] == 60 and numbers["frames_mapped"] > 0
    assert math.isfinite(numbers["ate_m"]) and numbers["seconds_per_frame"] > 0
    assert matrix["summary"]["ate_m"]["gps-only"]["surveys"] == 1
    report = json.loads((tmp_path / "surveys" / tiny.name / "gps-only" / "report.json").read_text())
    assert "lanes" in report["accuracy"] and "rpe_10s_m" in report["accuracy"]["trajectory"]
    assert not (tmp_path / "surveys" / tiny.name / "sim" / "sonar.oculus").exists()
    text = (tmp_path / "matrix.md").read_text()
    assert "## Absolute trajectory error, RMS (m)" in text and tiny.name in text
    assert f"skipped {broken.name}" in text
    # Resumed: the finished survey is taken as it was, not simulated again.
    shutil.rmtree(tmp_path / "surveys" / tiny.name / "sim")
    again = run_matrix([tiny], ["gps-only"], tmp_path, log=lines.append, resume=True)
    resumed = again["surveys"][0]["modes"]["gps-only"]
    assert resumed["ate_m"] == numbers["ate_m"] and resumed["frames_read"] == 60
    assert not (tmp_path / "surveys" / tiny.name / "sim").exists()


def test_a_bad_survey_name_is_one_line(tmp_path: Path, capsys) -> None:
    try:
        main(["--out", str(tmp_path), "--surveys", "nowhere-s1"])
    except SystemExit as exc:
        assert "unknown survey nowhere-s1" in str(exc)
    else:
        raise AssertionError("no error")
    assert set(MODES) == {"single-stage", "two-stage", "fmt-only", "gps-only", "streaming"}
