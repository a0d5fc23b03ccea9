"""Site configuration: the contract's keys and defaults, and errors that name the key."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from daemon.config import (
    SiteConfig,
    checked_keys,
    config_from_dict,
    dump_config,
    key_rule,
    load_config,
)
from drivers.errors import SeamapError
from tests.fuzzing import fuzz

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
        (
            '[daemon]\nvehicle = "a/b"\n',
            r"vehicle = 'a/b' is not a vehicle id \(an id holds no '/'",
        ),
        # The shore and the security sets refuse a space in an id: so does the config.
        ('[daemon]\nvehicle = "boat 1"\n', r"vehicle = 'boat 1' is not a vehicle id"),
        ("[mapping]\nmosaic_res_m = -0.02\n", r"\[mapping\] mosaic_res_m = -0.02 is outside"),
        ("[daemon]\nworkers = -2\n", r"\[daemon\] workers = -2 is outside -1\.\.256"),
        ("[live]\ncandidates = 0\n", r"\[live\] candidates = 0 is outside 1\.\.64"),
        ("[live]\nregistration_res_m = 0\n", r"\[live\] registration_res_m = 0 is outside"),
        ("[live]\nyaw_from_gyro = 1\n", r"\[live\] yaw_from_gyro must be true or false"),
        (
            '[sonar]\naddress = "sonar.local"\n',
            r"address = 'sonar.local' must be \"auto\" or an IPv4",
        ),
        (
            '[zenoh]\nlisten = ["0.0.0.0:7447"]\n',
            r"listen = '0.0.0.0:7447' is not a zenoh endpoint \(not PROTOCOL/ADDRESS",
        ),
        ("[sonar]\ntilt_deg = nan\n", r"tilt_deg must be finite"),
    ],
)
def test_wrong_values_are_errors_naming_the_key(tmp_path: Path, text: str, fragment: str) -> None:
    with pytest.raises(SeamapError, match=fragment):
        load_config(write(tmp_path, text))


@pytest.mark.parametrize("method", ["robust", "average", "hurtos", "su"])
def test_every_blending_method_loads_and_reaches_the_pipeline(tmp_path: Path, method: str) -> None:
    from daemon.replay import pipeline_params

    config = load_config(write(tmp_path, f'[mapping]\nblending = "{method}"\n'))
    assert config.mapping.blending == method
    assert pipeline_params(config).blend.method == method


def test_a_wrong_blending_method_names_the_choices(tmp_path: Path) -> None:
    expected = r"\[mapping\] blending = 'median' is not one of robust, average, hurtos, su$"
    with pytest.raises(SeamapError, match=expected):
        load_config(write(tmp_path, '[mapping]\nblending = "median"\n'))


@pytest.mark.parametrize(
    ("key", "value", "fragment"),
    [
        ("cell_m", 0.0, "cell_m = 0.0 is outside 0.05..5"),
        ("cell_m", 10, "cell_m = 10 is outside 0.05..5"),
        ("min_passes", 0, "min_passes = 0 is outside 1..1000"),
        ("min_passes", 1.5, "min_passes must be an integer"),
        ("min_range_m", -1.0, "min_range_m = -1.0 is outside 0..120"),
        ("max_range_m", 500.0, "max_range_m = 500.0 is outside 0..120"),
        ("min_grazing_deg", 95.0, "min_grazing_deg = 95.0 is outside 0..90"),
        ("pass_gap_s", 0.2, "pass_gap_s = 0.2 is outside 1..86400"),
        ("min_gap_m2", -0.5, "min_gap_m2 = -0.5 is outside 0..1e+08"),
        ("min_gap_m2", "1", "min_gap_m2 must be a number"),
    ],
)
def test_coverage_keys_are_checked_where_the_others_are(
    key: str, value: object, fragment: str
) -> None:
    expected = "^" + re.escape(f"config: [coverage] {fragment}")
    with pytest.raises(SeamapError, match=expected) as error:
        config_from_dict({"coverage": {key: value}})
    assert "\n" not in str(error.value)


def test_coverage_ranges_must_make_a_band() -> None:
    with pytest.raises(SeamapError, match=r"min_range_m = 4 is not below max_range_m = 3"):
        config_from_dict({"coverage": {"min_range_m": 4.0, "max_range_m": 3.0}})
    band = config_from_dict({"coverage": {"min_range_m": 1.0, "max_range_m": 3.0}}).coverage
    assert (band.min_range_m, band.max_range_m) == (1.0, 3.0)
    # 0 is the mapper's own band: any near limit goes with it.
    assert config_from_dict({"coverage": {"min_range_m": 4.0}}).coverage.max_range_m == 0.0


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


KEYS = sorted(checked_keys())


def test_every_key_has_its_check() -> None:
    # checked_keys raises for a key without one; every table's keys are walked.
    kinds = checked_keys()
    assert len(kinds) == sum(len(vars(table)) for table in vars(SiteConfig()).values())
    assert {kinds[k] for k in kinds} <= {"choice", "range", "text", "free", "bool"}


def _bad_value(table: str, key: str, data: st.DataObject) -> object:
    kind = checked_keys()[(table, key)]
    rule = key_rule(table, key)
    default = getattr(getattr(SiteConfig(), table), key)
    if kind == "choice":
        if isinstance(default, str):
            return data.draw(st.text(max_size=12).filter(lambda v: v not in rule))
        return data.draw(st.integers(-(10**6), 10**6).filter(lambda v: v not in rule))
    if kind == "range":
        low, high = rule
        span = max(abs(low), abs(high), 1.0)
        below = st.floats(-1e12 * span, low, exclude_max=True, allow_nan=False)
        above = st.floats(high, 1e12 * span, exclude_min=True, allow_nan=False)
        value = data.draw(st.one_of(below, above))
        if isinstance(default, int):
            value = math.floor(value) if value < low else math.ceil(value)
            if low <= value <= high:  # rounding brought it back in
                value = int(high) + 1
        return value
    assert kind == "text"
    wrong = {
        ("daemon", "vehicle"): st.sampled_from(["", "a/b", "boat*", " boat", "x#"]),
        ("daemon", "state_dir"): st.sampled_from(["", "   "]),
        ("sonar", "address"): st.sampled_from(["sonar", "256.1.1.1", "10.0.0", ""]),
        ("mavlink", "url"): st.sampled_from(["", " "]),
        ("zenoh", "listen"): st.sampled_from([["127.0.0.1:7447"], ["tcp/127.0.0.1"], ["tcp/:1"]]),
        ("zenoh", "connect"): st.sampled_from([["tcp/h:99999"], ["tcp"], ["/x:1"]]),
    }
    return data.draw(wrong[(table, key)])


def _good_value(table: str, key: str, data: st.DataObject) -> object:
    kind = checked_keys()[(table, key)]
    rule = key_rule(table, key)
    default = getattr(getattr(SiteConfig(), table), key)
    if kind == "choice":
        return data.draw(st.sampled_from(rule))
    if kind == "range":
        if isinstance(default, int) and not isinstance(default, bool):
            return data.draw(st.integers(int(rule[0]), int(rule[1])))
        return data.draw(st.floats(rule[0], rule[1], allow_nan=False))
    if kind == "bool":
        return data.draw(st.booleans())
    return default


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow], deadline=None)
@given(
    st.sampled_from([k for k in KEYS if checked_keys()[k] in ("choice", "range", "text")]),
    st.data(),
)
def test_a_value_outside_its_range_or_choices_is_one_error_naming_the_key(
    key: tuple[str, str], data: st.DataObject
) -> None:
    table, name = key
    value = _bad_value(table, name, data)
    with pytest.raises(SeamapError, match=rf"^config: \[{table}\] {name}\b") as error:
        config_from_dict({table: {name: value}})
    assert "\n" not in str(error.value)


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow], deadline=None)
@given(st.sampled_from(KEYS), st.data())
def test_a_value_within_its_range_or_choices_is_taken(
    key: tuple[str, str], data: st.DataObject
) -> None:
    table, name = key
    value = _good_value(table, name, data)
    config = config_from_dict({table: {name: value}})
    assert getattr(getattr(config, table), name) == value


_TOML_ATOMS = st.sampled_from(
    ["[daemon]", "[sonar]", "[mapping]", "[zenoh]", "[mavlink]", "[coverage]", "[x]", "=",
     "\n", '"', "'", "[", "]", "{", "}", ",", "#", "true", "nan", "inf", "-", "1e999", "0x1F",
     "tilt_deg", "listen", "mosaic_res_m", "vehicle", " ", "\\", "\u00e9", "[[a]]", "a.b", "\x00"]
)  # fmt: skip
_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda inner: (
        st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=8), inner, max_size=3)
    ),
    max_leaves=6,
)


@pytest.mark.fuzz
@fuzz(300)
@given(text=st.lists(st.one_of(_TOML_ATOMS, st.text(max_size=6)), max_size=40))
def test_any_text_as_a_site_file_is_a_config_or_one_seamap_error(
    tmp_path_factory: pytest.TempPathFactory, text: list[str]
) -> None:
    path = tmp_path_factory.getbasetemp() / "fuzz-site.toml"
    path.write_text("".join(text), encoding="utf-8", errors="surrogatepass")
    try:
        load_config(path)
    except SeamapError as error:
        assert "\n" not in str(error)


@pytest.mark.fuzz
@fuzz(300)
@given(
    table=st.sampled_from(["daemon", "sonar", "mavlink", "zenoh", "mapping", "coverage", "other"]),
    values=st.dictionaries(
        st.one_of(st.sampled_from([k for _, k in KEYS]), st.text(max_size=10)), _VALUES,
        max_size=4,
    ),
)  # fmt: skip
def test_any_values_are_a_config_or_one_seamap_error(table: str, values: dict[str, object]) -> None:
    try:
        config_from_dict({table: values})
    except SeamapError as error:
        assert "\n" not in str(error)


def test_the_live_keys_reach_the_live_engine_and_leave_the_survey_end_pass_alone(
    tmp_path: Path,
) -> None:
    from daemon.replay import pipeline_params, streaming_params

    text = (
        "[live]\nregistration_res_m = 0.05\nyaw_from_gyro = false\ncandidates = 12\n"
        "redraws_per_frame = 0.25\n"
    )
    config = load_config(write(tmp_path, text))
    pipeline = pipeline_params(config)
    live = streaming_params(pipeline, config.live)
    assert live.live_registration_res_m == 0.05
    assert live.live_yaw_from_gyro is False
    assert live.live_candidates == 12
    assert live.resolve.redraws_per_frame == 0.25
    # The survey-end pass registers and blends with the pipeline's own settings.
    assert live.pipeline == pipeline
    assert pipeline.blend.top_n == 16
    assert pipeline.preprocess.registration_res_m != 0.05
