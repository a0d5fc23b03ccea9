"""The simulator's truth written as a reference trajectory CSV scores one replay as its
truth.json does: ATE, RPE, heading error and lane disagreement equal to within the
rounding of the CSV's digits; without east/north (projected from lat/lon) the same; a
reference with two rows around each ping and none at its time (interpolated) the same.

One small simulated survey (two 8 m lanes, a ping every 2 s so that each frame is its
own pass and the lanes have pairs to disagree on), replayed once gps-only, scored against
every reference by one scorer."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from daemon.replay import replay
from tools.evaluation.truth import truth_scorer
from tools.sim import simulate

COLUMNS = ("time", "lat", "lon", "east", "north", "heading_deg", "roll_deg", "pitch_deg",
           "altitude_m")  # fmt: skip
DIGITS = {"time": 6, "lat": 9, "lon": 9, "east": 4, "north": 4, "heading_deg": 4,
          "roll_deg": 4, "pitch_deg": 4, "altitude_m": 4}  # fmt: skip


def write_reference(path: Path, rows: list[dict[str, float]], columns: tuple[str, ...]) -> None:
    """Rows in the CSV with trajectory.csv's digits (and as many for the attitude)."""
    lines = [",".join(columns)]
    lines += [",".join(f"{row[c]:.{DIGITS[c]}f}" for c in columns) for row in rows]
    path.write_text("\n".join(lines) + "\n")


def around_each_ping(pings: list[dict[str, Any]], offset_s: float) -> list[dict[str, float]]:
    """Two rows per ping, ``offset_s`` before and after its time, on the line through its
    pose along the pose's motion (the difference to the next ping, the last ping's to the
    one before): none at a ping's time, and the pose half-way between them is the ping's."""
    rows = []
    for k, ping in enumerate(pings):
        a, b = (pings[k], pings[k + 1]) if k + 1 < len(pings) else (pings[k - 1], pings[k])
        dt = b["time"] - a["time"]
        rate = {c: (b[c] - a[c]) / dt for c in ("lat", "lon", "east", "north")}
        turn = (b["heading_deg"] - a["heading_deg"] + 180.0) % 360.0 - 180.0
        for sign in (-1.0, 1.0):
            row = {c: ping[c] + sign * offset_s * rate[c] for c in rate}
            row["time"] = ping["time"] + sign * offset_s
            row["heading_deg"] = (ping["heading_deg"] + sign * offset_s * turn / dt) % 360.0
            row.update({c: ping[c] for c in ("roll_deg", "pitch_deg", "altitude_m")})
            rows.append(row)
    return rows


@pytest.fixture(scope="module")
def survey(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Path]]:
    """The simulated survey's folder, and its truth as each reference file."""
    root = tmp_path_factory.mktemp("reference")
    sim = root / "sim"
    simulate("quadrats", 2, sim, lane_length_m=8.0, n_lanes=2, ping_rate_hz=0.5, n_beams=64,
             range_resolution_m=0.02, seabed_resolution_m=0.04)  # fmt: skip
    pings = json.loads((sim / "truth.json").read_text())["pings"]
    assert len(pings) > 25
    references = {"json": sim / "truth.json"}
    for name, rows, columns in (
        ("csv", pings, COLUMNS),
        ("csv_lat_lon", pings, tuple(c for c in COLUMNS if c not in ("east", "north"))),
        ("csv_contract", pings, COLUMNS[:6]),
        ("csv_around", around_each_ping(pings, 0.3), COLUMNS),
    ):
        references[name] = root / f"{name}.csv"
        write_reference(references[name], rows, columns)
    return sim, references


@pytest.fixture(scope="module")
def scored(survey: tuple[Path, dict[str, Path]]) -> dict[str, dict[str, Any]]:
    """report.json's ``accuracy`` against each reference, from one gps-only replay."""
    sim, references = survey
    scorers = {name: truth_scorer(path) for name, path in references.items()}
    # Nearest row only (no interpolation): the rows around the pings are 0.3 s off.
    scorers["csv_around_nearest"] = truth_scorer(references["csv_around"], 0.35, 0.0)

    def score(*args: Any) -> dict[str, Any]:
        return {name: scorer(*args) for name, scorer in scorers.items()}

    report = replay(
        [sim / "sonar.oculus"], [sim / "nav.tlog"], sim / "site.toml", "gps-only",
        sim.parent / "out", scorer=score, workers=0,
    )  # fmt: skip
    accuracy: dict[str, dict[str, Any]] = report["accuracy"]
    return accuracy


TRAJECTORY = ("rmse", "mean", "max", "aligned_rmse", "heading_rmse_deg", "rpe_10s_m",
              "rpe_10s_deg", "rpe_10s_pairs", "frames_scored")  # fmt: skip
LANES = ("rms_m", "median_m", "p90_m", "max_m", "pairs", "points")


def numbers(accuracy: dict[str, Any]) -> dict[str, float]:
    """The trajectory's numbers and the lane disagreement over the 1 m grid (the truth's
    also counts its quadrats' centres, which a reference trajectory does not know)."""
    out = {f"trajectory.{k}": accuracy["trajectory"][k] for k in TRAJECTORY}
    out.update({f"lanes.{k}": accuracy["lanes"]["grid"][k] for k in LANES})
    return out


def assert_same(got: dict[str, Any], want: dict[str, Any]) -> None:
    """Equal to within the CSV's rounding: 0.1 mm in position, 1e-4 degrees in heading."""
    a, b = numbers(got), numbers(want)
    for key in b:
        assert math.isfinite(b[key]), key
        tolerance = 1e-3 if key.endswith("_deg") else 2e-4
        assert a[key] == pytest.approx(b[key], abs=tolerance), (key, a[key], b[key])


def test_the_truth_as_a_csv_scores_as_the_truth_json(scored: dict[str, dict[str, Any]]) -> None:
    want = scored["json"]
    assert want["lanes"]["pairs"] > 100 and want["trajectory"]["rmse"] > 0.05
    assert_same(scored["csv"], want)
    reference = scored["csv"]["reference"]
    assert reference["kind"] == "reference trajectory"
    assert reference["frames_matched"] == reference["frames"] == want["reference"]["frames"]
    assert "quadrat_spacing" in want and "quadrat_spacing" not in scored["csv"]
    assert "seabed" in scored["csv"]["unavailable"]


def test_without_east_north_the_csv_scores_the_same(scored: dict[str, dict[str, Any]]) -> None:
    assert_same(scored["csv_lat_lon"], scored["json"])


def test_a_faster_reference_is_interpolated_to_the_frames(
    scored: dict[str, dict[str, Any]],
) -> None:
    around = scored["csv_around"]
    assert around["reference"]["frames_interpolated"] == around["reference"]["frames"]
    assert_same(around, scored["json"])
    # The nearest row alone is 0.3 s off (at the boat's 0.4 m/s, 0.12 m along the track):
    # the ATE moves by some 50 times the interpolated reference's tolerance.
    nearest = scored["csv_around_nearest"]
    assert nearest["reference"]["frames_nearest"] == nearest["reference"]["frames"]
    assert abs(nearest["trajectory"]["rmse"] - scored["json"]["trajectory"]["rmse"]) > 0.005


def test_the_contract_columns_alone_score_the_trajectory_alike(
    scored: dict[str, dict[str, Any]],
) -> None:
    # Without roll, pitch and altitude the heads are level at the replay's altitude:
    # the trajectory's numbers are the same, the lanes' nearly so (the fans' edges move).
    contract, want = numbers(scored["csv_contract"]), numbers(scored["json"])
    for key in (k for k in want if k.startswith("trajectory.")):
        assert contract[key] == pytest.approx(want[key], abs=1e-3), key
    assert contract["lanes.rms_m"] == pytest.approx(want["lanes.rms_m"], rel=0.1)
    assert "level" in scored["csv_contract"]["reference"]["assumed"]
    print({k: (contract[k], want[k]) for k in want if k.startswith("lanes.")})


def test_seamap_replay_takes_the_csv_and_says_what_it_cannot_score(
    survey: tuple[Path, dict[str, Path]], scored: dict[str, dict[str, Any]], tmp_path: Path
) -> None:
    sim, reference = survey[0], survey[1]["csv_contract"]
    done = subprocess.run(
        [sys.executable, "-m", "seamap", "replay", "--sonar", str(sim / "sonar.oculus"),
         "--nav", str(sim / "nav.tlog"), "--config", str(sim / "site.toml"),
         "--mode", "gps-only", "--workers", "0", "--truth", str(reference),
         "--out", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    ate = report["accuracy"]["trajectory"]["rmse"]
    assert ate == pytest.approx(scored["csv_contract"]["trajectory"]["rmse"], abs=1e-9)
    assert f"accuracy: ATE {ate:.3f} m" in done.stdout
    assert "not available with a reference trajectory" in done.stdout


def test_seamap_evaluate_scores_every_method_against_the_csv(
    survey: tuple[Path, dict[str, Path]], scored: dict[str, dict[str, Any]], tmp_path: Path
) -> None:
    sim, reference = survey[0], survey[1]["csv_contract"]
    out = tmp_path / "report"
    done = subprocess.run(
        [sys.executable, "-m", "seamap", "evaluate", str(sim), "--truth", str(reference),
         "--every", "30", "--out", str(out)],
        capture_output=True, text=True, timeout=1200,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    table_ii = json.loads((out / "tables.json").read_text())["table_ii"]
    assert table_ii["reference"]["frames_matched"] == table_ii["reference"]["frames"]
    rows = table_ii["truth"]
    assert {"gps-only", "single-stage", "fmt-pairwise", "orb"} <= set(rows)
    assert all(math.isfinite(row["ate_m"]) for row in rows.values())
    # Its gps-only replay is the one scored above against truth.json.
    want = scored["json"]["trajectory"]
    assert rows["gps-only"]["ate_m"] == pytest.approx(want["rmse"], abs=2e-4)
    assert rows["gps-only"]["rpe_10s_m"] == pytest.approx(want["rpe_10s_m"], abs=2e-4)
    report = (out / "report.md").read_text()
    assert "Against the reference trajectory" in report
    assert "not available with a reference trajectory" in report
