"""An echosounder's depths in a .tlog reach the projection: a simulated sloping shore
(the simulator's own echosounder, written as DISTANCE_SENSOR and RANGEFINDER) replayed
with its site file gives every ping an altitude from the soundings, close to the truth's;
without them (``[echosounder] use = false``) from the sonar's own first seabed return
(which keeps the configured altitude where it agrees with it), and without that too
(``[sonar] seabed_from_pings = false``) the configured altitude, level."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from daemon.config import load_config
from daemon.replay import replay
from tools.sim.survey import simulate


@pytest.fixture(scope="module")
def shore(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("shore")
    simulate("shore", 1, out, max_pings=80, n_beams=128)
    return out


def test_the_soundings_in_the_tlog_set_each_pings_altitude(shore: Path, tmp_path: Path) -> None:
    config = load_config(shore / "site.toml")
    assert config.echosounder.use
    report = replay(
        shore / "sonar.oculus", shore / "nav.tlog", None, "gps-only", tmp_path / "r", config=config
    )
    bottom = report["bottom"]
    assert bottom["source"] == "echosounder"
    assert bottom["soundings"] > 100
    assert bottom["pings_with_plane"] == report["frames"]["read"]
    truth = json.loads((shore / "truth.json").read_text())
    altitudes = np.array([p["altitude_m"] for p in truth["pings"]])
    # The soundings' altitudes span the truth's (the site file gives only their mean).
    assert abs(bottom["altitude_m"]["median"] - float(np.median(altitudes))) < 0.06
    assert abs(bottom["altitude_m"]["min"] - float(altitudes.min())) < 0.1
    assert abs(bottom["altitude_m"]["max"] - float(altitudes.max())) < 0.1

    # Without the echosounder, the sonar's own first return: over these 16 s the bed is
    # level to 2 % at the site's altitude, which the soundings confirm and which is kept;
    # told 0.3 m wrong, the soundings' altitudes are used instead.
    deaf = dataclasses.replace(
        config, echosounder=dataclasses.replace(config.echosounder, use=False)
    )
    own = replay(
        shore / "sonar.oculus", shore / "nav.tlog", None, "gps-only", tmp_path / "s", config=deaf
    )
    assert own["bottom"]["source"] == "configured"
    agrees = own["bottom"]["sonar_agrees"]
    assert agrees["pings"] == report["frames"]["read"]
    assert abs(agrees["median_altitude_m"] - float(np.median(altitudes))) < 0.06
    wrong = dataclasses.replace(
        deaf, sonar=dataclasses.replace(deaf.sonar, altitude_m=deaf.sonar.altitude_m + 0.3)
    )
    told = replay(
        shore / "sonar.oculus", shore / "nav.tlog", None, "gps-only", tmp_path / "w", config=wrong
    )
    assert told["bottom"]["source"] == "sonar"
    assert told["bottom"]["pings_with_plane"] == report["frames"]["read"]
    assert abs(told["bottom"]["altitude_m"]["median"] - float(np.median(altitudes))) < 0.06
    off = dataclasses.replace(
        deaf, sonar=dataclasses.replace(config.sonar, seabed_from_pings=False)
    )
    plain = replay(
        shore / "sonar.oculus", shore / "nav.tlog", None, "gps-only", tmp_path / "p", config=off
    )
    assert plain["bottom"] == {"source": "configured", "altitude_m": config.sonar.altitude_m}
    # Projected at other altitudes, the same poses draw another mosaic.
    assert (tmp_path / "r" / "mosaic.tif").read_bytes() != (
        tmp_path / "p" / "mosaic.tif"
    ).read_bytes()
