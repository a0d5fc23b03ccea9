"""The fan geometry follows the pings: kept while it holds, rebuilt when the sonar's
range or beams change (the Oculus changes range mid-survey)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np

from daemon.config import load_config
from daemon.replay import mount_from_config, pipeline_params, read_navigation
from drivers.oculus.logfile import iter_pings
from mapping.frames import _PREPROCESSORS, LocalRegistration, SonarMount, prepare_frame_job
from mapping.pipeline import Mode, map_survey
from mapping.polar import Attitude
from mapping.preprocess import PreprocessParams, SonarFrame
from mapping.samples import Ping
from mapping.tasks import InlinePool
from tools.sim import simulate


def _ping(t: float, n_ranges: int, resolution_m: float, bearings: np.ndarray) -> Ping:
    rng = np.random.default_rng(int(t * 10))
    image = rng.integers(0, 255, (n_ranges, bearings.size), dtype=np.uint8)
    return Ping(t, int(t * 10), 2, 1.2e6, resolution_m, bearings, image)


def test_the_geometry_is_kept_while_the_pings_share_it_and_rebuilt_when_they_do_not() -> None:
    local = LocalRegistration(SonarMount(altitude_m=1.0, tilt_rad=0.35))
    bearings = np.linspace(-1.13, 1.13, 128)
    local.frame(_ping(0.0, 200, 0.02, bearings))
    first = local.preprocessor
    assert first is not None
    # The same geometry in new arrays (each ping decodes its own): the same tables.
    local.frame(_ping(0.1, 200, 0.02, bearings.copy()))
    assert local.preprocessor is first
    # A longer range: new tables, a longer grid.
    local.frame(_ping(0.2, 200, 0.03, bearings))
    assert local.preprocessor is not first
    longer = local.preprocessor
    assert longer is not None and longer.grid is not None and first.grid is not None
    assert longer.grid.shape[0] > first.grid.shape[0]
    # Other beams (a narrower fan) at that range: rebuilt again.
    local.frame(_ping(0.3, 200, 0.03, bearings * 0.5))
    assert local.preprocessor is not longer
    assert local.preprocessor is not None and local.preprocessor.grid is not None
    assert local.preprocessor.grid.shape[1] < longer.grid.shape[1]


def _same_frames(a: SonarFrame, b: SonarFrame) -> None:
    for name in ("image", "mask", "weight", "coarse", "fan_weight", "coarse_mask", "own_mask"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert x.dtype == y.dtype and np.array_equal(x, y), name


def test_a_ping_preprocessed_elsewhere_is_the_frame_preprocessed_here() -> None:
    """``prepare_job`` hands out what ``frame`` carries from the pings before (the fan, the
    first frame's histogram reference, the ping's attitude): ``prepare_frame_job`` in a
    fresh process state gives the same frame to the bit, tilted pings at their own
    altitude included. The first ping, a new geometry and a flat field stay here."""
    bearings = np.linspace(-1.13, 1.13, 128)

    def attitude(t: float) -> Attitude:
        return Attitude(0.02 * np.sin(t), 0.03 * np.cos(t), 1.0 + 0.2 * np.sin(3 * t))

    mount = SonarMount(altitude_m=1.0, tilt_rad=0.35, forward_m=0.4)
    here = LocalRegistration(mount, attitude=attitude)
    elsewhere = LocalRegistration(mount, attitude=attitude)
    pings = [_ping(0.1 * k, 200, 0.02, bearings.copy()) for k in range(6)]
    assert elsewhere.prepare_job(pings[0]) is None  # nothing known yet
    elsewhere.frame(pings[0])
    _same_frames(elsewhere.frame(pings[0]), here.frame(pings[0]))
    jobs = []
    for ping in pings[1:]:
        job = elsewhere.prepare_job(ping)
        assert job is not None
        jobs.append(job)
        _PREPROCESSORS.clear()  # as in a worker that never saw this survey
        _same_frames(prepare_frame_job(job), here.frame(ping))
    for job in jobs:  # one preprocessor kept for them all
        prepare_frame_job(job)
    assert len(_PREPROCESSORS) == 1
    # Another range: its tables are built here first.
    assert elsewhere.prepare_job(_ping(1.0, 200, 0.03, bearings)) is None
    flat = LocalRegistration(mount, PreprocessParams(flat_field_s=5.0))
    flat.frame(pings[0])
    assert flat.prepare_job(pings[1]) is None  # the running mean is kept here


class _TwoAtOnce(InlinePool):
    """Tasks here, as a pool of two would be given them (``workers`` decides what the
    survey-end pass hands out)."""

    workers = 2


def test_the_pass_preprocessing_in_a_pool_gives_the_same_map_across_a_range_change(
    tmp_path: Path,
) -> None:
    """A survey whose sonar range changes mid-way (the Oculus at a shorter range from ping
    60): the pass's frames preprocessed in the pool (registrations, closures, blending)
    wait for the frames of the old range to be registered, the first of the new is
    preprocessed here, and the registrations, poses and mosaic are those of one process.
    Loop closure candidates between frames of the two ranges are left out."""
    simulate("quadrats", 5, tmp_path, max_pings=140, n_beams=64, ping_rate_hz=2)
    config = load_config(tmp_path / "site.toml")
    nav, _ = read_navigation(tmp_path / "nav.tlog", config)
    mount = mount_from_config(config.sonar)
    params = pipeline_params(config)

    def pings() -> Iterator[Ping]:
        for k, ping in enumerate(iter_pings(tmp_path / "sonar.oculus")):
            yield ping if k < 60 else replace(ping, image=ping.image[: ping.n_ranges * 4 // 5])

    here = map_survey(pings, nav, mount, params, Mode.SINGLE_STAGE)
    pooled = map_survey(pings, nav, mount, params, Mode.SINGLE_STAGE, pool=_TwoAtOnce())
    assert sum(o.accepted for o in here.outcomes) >= 100, Counter(o.reason for o in here.outcomes)
    # Candidate closures between the two ranges were left out (they raised, and the
    # whole pass with them), those within one range registered.
    assert here.loops.other_geometry > 0 and here.loops.registered > 0, here.loops
    assert pooled.loops == here.loops
    assert pooled.edges == here.edges
    assert [o.reason for o in pooled.outcomes] == [o.reason for o in here.outcomes]
    np.testing.assert_array_equal(pooled.poses, here.poses)
    tiles = {t.key: t.values.tobytes() for t in here.mosaic.rendered_tiles()}
    assert {t.key: t.values.tobytes() for t in pooled.mosaic.rendered_tiles()} == tiles
