"""End to end: a simulated survey replayed into a georeferenced mosaic whose quadrats lie
where the truth puts them."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import rasterio

from mapping.metrics import locate_quadrats, quadrat_spacing_error
from seamap.cli import main
from tools.evaluate import quadrats_of
from tools.sim import simulate


@pytest.fixture(scope="module")
def survey(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("survey")
    simulate("quadrats", 2, folder, max_pings=220, n_beams=256)
    return folder


@pytest.fixture(scope="module")
def result(survey: Path) -> Path:
    out = survey / "result"
    status = main(
        [
            "replay",
            "--sonar", str(survey / "sonar.oculus"),
            "--nav", str(survey / "nav.tlog"),
            "--config", str(survey / "site.toml"),
            "--out", str(out),
            "--truth", str(survey / "truth.json"),
        ]
    )  # fmt: skip
    assert status == 0
    return out


def test_result_folder_follows_the_contract(survey: Path, result: Path) -> None:
    truth = json.loads((survey / "truth.json").read_text())
    with rasterio.open(result / "mosaic.tif") as mosaic:
        assert mosaic.count == 1 and mosaic.dtypes[0] == "uint8"
        assert mosaic.crs.to_epsg() == truth["site"]["epsg"]
        assert mosaic.nodata == 0
        t = mosaic.transform
        assert t.b == 0 and t.d == 0 and t.a == -t.e > 0  # north-up, square pixels
        image = mosaic.read(1)
    assert (image > 0).mean() > 0.3
    assert (result / "mosaic.png").stat().st_size > 1000
    with (result / "trajectory.csv").open() as stream:
        rows = list(csv.DictReader(stream))
    assert list(rows[0]) == ["time", "lat", "lon", "east", "north", "heading_deg"]
    report = json.loads((result / "report.json").read_text())
    assert len(rows) == report["frames"]["mapped"] > 200
    first = truth["pings"][0]
    assert float(rows[0]["time"]) == pytest.approx(first["time"], abs=1e-6)
    assert 0 <= float(rows[0]["heading_deg"]) < 360
    for key in ("read", "mapped", "rejected"):
        assert key in report["frames"]
    for stage in ("preprocess", "registration", "ekf", "optimisation", "blending", "total"):
        assert stage in report["timings_s"]


def _rigid_fit(true: np.ndarray, found: np.ndarray) -> tuple[float, np.ndarray]:
    """Rotation (radians) and residuals (n, 2) of the 2-D rigid transform that best takes
    the true points onto the found ones (least squares, Kabsch)."""
    a, b = true - true.mean(axis=0), found - found.mean(axis=0)
    angle = float(np.arctan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a * b)))
    c, s = np.cos(angle), np.sin(angle)
    rotated = a @ np.array([[c, s], [-s, c]])
    return angle, b - rotated


def test_quadrats_lie_where_the_truth_puts_them(survey: Path, result: Path) -> None:
    truth = json.loads((survey / "truth.json").read_text())
    quadrats = quadrats_of(truth)
    with rasterio.open(result / "mosaic.tif") as mosaic:
        image = mosaic.read(1)
        t = mosaic.transform
    found = locate_quadrats(image / 255.0, image > 0, t.c, t.f, t.a, quadrats)
    located = [(q, f) for q, f in zip(quadrats, found, strict=True) if f is not None]
    assert len(located) >= 4
    # Georeferenced by a GPS with a metre of bias: within a few metres.
    offsets = np.array([(f[0] - q.east, f[1] - q.north) for q, f in located])
    assert np.all(np.linalg.norm(offsets, axis=1) < 3.0)
    # A 44-second lane cannot tell a magnetic compass's misalignment from a heading
    # better than a few degrees (the GNSS track wanders by a metre over it): the map may
    # turn as a whole, a few degrees, but its geometry holds: the quadrats sit where one
    # rigid transform of the truth puts them, to a few centimetres.
    angle, residuals = _rigid_fit(
        np.array([(q.east, q.north) for q, _ in located]), np.array([f[:2] for _, f in located])
    )
    assert abs(np.degrees(angle)) < 10.0
    assert float(np.sqrt(np.mean(np.sum(residuals**2, axis=1)))) < 0.05
    spacing = quadrat_spacing_error(quadrats, found)
    assert spacing["rmse"] < 0.05


def test_bad_inputs_end_in_one_line(
    tmp_path: Path, survey: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    junk = tmp_path / "junk.tlog"
    junk.write_text("not a log\n")
    args = [
        "replay",
        "--sonar",
        str(survey / "sonar.oculus"),
        "--nav",
        str(junk),
        "--out",
        str(tmp_path / "o"),
    ]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "junk.tlog" in err[0]
    args = [
        "replay",
        "--sonar",
        str(junk),
        "--nav",
        str(survey / "nav.tlog"),
        "--out",
        str(tmp_path / "o"),
    ]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "junk.tlog" in err[0]
