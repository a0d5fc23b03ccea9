"""The streaming engine: samples in any arrival order, bounded memory, live tiles whose
versions grow, and a survey-end pass equal to the offline single-stage pipeline."""

from __future__ import annotations

import heapq
import itertools
import math
import random
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest

from daemon.config import SiteConfig, load_config
from daemon.replay import mount_from_config, pipeline_params, read_navigation
from drivers.oculus.logfile import iter_pings
from mapping.frames import SonarMount
from mapping.live_resolve import ResolveParams
from mapping.mosaic import assemble
from mapping.pipeline import Mode, NavSamples, PipelineParams, SurveyResult, map_survey
from mapping.samples import Ping
from mapping.streaming import PoseUpdate, StreamingEngine, StreamingParams, TileUpdate
from mapping.tiles import TileStore
from tools.sim import simulate
from tools.sim.stream import survey_events


@dataclass(frozen=True)
class Stream:
    """A short survey (100 pings, 20 s) in arrival order, and its site."""

    samples: list[Any]
    config: SiteConfig

    def engine(self, **kw: object) -> StreamingEngine:
        params = StreamingParams(pipeline=pipeline_params(self.config), **kw)  # type: ignore[arg-type]
        return StreamingEngine(mount_from_config(self.config.sonar), params)

    def run(self, samples: list[Any], **kw: object) -> StreamingEngine:
        engine = self.engine(**kw)
        for sample in samples:
            engine.add(sample)
        engine.flush()
        return engine


@pytest.fixture(scope="module")
def stream() -> Stream:
    simulated = survey_events("quadrats", 4, max_pings=100, n_beams=128)
    return Stream([s for _, s in simulated.events], simulated.site_config)


def test_shuffled_and_duplicated_samples_give_the_same_map(stream: Stream) -> None:
    ordered = stream.samples
    reference = stream.run(ordered)
    rng = random.Random(7)
    # Late by up to 0.1 s (well inside the reorder window), and every 50th sample twice.
    jittered = sorted(ordered, key=lambda s: s.time + rng.uniform(0.0, 0.1))
    duplicated: list[Any] = []
    for k, sample in enumerate(jittered):
        duplicated.append(sample)
        if k % 50 == 0:
            duplicated.append(sample)
    engine = stream.run(duplicated)
    assert engine.stats.samples_duplicate == len(range(0, len(jittered), 50))
    assert engine.stats.samples_late == 0
    assert engine.stats.frames_received == reference.stats.frames_received
    np.testing.assert_allclose(np.array(engine.poses), np.array(reference.poses), atol=1e-9)


def test_samples_older_than_the_reorder_window_are_counted_not_used(stream: Stream) -> None:
    # The survey's first 30 pings (6 s) and the navigation between them.
    pings = [k for k, sample in enumerate(stream.samples) if isinstance(sample, Ping)]
    ordered = stream.samples[: pings[30]]
    engine = stream.run(ordered[:-5])
    before = engine.stats.samples_late
    engine.add(replace(ordered[100], time=ordered[100].time + 1e-6))  # seconds too late
    assert engine.stats.samples_late == before + 1


def test_live_tiles_are_published_with_growing_versions(stream: Stream) -> None:
    versions: dict[tuple[int, int], list[int]] = defaultdict(list)
    poses: list[PoseUpdate] = []

    def on_tile(update: TileUpdate) -> None:
        versions[update.key].append(update.version)
        assert update.values.shape == (update.size_px, update.size_px)
        assert update.epsg == 32618

    engine = stream.engine(move_threshold_m=0.005, live_move_threshold_m=0.01)
    engine.on_tile = on_tile
    engine.on_pose = poses.append
    for sample in stream.samples:
        engine.add(sample)
    engine.flush()
    assert engine.stats.frames_reblended > 0  # poses under tiles moved...
    assert any(len(v) > 1 for v in versions.values())  # ...and their tiles were republished
    for history in versions.values():
        assert history == sorted(history) and len(set(history)) == len(history)
    finals = {p.frame for p in poses if p.final}
    assert finals == {k for k, pose in enumerate(engine.poses) if np.isfinite(pose).all()}


def test_memory_follows_the_area_not_the_survey_length() -> None:
    # 100 s along a lane at 0.5 m/s, the sonar at the field day's 5 Hz (the hectare's 10
    # would only add pings: memory follows the area worked and how long tiles wait).
    hectare = survey_events("hectare", 2, max_pings=500, n_beams=32, ping_rate_hz=5.0)
    # Idle tiles wait in memory up to 32 MB (six tiles), then on disk.
    params = StreamingParams(
        pipeline=pipeline_params(hectare.site_config), evict_after_s=10.0, tile_memory_mb=32.0
    )
    engine = StreamingEngine(mount_from_config(hectare.site_config.sonar), params)
    peak_tiles = peak_live = 0
    for _, sample in hectare.events:
        engine.add(sample)  # type: ignore[arg-type]
        peak_tiles = max(peak_tiles, len(engine.tiles.active))
        peak_live = max(peak_live, len(engine.drawing.live))
    engine.flush()
    # The boat drove ~50 m along a lane: many tiles made, few held at any time.
    assert len(engine.tiles.all_keys()) >= 25
    assert peak_tiles <= 16
    assert peak_live <= params.window_frames + params.solve_every
    assert engine.tiles.spilled > 0


@dataclass(frozen=True)
class Recorded:
    """A recorded survey (100 pings, 20 s) and its offline single-stage result."""

    nav: NavSamples
    mount: SonarMount
    params: PipelineParams
    sonar: Path
    offline: SurveyResult

    def pings(self) -> Iterator[Ping]:
        return iter_pings(self.sonar)

    def streamed(self, params: StreamingParams) -> SurveyResult:
        """The streaming engine fed in arrival order, then its survey-end pass."""
        engine = StreamingEngine(self.mount, params)
        nav = self.nav
        streams: list[Any] = [nav.imu, nav.gnss, nav.heading, nav.attitude, self.pings()]
        for sample in heapq.merge(*streams, key=lambda s: s.time):
            engine.add(sample)
        return engine.finish(self.pings)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Recorded:
    folder = tmp_path_factory.mktemp("stream")
    simulate("quadrats", 3, folder, max_pings=100, n_beams=256)
    config = load_config(folder / "site.toml")
    nav, _ = read_navigation(folder / "nav.tlog", config)
    mount = mount_from_config(config.sonar)
    params = pipeline_params(config)

    def pings() -> Iterator[Ping]:
        return iter_pings(folder / "sonar.oculus")

    offline = map_survey(pings, nav, mount, params, Mode.SINGLE_STAGE)
    return Recorded(nav, mount, params, folder / "sonar.oculus", offline)


def test_survey_end_pass_equals_single_stage(recorded: Recorded) -> None:
    final = recorded.streamed(StreamingParams(pipeline=recorded.params))
    offline = recorded.offline
    assert isinstance(final.mode, Mode)
    both = final.mapped & offline.mapped
    assert both.sum() >= 0.98 * offline.mapped.sum()
    difference = np.linalg.norm(final.poses[both, :2] - offline.poses[both, :2], axis=1)
    assert difference.max() < 0.005  # a few millimetres (in fact the same computation)


@pytest.mark.xfail(
    reason="reused live registrations are weighed with fixed sigmas (the streaming engine "
    "does not carry FrameOutcome.registration): the shape 2.4 cm p90 off offline "
    "(quadrats seed 3, 100 pings; bound 1.5 cm). Off by default: the pass registers again",
    strict=False,
)
def test_survey_end_pass_reusing_live_registrations_keeps_the_shape(recorded: Recorded) -> None:
    # Reusing the live registrations (made at the same resolution) instead of registering
    # again stays within a centimetre or so.
    reuse = StreamingParams(
        pipeline=recorded.params, reuse_registrations=True, live_registration_res_m=None
    )
    reused = recorded.streamed(reuse)
    offline = recorded.offline
    both = reused.mapped & offline.mapped
    shift = reused.poses[both, :2] - offline.poses[both, :2]
    # Where a 20-second survey sits rests on a GNSS whose bias wanders by a metre: other
    # registrations move the whole map by a few centimetres. Its shape stays within one.
    assert np.linalg.norm(shift, axis=1).max() < 0.1
    shape = np.linalg.norm(shift - np.median(shift, axis=0), axis=1)
    assert np.percentile(shape, 90) < 0.015


def test_a_re_solve_redraws_over_the_next_frames_and_ends_drawn_where_it_put_them(
    stream: Stream,
) -> None:
    """A re-solve may move hundreds of frames: drawn again all at once, the engine would
    hold the next ping for seconds (the daemon would skip frames). They are drawn again
    within the redraw budget as the pings come, and by the end every frame is drawn at
    its pose."""
    resolve = replace(ResolveParams(), redraw_m=0.001, every_s=5.0, redraws_per_frame=1.0)
    engine = stream.engine(resolve=resolve)
    per_sample: list[int] = []
    redraw_one = engine.drawing.redraw_one

    def counted(*args: Any) -> Any:
        per_sample[-1] += 1
        return redraw_one(*args)

    engine.drawing.redraw_one = counted  # type: ignore[method-assign,assignment]
    for sample in stream.samples:
        per_sample.append(0)
        engine.add(sample)
    engine.flush()
    assert engine.stats.resolves >= 2
    assert sum(per_sample[:-1]) >= 30  # moved frames drawn again while pinging
    # While pinging, within the budget a frame (the reorder window may release two
    # pings together); the flush draws the rest.
    assert max(per_sample[:-1]) <= 2
    frames = sum(isinstance(s, Ping) for s in stream.samples)
    assert sum(per_sample[:-1]) <= resolve.redraws_per_frame * frames + 1
    assert not engine.drawing.to_redraw
    # How long the drawn map lagged the solution is measured.
    stats = engine.stats
    assert 0 < stats.redraw_wait_mean_s <= stats.redraw_wait_max_s
    # Drawn where its pose is (within what leaving the live window re-blends for).
    tolerance = max(resolve.redraw_m, engine.params.move_threshold_m)
    for k, drawn in engine.resolver.drawn.items():
        sonar = engine.mount.sonar_pose(engine.poses[k])
        moved = np.hypot(*(sonar[:2] - drawn.blended_sonar[:2]))
        moved += 5.0 * abs(math.remainder(sonar[2] - drawn.blended_sonar[2], 2 * math.pi))
        assert moved <= tolerance + 1e-9, k
    # The live poses are the re-solves' whatever the budget: it sets only how soon the
    # drawn map follows them.
    slower = stream.engine(resolve=replace(resolve, redraws_per_frame=0.25))
    for sample in stream.samples:
        slower.add(sample)
    slower.flush()
    assert slower.stats.frames_redrawn < stats.frames_redrawn
    assert slower.stats.redraw_wait_max_s > stats.redraw_wait_max_s
    np.testing.assert_array_equal(np.array(slower.poses), np.array(engine.poses))


def mosaic_of(tiles: TileStore) -> npt.NDArray[np.uint8]:
    image, _ = assemble(tiles.grid, {t.key: t.values for t in tiles.rendered_tiles()})
    return image


@pytest.fixture(scope="module")
def live_robust(stream: Stream) -> npt.NDArray[np.uint8]:
    return mosaic_of(stream.run(stream.samples).tiles)


@pytest.mark.parametrize("method", ["hurtos", "su"])
def test_the_live_map_blends_by_the_configured_method(
    stream: Stream, live_robust: npt.NDArray[np.uint8], method: str
) -> None:
    config = replace(stream.config, mapping=replace(stream.config.mapping, blending=method))
    engine = Stream(stream.samples, config).run(stream.samples)
    assert engine.params.pipeline.blend.method == method
    image = mosaic_of(engine.tiles)
    # The same seabed covered (to a few pixels: where a robust score is 0 nothing is
    # offered), blended otherwise.
    assert image.shape == live_robust.shape
    covered, reference = image > 0, live_robust > 0
    assert (covered != reference).sum() <= 0.001 * reference.sum()
    both = covered & reference
    assert np.abs(image[both].astype(float) - live_robust[both]).mean() > 2.0
    if method == "hurtos":
        # Frames the live re-solve may still draw again are all movable: a full stack
        # drops the weakest of them. Without re-solves frames settle as they leave the
        # window, and then those a full stack has no room for still count.
        assert engine.tiles.movable and not any(
            t.rest_weight is not None and t.rest_weight.any() for t in engine.tiles.active.values()
        )
        settled = Stream(stream.samples, config).run(
            stream.samples, resolve=replace(ResolveParams(), enabled=False)
        )
        assert any(
            t.rest_weight is not None and t.rest_weight.any() for t in settled.tiles.active.values()
        )


def test_the_survey_end_pass_blends_by_the_configured_method(recorded: Recorded) -> None:
    mosaics = {}
    for method in ("robust", "average", "hurtos", "su"):
        params = replace(recorded.params, blend=replace(recorded.params.blend, method=method))
        result = map_survey(recorded.pings, recorded.nav, recorded.mount, params, Mode.GPS_ONLY)
        mosaics[method] = mosaic_of(result.mosaic)
    reference = mosaics["robust"] > 0
    for method, image in mosaics.items():
        assert image.shape == mosaics["robust"].shape
        assert ((image > 0) != reference).sum() <= 0.001 * reference.sum(), method
    for a, b in itertools.combinations(mosaics, 2):
        both = (mosaics[a] > 0) & (mosaics[b] > 0)
        assert np.abs(mosaics[a][both].astype(float) - mosaics[b][both]).mean() > 2.0, (a, b)


def test_the_live_map_projects_each_ping_at_the_echosounders_seabed() -> None:
    """A sloping shore (sonar 1.1-2.1 m above the bed) with an echosounder on the
    autopilot, its first two minutes: live, each ping's altitude comes from the soundings
    so far (the bottom model rebuilt every few seconds), not the site file's mean
    (measured: 4.8 cm from the truth at the median, the site's mean 12.6 cm)."""
    simulated = survey_events("shore", 1, max_pings=600, n_beams=64)
    config = simulated.site_config
    assert config.echosounder.use
    truth = dict(zip(simulated.truth.acquisition_time, simulated.truth.altitude_m, strict=True))
    samples: list[Any] = [s for _, s in simulated.events]
    params = StreamingParams(pipeline=pipeline_params(config))
    engine = StreamingEngine(mount_from_config(config.sonar), params)
    asked = engine.local.attitude
    assert asked is not None
    seen: list[tuple[float, float | None]] = []

    def recording(stamp: float) -> Any:
        attitude = asked(stamp)
        seen.append((stamp, attitude.altitude_m if attitude is not None else None))
        return attitude

    engine.local.attitude = recording
    for sample in samples:
        engine.add(sample)
    engine.flush()
    pings = [s for s in samples if isinstance(s, Ping)]
    assert len(seen) >= len(pings) - 1
    configured = config.sonar.altitude_m
    live = [(t, a) for t, a in seen if a is not None]
    # After the first seconds every ping has the soundings' altitude ...
    assert len(live) >= 0.8 * len(seen)
    latency = params.pipeline.single_stage.graph.sonar_latency_s
    errors, off = [], []
    for stamp, altitude in live:
        true = min(truth.items(), key=lambda kv: abs(kv[0] - (stamp - latency)))[1]
        errors.append(altitude - true)
        off.append(configured - true)
    # ... closer to the truth than the site file's mean is, by far.
    assert float(np.median(np.abs(errors))) < 0.5 * float(np.median(np.abs(off)))
    assert float(np.median(np.abs(errors))) < 0.08
