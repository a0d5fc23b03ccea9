"""Site configuration: the contract's keys and defaults, and errors that name the key."""

from __future__ import annotations

from pathlib import Path

import pytest

from seamap.config import SiteConfig, dump_config, load_config
from seamap.errors import SeamapError

CONTRACT_EXAMPLE = """
[daemon]
vehicle = "boat1"              # zenoh vehicle id
state_dir = "/var/lib/seamap"  # surveys are kept under state_dir/surveys/{survey}/
survey_autostart = false       # true: open a survey as soon as the daemon runs

[sonar]
mount_x_m = -0.45     # body-frame offset of the sonar from the GPS antenna, forward
mount_y_m = 0.0       # starboard
mount_z_m = 0.3       # down
mount_yaw_deg = 0.0   # sonar boresight relative to the bow, clockwise
tilt_deg = 15.0       # downward tilt of the boresight
altitude_m = 1.0      # sonar height above the seabed, when known (ground-range correction)
address = "auto"      # "auto": take the first sonar heard on the status port
tcp_port = 52100
status_port = 52102

[mavlink]
url = "udpin:0.0.0.0:14550"    # pymavlink form, or a serial device such as "/dev/ttyACM0"
baud = 115200

[zenoh]
mode = "peer"
listen = ["tcp/0.0.0.0:7447"]
connect = []
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "site.toml"
    path.write_text(text)
    return path


def test_contract_example_equals_the_defaults(tmp_path: Path) -> None:
    assert load_config(write(tmp_path, CONTRACT_EXAMPLE)) == SiteConfig()


def test_a_file_may_set_any_subset(tmp_path: Path) -> None:
    config = load_config(write(tmp_path, "[sonar]\ntilt_deg = 20\naltitude_m = 1.5\n"))
    assert config.sonar.tilt_deg == 20.0
    assert isinstance(config.sonar.tilt_deg, float)
    assert config.sonar.altitude_m == 1.5
    assert config.sonar.mount_x_m == -0.45
    assert config.mavlink == SiteConfig().mavlink


def test_unknown_key_is_an_error_naming_it(tmp_path: Path) -> None:
    with pytest.raises(SeamapError, match=r"unknown key 'tilt' in \[sonar\]"):
        load_config(write(tmp_path, "[sonar]\ntilt = 20\n"))


def test_unknown_table_is_an_error_naming_it(tmp_path: Path) -> None:
    with pytest.raises(SeamapError, match=r"unknown table \[sonra\]"):
        load_config(write(tmp_path, "[sonra]\ntilt_deg = 20\n"))


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ('[sonar]\ntcp_port = "52100"\n', r"\[sonar\] tcp_port must be an integer"),
        ("[sonar]\ntilt_deg = true\n", r"\[sonar\] tilt_deg must be a number"),
        ("[daemon]\nsurvey_autostart = 1\n", r"survey_autostart must be true or false"),
        ('[zenoh]\nlisten = "tcp/0.0.0.0:7447"\n', r"\[zenoh\] listen must be a list"),
        ('[mavlink]\nheading_source = "gyro"\n', r"heading_source = 'gyro' is not one of"),
        ('[daemon]\nvehicle = "a/b"\n', r"vehicle 'a/b' must be a non-empty id without '/'"),
        ("[sonar]\ntilt_deg = nan\n", r"tilt_deg must be finite"),
    ],
)
def test_wrong_values_are_errors_naming_the_key(tmp_path: Path, text: str, fragment: str) -> None:
    with pytest.raises(SeamapError, match=fragment):
        load_config(write(tmp_path, text))


def test_malformed_and_missing_files_are_one_line_errors(tmp_path: Path) -> None:
    with pytest.raises(SeamapError, match="not valid TOML"):
        load_config(write(tmp_path, "[sonar\n"))
    with pytest.raises(SeamapError, match="no such config file"):
        load_config(tmp_path / "missing.toml")


def test_dump_round_trips(tmp_path: Path) -> None:
    config = load_config(
        write(tmp_path, '[sonar]\ntilt_deg = 12.5\n[zenoh]\nconnect = ["tcp/127.0.0.1:7447"]\n')
    )
    assert load_config(write(tmp_path, dump_config(config))) == config
