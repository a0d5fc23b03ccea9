"""The mapping's work in worker processes (``daemon.workers``): the same map, to the bit,
wherever the live engine's front runs or the survey-end pass's tasks do, and a worker
killed mid-survey is replaced."""

from __future__ import annotations

import os
import signal
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from daemon.config import SiteConfig, load_config
from daemon.replay import mount_from_config, pipeline_params, read_navigation, streaming_params
from daemon.workers import ProcessFront, ProcessPool, live_front
from drivers.oculus.logfile import iter_pings
from mapping.pipeline import Mode, map_survey
from mapping.samples import Ping
from mapping.stream_front import InlineFront
from mapping.streaming import PoseUpdate, StreamingEngine, TileUpdate
from tools.sim import simulate
from tools.sim.stream import survey_events


@dataclass(frozen=True)
class Survey:
    samples: list[Any]
    config: SiteConfig


@dataclass
class Run:
    engine: StreamingEngine
    poses: list[PoseUpdate]
    tiles: list[tuple[Any, int, bytes]]


def _survey(scenario: str, seed: int, pings: int) -> Survey:
    simulated = survey_events(scenario, seed, max_pings=pings, n_beams=128)
    return Survey([s for _, s in simulated.events], simulated.site_config)


@pytest.fixture(scope="module")
def quadrats() -> Survey:
    """Two lanes and the start of a third: the live loop closures' registrations start
    about frame 300, where the third lane passes over the first."""
    return _survey("quadrats", 4, 380)


@pytest.fixture(scope="module")
def shore() -> Survey:
    """A sloping shore with an echosounder: each ping's seabed comes from the soundings
    placed by the live poses, the one thing the front is given from the later stages."""
    return _survey("shore", 1, 300)


def _run(survey: Survey, workers: int, kill_at: int | None = None, kill: int = 0) -> Run:
    """``kill_at``: the ping at which worker ``kill`` (0: the front's, 1: the live
    closures') is killed."""
    mount = mount_from_config(survey.config.sonar)
    params = streaming_params(pipeline_params(survey.config), survey.config.live)
    said: list[str] = []
    front = live_front(mount, params, workers, log=said.append)
    poses: list[PoseUpdate] = []
    tiles: list[tuple[Any, int, bytes]] = []

    def on_tile(update: TileUpdate) -> None:
        tiles.append((update.key, update.version, update.values.tobytes()))

    engine = StreamingEngine(mount, params, on_pose=poses.append, on_tile=on_tile, front=front)
    pings = 0
    try:
        for sample in survey.samples:
            engine.add(sample)
            if isinstance(sample, Ping):
                pings += 1
                if pings == kill_at:
                    assert isinstance(front, ProcessFront)
                    os.kill(front.pids[kill], signal.SIGKILL)
        engine.flush()
    finally:
        engine.close()
    if kill_at is not None:
        assert isinstance(front, ProcessFront)
        assert front.restarts == 1
        assert len(said) == 1 and "restarted" in said[0], said
    else:
        assert not said
    return Run(engine, poses, tiles)


@pytest.mark.parametrize("name", ["quadrats", "shore"])
def test_the_live_map_is_the_same_to_the_bit_with_the_front_in_a_worker(
    name: str, request: pytest.FixtureRequest
) -> None:
    survey: Survey = request.getfixturevalue(name)
    inline = _run(survey, workers=0)
    worker = _run(survey, workers=1)
    two = _run(survey, workers=2)  # the live closures' registrations in a second worker
    assert isinstance(inline.engine.front, InlineFront)
    assert isinstance(worker.engine.front, ProcessFront)
    assert isinstance(two.engine.front, ProcessFront) and two.engine.front.side
    closures = inline.engine.closures
    if name == "quadrats":
        assert closures is not None and closures.stats.attempts >= 10, closures
    assert inline.engine.stats.frames_mapped > 250
    assert inline.engine.stats.resolves >= 1  # the re-solve and its redraws are in it
    # Every pose update, every tile published, in the same order, to the bit.
    for run in (worker, two):
        assert run.poses == inline.poses
        assert run.tiles == inline.tiles
        np.testing.assert_array_equal(np.array(run.engine.poses), np.array(inline.engine.poses))


@pytest.mark.parametrize("kill", [0, 1], ids=["front", "closures"])
def test_a_worker_killed_mid_survey_is_replaced_and_the_survey_goes_on(
    quadrats: Survey, kill: int
) -> None:
    # The closures' worker is killed while it has registrations to answer.
    killed = _run(quadrats, workers=1 + kill, kill_at=120 if kill == 0 else 330, kill=kill)
    stats = killed.engine.stats
    assert stats.frames_received == sum(isinstance(s, Ping) for s in quadrats.samples)
    # The frames the dead worker held are registered by the new one: none is lost.
    assert stats.frames_mapped >= stats.frames_received - 2
    assert all(np.all(np.isfinite(p)) for p in killed.engine.poses[-100:])


def _die_once(job: tuple[int, str]) -> int:
    """A pure task whose worker dies the first time it meets job 3 (a marker file says it
    did): the pool must run the job again and go on."""
    value, marker = job
    if value == 3 and not Path(marker).exists():
        Path(marker).touch()
        os._exit(1)
    return value * value


def test_the_pool_gives_results_in_order_and_runs_a_dead_workers_tasks_again(
    tmp_path: Path,
) -> None:
    said: list[str] = []
    pool = ProcessPool(2, log=said.append)
    try:
        marker = str(tmp_path / "died")
        results = list(pool.run(_die_once, ((k, marker) for k in range(10))))
    finally:
        pool.close()
    assert results == [k * k for k in range(10)]
    assert pool.restarts == 1 and len(said) == 1 and "run again" in said[0]


class _Unpicklable(Exception):
    def __reduce__(self) -> Any:
        raise TypeError("not across processes")


def _fails_on(job: int) -> int:
    """A pure task that raises for some jobs, as a task on bad input would."""
    if job == 2:
        raise ValueError("ping 2 has no beams")
    if job == 4:
        raise FileNotFoundError("no such table")
    if job == 6:
        raise _Unpicklable("a local error")
    return job + 100


def test_a_task_that_raises_in_a_worker_raises_in_the_engine_and_the_worker_goes_on() -> None:
    """Before, the worker ended with the error, was started again with the same job and
    ended again, without end. Now the error is raised where the result is taken (an
    OSError too, which is not taken for a dead worker), and the worker takes the next
    job."""
    said: list[str] = []
    pool = ProcessPool(1, log=said.append)
    try:
        assert pool.submit(_fails_on, 1).result() == 101
        with pytest.raises(ValueError, match="no beams"):
            pool.submit(_fails_on, 2).result()
        with pytest.raises(FileNotFoundError, match="no such table"):
            pool.submit(_fails_on, 4).result()
        with pytest.raises(RuntimeError, match="_Unpicklable: a local error"):
            pool.submit(_fails_on, 6).result()
        assert list(pool.run(_fails_on, [3, 5])) == [103, 105]
    finally:
        pool.close()
    assert pool.restarts == 0 and said == []


def test_the_survey_end_pass_in_workers_gives_the_same_map(tmp_path: Path) -> None:
    """The survey-end pass's preprocessing, registrations (computed ahead,
    ``mapping.ahead``) and loop closures in two worker processes: the same registrations,
    closures, poses and mosaic, to the bit (quadrats at 2 Hz: three lanes in 150 s)."""
    simulate("quadrats", 5, tmp_path, max_pings=300, n_beams=128, ping_rate_hz=2)
    config = load_config(tmp_path / "site.toml")
    nav, _ = read_navigation(tmp_path / "nav.tlog", config)
    mount = mount_from_config(config.sonar)
    params = replace(pipeline_params(config), register_ahead=True)

    def pings() -> Iterator[Ping]:
        return iter_pings(tmp_path / "sonar.oculus")

    here = map_survey(pings, nav, mount, params, Mode.SINGLE_STAGE)
    pool = ProcessPool(2)
    try:
        pooled = map_survey(pings, nav, mount, params, Mode.SINGLE_STAGE, pool=pool)
    finally:
        pool.close()
    assert here.loops.registered >= 10, here.loops  # closures were there to register
    assert pooled.ahead["ahead"] >= 250, pooled.ahead  # the registrations came from the pool
    assert pooled.edges == here.edges
    assert [o.reason for o in pooled.outcomes] == [o.reason for o in here.outcomes]
    assert pooled.loops == here.loops
    assert pooled.closures == here.closures
    np.testing.assert_array_equal(pooled.poses, here.poses)
    # Its frames preprocessed in the pool, for the registrations and for blending: the
    # same mosaic, tile for tile.
    tiles = {t.key: t.values.tobytes() for t in here.mosaic.rendered_tiles()}
    assert len(tiles) >= 20
    assert {t.key: t.values.tobytes() for t in pooled.mosaic.rendered_tiles()} == tiles
