"""Live loop closures: the current frame registered against keyframes of the already-final
map from an earlier pass, and fed to the live anchor as a measurement of the chain's
correction.

Between two lanes a minute apart the GNSS bias changes by a metre and the chain drifts
(its heading error over a U-turn), so neither can hold two passes over the same seabed
together to centimetres; a registration between them can, as in real-time sonar SLAM
(Hurtós et al. 2015, doi:10.1002/rob.21516; Westman & Kaess, "Degeneracy-aware imaging
sonar SLAM", ICRA 2019). The offline pass does the same in batch (``mapping.loops``,
``mapping.closures``); live, the earlier pass is final, so a closure says where the
current frame j must be for the map to agree with itself: the keyframe i's final pose
composed with the registration, minus the chain at j, a direct measurement of the chain's
correction (position and heading) for ``mapping.live_anchor``.

Keyframes: one final frame per ``keyframe_spacing_m`` travelled (or ``keyframe_turn_deg``
turned), its blending-grid image as uint8 with its final pose and the anchor's
covariance then (its own uncertainty), in a bounded store (the oldest leave first).

Robustness first: seabeds repeat (quadrat rows and farm racks a metre apart, ripples
0.2-0.45 m), and one false peak a period away would pull a whole lane a period off. So

1. each registration keeps several peaks (``register_far`` hypotheses); each is gated on
   the anchor's innovation covariance (chi-square), and a registration with two distinct
   plausible peaks whose likelihoods are close is refused (ambiguous);
2. a closure between a new pair of passes is applied only once ``confirm`` successive
   closures of that pair agree within their covariances and the chain's drift between
   them (Mangelson et al., ICRA 2018, doi:10.1109/ICRA.2018.8460217, pairwise
   consistency, applied as the closures arrive);
3. later closures of a confirmed pair are applied one by one, each still gated.

A closure's registration is a pure task (``ClosureJob``, run by ``ClosureRegistrar``):
``propose`` chooses the keyframe and the search for frame j from the live state, the
registration runs wherever the engine puts it (its front worker, with the pings that
follow), and ``conclude`` gates and applies it a fixed number of frames later against the
anchor as it is then, the measurement's covariance widened by the chain's drift since
frame j (``LiveAnchor.drift_covariance``). ``consider`` does all three at once.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

from mapping.closures import world_rotation
from mapping.fmt import FmtParams, FmtRegistrar, PreparedFrame, Registration, cached_registrar
from mapping.frames import SonarMount
from mapping.grid import SonarGrid
from mapping.live_anchor import LiveAnchor
from mapping.loops import footprint_overlap
from mapping.se2 import RelativePose, compose, relative_pose, turn

Array = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class LiveClosureParams:
    enabled: bool = True
    keyframe_spacing_m: float = 0.5
    """A final frame becomes a keyframe after this much travel since the last one."""
    keyframe_turn_deg: float = 10.0
    """...or this much turn."""
    memory_mb: float = 64.0
    """Keyframe images kept (the oldest leave first): 0.1 MB each on a 5 m fan at 2 cm."""
    min_gap_s: float = 8.0
    """A keyframe closes the current frame only when it is this much older (nearer in
    time, the chain itself holds)."""
    min_overlap: float = 0.3
    """Smallest share of the lit fan the two frames must see in common."""
    attempt_every_s: float = 1.0
    """At most one registration per this many seconds of survey time (each costs a
    registration on the blending grid, about twice a consecutive one)."""
    hypotheses: int = 4
    """Distinct correlation peaks kept per registration."""
    search_sigma_m: tuple[float, float] = (0.05, 2.0)
    """Bounds of the prior's translation sigma handed to the registrar (the anchor's
    predicted sigma between them): it weighs the peaks, the whole surface is searched."""
    min_log_likelihood: float = 70.0
    """The registration's strongest peak must be at least this strong (the registrar's
    log-likelihood, peak height times the highest over the noise variance, with the
    prior's term): on simulated field days every strongest peak that was wrong by more
    than 30 cm on the seabed was below 60, and 96 % of right ones above 70."""
    gate_chi2: float = 16.27
    """Squared Mahalanobis distance of a hypothesis from the anchor's prediction (3 dof,
    99.9 %): the right hypotheses' distances have a heavier tail than chi-square (95 %
    below 16.9 measured), the wrong ones that come this near are weak peaks."""
    ambiguity_log_ratio: float = 20.0
    """Two distinct hypotheses both within the gate whose registrar log-likelihoods are
    closer than this: the registration is refused."""
    distinct_m: float = 0.1
    """Hypotheses imply the same correction when closer than this."""
    confirm: int = 3
    """Agreeing closures of a new pair of passes before the first is applied."""
    consistency_chi2: float = 11.34
    """Between two closures' measurements (3 dof, 99 %)."""
    new_pair_sigma_m: float = 0.5
    """Added (per axis) to what is unknown between the map and the live chain at a new
    pair of passes (the gate's prediction, and the anchor's widening when the pair is
    confirmed): the right closures of new pairs were found up to 0.8 m from the anchor's
    prediction (along the lanes after a U-turn, 3-6 sigma of the modelled drift), and the
    pair is confirmed by agreement, not by the gate."""
    pass_gap_s: float = 8.0
    """Closures further apart than this in the current frame's time belong to other
    passes; a confirmed pair lapses after this long without a closure."""
    hold_before_s: float = 3.0
    """Frames since the last closure applied, and at least this long before a pending
    closure, are held live with it (the pass was over the old one, seen from farther,
    before the best overlap came)."""
    max_gate_misses: int = 3
    """A confirmed pair whose closures miss the gate this many times running lapses."""
    sigma_floor_m: float = 0.02
    """Added to the registrar's sigma per axis (the registrar's is a first-order figure
    that misses view-dependent shading)."""
    sigma_floor_deg: float = 0.3
    opposite_look_sigma_m: tuple[float, float] = (0.05, 0.05)
    """Extra (forward, starboard) sigma of a closure between headings more than 90
    degrees apart (shading and shadows move with the look direction)."""
    opposite_yaw_sigma_deg: float = 0.6
    keyframe_sigma_m: float = 0.012
    """A keyframe's pose against the drawn map: frames are re-blended only when they
    moved more than ``StreamingParams.move_threshold_m`` (2 cm), so where the seabed is
    drawn differs from the final pose by up to that (uniform: 2 cm / sqrt 3)."""


@dataclass(slots=True)
class Keyframe:
    """A final frame kept for closures: vehicle pose (local metres, grid heading), the
    anchor's correction (c_e, c_n, h) it was drawn with, and its image (uint8)."""

    index: int
    time: float
    pose: Array
    sonar: Array
    correction: Array
    heading_var: float
    image: npt.NDArray[np.uint8]
    grid: SonarGrid


@dataclass(frozen=True, slots=True)
class Closure:
    """One closure's measurement of the anchor's (c_e, c_n, h) for frame j, and the
    keyframe's own correction (so ``measured - keyframe_correction`` is the chain's drift
    between the two passes, which the map's own bends leave out)."""

    i: int
    j: int
    time_i: float
    time_j: float
    relative: RelativePose  # vehicle j in vehicle i
    measured: Array
    covariance: Array  # world frame (east, north, heading), with floors
    keyframe_correction: Array
    chain_xy: Array
    d2: float
    heading_i: float = 0.0
    """The keyframe's heading when registered (the covariance's frame)."""

    @property
    def drift(self) -> Array:
        d = self.measured - self.keyframe_correction
        d[2] = turn(float(d[2]))
        return d


@dataclass
class _Attempt:
    """A closure proposed for frame ``index`` whose registration is out."""

    index: int
    time: float
    sonar: Array
    chain_xy: Array
    chain_heading: float
    keyframe: Keyframe


@dataclass(frozen=True, slots=True)
class ClosureJob:
    """A closure's registration, a pure task: the keyframe's image (uint8) against frame
    ``index``'s, both on the blending grid ``grid`` with the fixed fan ``mask``, from the
    ``prior`` the live poses give (sonar ``index`` in sonar ``keyframe``), each peak
    weighed with the anchor's predicted ``sigma_m``, ``hypotheses`` peaks kept."""

    index: int
    keyframe: int
    keyframe_image: npt.NDArray[np.uint8]
    image: npt.NDArray[np.float32]
    grid: SonarGrid
    mask: npt.NDArray[np.bool_]
    fmt: FmtParams
    prior: RelativePose
    sigma_m: float
    hypotheses: int


class ClosureRegistrar:
    """Runs ``ClosureJob``s, keeping the last two keyframes prepared (successive attempts
    often use the same keyframe; each holds its sector spectra, a few MB)."""

    def __init__(self) -> None:
        self._prepared: dict[tuple[int, SonarGrid], PreparedFrame] = {}

    def run(self, job: ClosureJob) -> Registration:
        registrar = cached_registrar(job.grid, job.mask, job.fmt)
        key = (job.keyframe, job.grid)
        prepared = self._prepared.get(key)
        if prepared is None:
            image = job.keyframe_image.astype(np.float32) * np.float32(1 / 255)
            prepared = registrar.prepare(image)
            if len(self._prepared) >= 2:
                self._prepared.pop(next(iter(self._prepared)))
            self._prepared[key] = prepared
        return registrar.register_far(
            prepared, job.image, job.prior, prior_sigma_m=job.sigma_m, n_hypotheses=job.hypotheses
        )


@dataclass
class _Pair:
    """A confirmed pair of passes: its last closure and how often it missed the gate."""

    last: Closure
    misses: int = 0


@dataclass
class ClosureStats:
    keyframes: int = 0
    keyframes_evicted: int = 0
    keyframe_bytes: int = 0
    attempts: int = 0
    rejected_weak: int = 0
    rejected_gate: int = 0
    rejected_ambiguous: int = 0
    pending: int = 0
    rejected_inconsistent: int = 0
    confirmed_pairs: int = 0
    applied: int = 0
    log: list[dict[str, float | list[float]]] = field(default_factory=list)


class KeyframeStore:
    """Keyframes in a bounded store with a coarse spatial index of their fan centres."""

    def __init__(
        self, params: LiveClosureParams, lit_m: tuple[float, float], half_fan_rad: float
    ) -> None:
        self.params = params
        self.lit_m = lit_m
        self.half_fan_rad = half_fan_rad
        self.cell_m = max(lit_m[1], 1.0)
        self.frames: dict[int, Keyframe] = {}
        self._order: deque[int] = deque()
        self._cells: dict[tuple[int, int], list[int]] = {}
        self._last: Keyframe | None = None
        self.bytes = 0
        self.evicted = 0

    def _cell(self, sonar: Array) -> tuple[int, int]:
        mid = 0.5 * (self.lit_m[0] + self.lit_m[1])
        x = float(sonar[0]) + mid * math.sin(float(sonar[2]))
        y = float(sonar[1]) + mid * math.cos(float(sonar[2]))
        return math.floor(x / self.cell_m), math.floor(y / self.cell_m)

    def offer(
        self,
        index: int,
        time: float,
        pose: Array,
        sonar: Array,
        correction: Array,
        heading_var: float,
        image: npt.NDArray[np.float32],
        grid: SonarGrid,
    ) -> bool:
        """Keep a final frame as a keyframe when it is far enough from the last one."""
        p = self.params
        last = self._last
        if last is not None:
            moved = math.hypot(pose[0] - last.pose[0], pose[1] - last.pose[1])
            turned = abs(turn(float(pose[2] - last.pose[2])))
            if moved < p.keyframe_spacing_m and turned < math.radians(p.keyframe_turn_deg):
                return False
        stored = np.clip(np.rint(image * np.float32(255.0)), 0, 255).astype(np.uint8)
        frame = Keyframe(
            index,
            time,
            pose.copy(),
            sonar.copy(),
            np.asarray(correction, float),
            heading_var,
            stored,
            grid,
        )
        self.frames[index] = frame
        self._order.append(index)
        self._cells.setdefault(self._cell(sonar), []).append(index)
        self._last = frame
        self.bytes += self.size_of(frame)
        while self.bytes > p.memory_mb * 2**20 and len(self._order) > 1:
            self._evict(self._order.popleft())
        return True

    @staticmethod
    def size_of(frame: Keyframe) -> int:
        """Bytes a keyframe holds (its image and its few numbers)."""
        numbers = frame.pose.nbytes + frame.sonar.nbytes + frame.correction.nbytes
        return int(frame.image.nbytes + numbers)

    def move(self, index: int, pose: Array, sonar: Array, correction: Array) -> None:
        """A keyframe was drawn again at ``pose`` (its chain's ``correction`` now)."""
        frame = self.frames.get(index)
        if frame is None:
            return
        old, new = self._cell(frame.sonar), self._cell(sonar)
        if old != new:
            cell = self._cells.get(old)
            if cell is not None and index in cell:
                cell.remove(index)
            self._cells.setdefault(new, []).append(index)
        frame.pose = np.asarray(pose, float).copy()
        frame.sonar = np.asarray(sonar, float).copy()
        frame.correction = np.asarray(correction, float).copy()

    def _evict(self, index: int) -> None:
        frame = self.frames.pop(index)
        cell = self._cells.get(self._cell(frame.sonar))
        if cell is not None:
            cell.remove(index)
        self.bytes -= self.size_of(frame)
        self.evicted += 1

    def best(self, sonar: Array, time: float) -> tuple[Keyframe, float] | None:
        """The keyframe at least ``min_gap_s`` older whose fan shares the most lit seabed
        with a fan at ``sonar`` (x, y, yaw), if it shares at least ``min_overlap``."""
        p = self.params
        cx, cy = self._cell(sonar)
        reach = math.ceil(2.0 * self.lit_m[1] / self.cell_m)
        near = [
            k
            for dx in range(-reach, reach + 1)
            for dy in range(-reach, reach + 1)
            for k in self._cells.get((cx + dx, cy + dy), ())
            if self.frames[k].time <= time - p.min_gap_s
        ]
        if not near:
            return None
        old = np.array([self.frames[k].sonar for k in near])
        now = np.repeat(np.asarray(sonar, float)[None], len(near), axis=0)
        share = np.minimum(
            footprint_overlap(old, now, self.lit_m, self.half_fan_rad),
            footprint_overlap(now, old, self.lit_m, self.half_fan_rad),
        )
        k = int(np.argmax(share))
        if share[k] < p.min_overlap:
            return None
        return self.frames[near[k]], float(share[k])


def _wrapped(v: Array) -> Array:
    out = np.asarray(v, float).copy()
    out[2] = turn(float(out[2]))
    return out


class LiveClosures:
    """See the module docstring. ``offer_keyframe`` as frames become final, ``consider``
    once per accepted frame."""

    def __init__(
        self,
        params: LiveClosureParams,
        mount: SonarMount,
        lit_m: tuple[float, float],
        half_fan_rad: float,
    ) -> None:
        self.params = params
        self.mount = mount
        self.store = KeyframeStore(params, lit_m, half_fan_rad)
        self.stats = ClosureStats()
        self.log_attempts = False
        """Keep every hypothesis and applied closure in ``stats.log`` (diagnostics)."""
        self._last_attempt = -math.inf
        self._last_applied = -math.inf  # time_j of the last closure applied
        self._attempts: dict[int, _Attempt] = {}
        """Closures proposed whose registrations are out, by frame."""
        self._stale = np.zeros((3, 3))
        """The chain's drift between the frame concluded and now (added to its
        measurements' covariance)."""
        self.registrar = ClosureRegistrar()
        """Runs the registrations of ``consider`` (``propose`` hands them out instead)."""
        self._pending: list[Closure] = []
        self._doubts: list[tuple[float, float]] = []  # (time_i, time_j) of ambiguities
        self._pairs: list[_Pair] = []
        self.taken: list[Closure] = []
        """Closures applied since the owner last emptied this list, as registered (for
        the live re-solve, ``mapping.live_resolve``)."""

    def offer_keyframe(
        self,
        index: int,
        time: float,
        pose: Array,
        correction: Array,
        heading_var: float,
        image: npt.NDArray[np.float32],
        grid: SonarGrid,
    ) -> None:
        """A frame became final at ``pose``, drawn with the anchor's ``correction``
        (c_e, c_n, h) whose heading was uncertain by ``heading_var`` (rad^2)."""
        sonar = self.mount.sonar_pose(pose)
        if self.store.offer(index, time, pose, sonar, correction, heading_var, image, grid):
            self.stats.keyframes += 1
        self.stats.keyframes_evicted = self.store.evicted
        self.stats.keyframe_bytes = self.store.bytes

    def rebase(self) -> None:
        """The drawn map was re-solved (``mapping.live_resolve``): keyframes moved and
        the anchor's correction with them. A confirmed pair's last closure takes its
        keyframe's new correction (else the next closure of the pair would follow the
        re-solve's move once more, as a bend of the map); closures waiting for agreement
        were measured against the map as it was, and wait again."""
        kept = []
        for pair in self._pairs:
            frame = self.store.frames.get(pair.last.i)
            if frame is None:
                continue
            pair.last = replace(pair.last, keyframe_correction=frame.correction.copy())
            kept.append(pair)
        self._pairs = kept
        self._pending = []

    def holding(self, now: float) -> float | None:
        """While closures of a new pair of passes wait for agreement (at survey time
        ``now``): the time from which the live frames should stay movable
        (``hold_before_s`` before the first of them, when the pass was already over the
        old one), else None."""
        self._pending = [c for c in self._pending if now - c.time_j <= self.params.pass_gap_s]
        if not self._pending:
            return None
        # Everything drawn since the last closure was applied was drawn with the
        # correction the new pair is about to correct.
        first = min(c.time_j for c in self._pending)
        return min(first - self.params.hold_before_s, self._last_applied)

    # -- one frame ------------------------------------------------------------------------
    def consider(
        self,
        index: int,
        time: float,
        pose: Array,
        chain_xy: Array,
        chain_heading: float,
        image: npt.NDArray[np.float32],
        registrar: FmtRegistrar,
        anchor: LiveAnchor,
    ) -> bool:
        """Try a closure for accepted frame ``index`` at its live ``pose`` (the chain at
        ``chain_xy``, ``chain_heading``, plus the anchor's correction) at once: propose,
        register here, conclude. True when the anchor was updated."""
        job = self.propose(
            index, time, pose, chain_xy, chain_heading, image,
            registrar.grid, registrar.mask, registrar.params, anchor,
        )  # fmt: skip
        if job is None:
            return False
        return self.conclude(index, self.registrar.run(job), chain_xy, time, anchor)

    def propose(
        self,
        index: int,
        time: float,
        pose: Array,
        chain_xy: Array,
        chain_heading: float,
        image: npt.NDArray[np.float32],
        grid: SonarGrid,
        mask: npt.NDArray[np.bool_],
        fmt: FmtParams,
        anchor: LiveAnchor,
    ) -> ClosureJob | None:
        """Choose a keyframe to close accepted frame ``index`` against (its ``image`` on
        the blending ``grid``, fixed fan ``mask``) and the registration's search, or None
        (none near enough, or too soon after the last attempt). The registration's answer
        goes to ``conclude``."""
        p = self.params
        if not p.enabled or time - self._last_attempt < p.attempt_every_s:
            return None
        sonar = self.mount.sonar_pose(pose)
        found = self.store.best(sonar, time)
        if found is None:
            return None
        keyframe, _ = found
        if keyframe.grid != grid:
            return None
        self._last_attempt = time
        self.stats.attempts += 1
        self._pairs = [pair for pair in self._pairs if time - pair.last.time_j <= p.pass_gap_s]
        pair = self._pair_of(keyframe.time, time)
        _, unknown = self._expected(keyframe, pair, chain_xy, time, anchor)
        predicted = anchor.correction_covariance() + unknown
        sigma = math.sqrt(max(float(np.linalg.eigvalsh(predicted[:2, :2])[-1]), 0.0))
        sigma = min(max(sigma, p.search_sigma_m[0]), p.search_sigma_m[1])
        self._attempts[index] = _Attempt(
            index, time, sonar.copy(), np.asarray(chain_xy, float).copy(), chain_heading, keyframe
        )
        return ClosureJob(
            index, keyframe.index, keyframe.image, image, grid, mask, fmt,
            relative_pose(keyframe.sonar, sonar), sigma, p.hypotheses,
        )  # fmt: skip

    def conclude(
        self,
        index: int,
        registration: Registration,
        chain_xy: Array,
        now: float,
        anchor: LiveAnchor,
    ) -> bool:
        """The registration proposed for frame ``index`` came back: gate it on the anchor
        as it is ``now`` (the chain then at ``chain_xy``), the measurement widened by the
        chain's drift since frame ``index``; apply what is confirmed. True when the anchor
        was updated."""
        attempt = self._attempts.pop(index, None)
        if attempt is None:
            return False
        p = self.params
        time, keyframe = attempt.time, attempt.keyframe
        path = np.asarray(chain_xy, float) - attempt.chain_xy
        drift = (float(path[0]), float(path[1]))
        self._stale = anchor.drift_covariance(max(now - time, 0.0), drift)
        self._pairs = [pair for pair in self._pairs if time - pair.last.time_j <= p.pass_gap_s]
        pair = self._pair_of(keyframe.time, time)
        bend, unknown = self._expected(keyframe, pair, attempt.chain_xy, time, anchor)
        closure = self._register(attempt, registration, anchor, bend, unknown)
        if closure is None:
            if pair is not None:
                pair.misses += 1
                if pair.misses >= p.max_gate_misses:
                    self._pairs.remove(pair)
            return False
        if pair is not None:
            pair.last, pair.misses = closure, 0
            anchor.shift(bend)
            self._apply(closure, anchor)
            self.taken.append(closure)
            return True
        return self._confirm(closure, anchor, unknown)

    def _expected(
        self,
        keyframe: Keyframe,
        pair: _Pair | None,
        chain_xy: Array,
        time: float,
        anchor: LiveAnchor,
    ) -> tuple[Array, Array]:
        """What the anchor is predicted to measure at frame ``time`` (the chain at
        ``chain_xy``) beyond its own correction: the map's known ``bend`` between a
        confirmed pair's last keyframe and this one (``pair``, None for a new pair of
        passes), and what is ``unknown`` (3 x 3)."""
        if pair is not None:
            # In a confirmed pair the map's own bend between its last keyframe and this
            # one is known: the live correction is predicted to follow it.
            return _wrapped(keyframe.correction - pair.last.keyframe_correction), np.zeros((3, 3))
        # A new pair: the map there was drawn with another correction than the live
        # one (the anchor moved since, with the GNSS and other closures), and the
        # chain drifted since; how much of the difference is which is unknown.
        ce, cn = anchor.correction
        moved = _wrapped(keyframe.correction - np.array([ce, cn, anchor.heading]))
        path = chain_xy - (keyframe.pose[:2] - keyframe.correction[:2])
        unknown = np.outer(moved, moved) + anchor.drift_covariance(
            time - keyframe.time, (float(path[0]), float(path[1]))
        )
        unknown[:2, :2] += self.params.new_pair_sigma_m**2 * np.eye(2)
        return np.zeros(3), unknown

    def _register(
        self,
        attempt: _Attempt,
        reg: Registration,
        anchor: LiveAnchor,
        bend: Array,
        unknown: Array,
    ) -> Closure | None:
        """Gate each hypothesis of the registration against the keyframe on the anchor's
        prediction (moved by the map's known ``bend``, widened by what is ``unknown``
        between the keyframe and now), refuse ambiguity; the chosen measurement."""
        p = self.params
        index, time, sonar, keyframe = attempt.index, attempt.time, attempt.sonar, attempt.keyframe
        chain_xy, chain_heading = attempt.chain_xy, attempt.chain_heading
        rotation = world_rotation(float(keyframe.pose[2]))
        turned = abs(turn(float(sonar[2] - keyframe.sonar[2])))
        floor = np.diag([p.sigma_floor_m**2] * 2 + [math.radians(p.sigma_floor_deg) ** 2])
        if turned > math.pi / 2:
            look_f, look_s = p.opposite_look_sigma_m
            floor += np.diag([look_f**2, look_s**2, math.radians(p.opposite_yaw_sigma_deg) ** 2])
        keyframe_cov = np.diag([p.keyframe_sigma_m**2] * 2 + [0.0])
        plausible: list[tuple[float, Closure]] = []  # (log-likelihood, closure)
        strongest = max((h.log_likelihood for h in reg.hypotheses), default=-math.inf)
        if strongest < p.min_log_likelihood:
            self.stats.rejected_weak += 1
            return None
        for rank, hyp in enumerate(reg.hypotheses or ()):
            vehicle = self.mount.vehicle_relative(hyp.relative)
            raw = self.mount.vehicle_covariance(hyp.covariance)
            implied = compose(keyframe.pose, vehicle)
            measured = _wrapped(
                np.array(
                    [implied[0] - chain_xy[0], implied[1] - chain_xy[1], implied[2] - chain_heading]
                )
            )
            covariance = rotation @ (raw + floor) @ rotation.T + keyframe_cov
            nu, s = anchor.closure_innovation(measured - bend, covariance + unknown + self._stale)
            d2 = float(nu @ np.linalg.solve(s, nu))
            closure = Closure(
                keyframe.index, index, keyframe.time, time, vehicle, measured, covariance,
                keyframe.correction, np.asarray(chain_xy, float).copy(), d2,
                float(keyframe.pose[2]),
            )  # fmt: skip
            if self.log_attempts:
                self._log(closure, rank, hyp.log_likelihood, hyp.score, raw, nu, s)
            if d2 < p.gate_chi2:
                plausible.append((hyp.log_likelihood, closure))
        if not plausible:
            self.stats.rejected_gate += 1
            return None
        plausible.sort(key=lambda item: -item[0])
        best_ll, best = plausible[0]
        if best_ll < strongest:
            # The registration's strongest peak is not where the anchor expects it: a
            # weaker one near the prediction is no evidence (the prediction may be what
            # is wrong), so nothing is taken.
            self.stats.rejected_gate += 1
            return None
        for rival_ll, rival in plausible[1:]:
            apart = float(np.hypot(*(rival.measured[:2] - best.measured[:2])))
            if apart > p.distinct_m and best_ll - rival_ll < p.ambiguity_log_ratio:
                self.stats.rejected_ambiguous += 1
                self._doubts.append((keyframe.time, time))
                return None
        return best

    def _log(
        self,
        closure: Closure,
        rank: int,
        log_likelihood: float,
        score: float,
        raw: Array,
        nu: Array,
        s: Array,
    ) -> None:
        self.stats.log.append(
            {
                "i": float(closure.i),
                "j": float(closure.j),
                "rank": float(rank),
                "forward_m": closure.relative.forward_m,
                "starboard_m": closure.relative.starboard_m,
                "yaw_rad": closure.relative.yaw_rad,
                "d2": closure.d2,
                "log_likelihood": log_likelihood,
                "score": score,
                "raw_cov": [float(v) for v in np.ravel(raw)],
                "nu": [float(v) for v in nu],
                "S": [float(v) for v in np.ravel(s)],
            }
        )

    # -- which closures reach the anchor --------------------------------------------------
    def _same_passes(self, time_i: float, time_j: float, other: Closure) -> bool:
        """Closures of the same pair of passes: near in the current frame's time, and the
        keyframe moved no more than that (plus a pass gap) along the earlier pass."""
        gap = self.params.pass_gap_s
        dt_j = abs(time_j - other.time_j)
        return dt_j <= gap and abs(time_i - other.time_i) <= dt_j + gap

    def _pair_of(self, time_i: float, time_j: float) -> _Pair | None:
        for pair in self._pairs:
            if self._same_passes(time_i, time_j, pair.last):
                return pair
        return None

    def _drift_between(self, a: Closure, b: Closure, anchor: LiveAnchor) -> Array:
        path = b.chain_xy - a.chain_xy
        return anchor.drift_covariance(abs(b.time_j - a.time_j), (float(path[0]), float(path[1])))

    def _consistent(self, a: Closure, b: Closure, anchor: LiveAnchor) -> bool:
        """Two closures imply the same drift of the chain against the map, within their
        covariances and the chain's drift between them."""
        if not self._same_passes(a.time_i, a.time_j, b):
            return False
        diff = _wrapped(b.drift - a.drift)
        cov = a.covariance + b.covariance + self._drift_between(a, b, anchor)
        return float(diff @ np.linalg.solve(cov, diff)) < self.params.consistency_chi2

    def _confirm(self, closure: Closure, anchor: LiveAnchor, unknown: Array) -> bool:
        """A closure of a new pair of passes waits until ``confirm`` of them agree, and
        one more for each that disagrees and each registration of the pair refused as
        ambiguous (a seabed that repeats: the strongest peak moves from one period to
        the next between registrations, and three of one period in a row prove
        nothing); then the anchor's uncertainty is widened by what was ``unknown``
        between the map there and the live chain, and the agreeing ones are applied
        (each as a measurement of the drift at this closure's keyframe, with the
        chain's drift since it was taken), then this one."""
        p = self.params
        self._pending = [c for c in self._pending if closure.time_j - c.time_j <= p.pass_gap_s]
        self._doubts = [d for d in self._doubts if closure.time_j - d[1] <= p.pass_gap_s]
        agreeing = [c for c in self._pending if self._consistent(c, closure, anchor)]
        rivals = sum(
            1
            for c in self._pending
            if c not in agreeing and self._same_passes(c.time_i, c.time_j, closure)
        )
        doubts = sum(1 for ti, tj in self._doubts if self._same_passes(ti, tj, closure))
        if len(agreeing) + 1 < p.confirm + rivals + doubts:
            self._pending.append(closure)
            self.stats.pending += 1
            return False
        self.stats.confirmed_pairs += 1
        self.stats.rejected_inconsistent += len(self._pending) - len(agreeing)
        anchor.inflate(unknown)
        for earlier in agreeing:
            measured = _wrapped(earlier.drift + closure.keyframe_correction)
            covariance = earlier.covariance + self._drift_between(earlier, closure, anchor)
            self._apply(replace(earlier, measured=measured, covariance=covariance), anchor)
        self._apply(closure, anchor)
        self.taken.extend([*agreeing, closure])
        self._pending = []
        self._pairs.append(_Pair(closure))
        return True

    def _apply(self, closure: Closure, anchor: LiveAnchor) -> None:
        covariance = closure.covariance + self._stale
        if self.log_attempts:
            nu, s = anchor.closure_innovation(closure.measured, covariance)
            self.stats.log.append(
                {
                    "applied": 1.0,
                    "i": float(closure.i),
                    "j": float(closure.j),
                    "forward_m": closure.relative.forward_m,
                    "starboard_m": closure.relative.starboard_m,
                    "yaw_rad": closure.relative.yaw_rad,
                    "d2": float(nu @ np.linalg.solve(s, nu)),
                }
            )
        anchor.update_closure(closure.measured, covariance)
        self.stats.applied += 1
        self._last_applied = max(self._last_applied, closure.time_j)
