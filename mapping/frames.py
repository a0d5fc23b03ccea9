"""Per-frame local registration, shared by the batch pipeline and the streaming engine.

Each ping is preprocessed into a Cartesian frame, registered by FMT against the last
accepted frame, and the result is validated against the EKF's relative motion with the
paper's thresholds tau_p, tau_a (Zhang et al., Eq. 4-5; Algorithm 1 lines 3-10). Frames
are sonar frames; the edges handed to the optimiser are vehicle-frame relative poses,
through the sonar's lever arm and mount yaw (``SonarMount``).
"""

from __future__ import annotations

import hashlib
import math
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from mapping.fmt import FmtParams, FmtRegistrar, PreparedFrame, Registration, cached_registrar
from mapping.grid import SonarGrid
from mapping.polar import Attitude, FanGeometry
from mapping.posegraph import Edge
from mapping.preprocess import Preprocessor, PreprocessParams, SonarFrame
from mapping.samples import Ping
from mapping.se2 import RelativePose, compose, relative_pose, wrap_pi
from mapping.tasks import TaskHandle, TaskPool

Array = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class SonarMount:
    """Where the sonar sits on the vehicle (body frame, relative to the GPS antenna).

    forward_m / starboard_m / down_m: lever arm (m); yaw_rad: boresight relative to the bow,
    clockwise; tilt_rad: boresight below horizontal; altitude_m: sonar height above the
    seabed (0 when unknown).
    """

    forward_m: float = -0.45
    starboard_m: float = 0.0
    down_m: float = 0.3
    yaw_rad: float = 0.0
    tilt_rad: float = math.radians(15.0)
    altitude_m: float = 1.0

    def matrix(self) -> Array:
        """Sonar level frame in the vehicle frame (3x3, (forward, starboard) metres)."""
        return RelativePose(self.forward_m, self.starboard_m, self.yaw_rad).matrix()

    def sonar_pose(self, vehicle: Array) -> Array:
        """Sonar (x, y, yaw) in the local frame from vehicle (x, y, heading): (..., 3)."""
        vehicle = np.asarray(vehicle, float)
        psi = vehicle[..., 2]
        s, c = np.sin(psi), np.cos(psi)
        x = vehicle[..., 0] + self.forward_m * s + self.starboard_m * c
        y = vehicle[..., 1] + self.forward_m * c - self.starboard_m * s
        return np.stack([x, y, (psi + self.yaw_rad) % (2 * math.pi)], axis=-1)

    def vehicle_relative(self, sonar: RelativePose) -> RelativePose:
        """Vehicle-frame relative pose from a sonar-frame one: M S M^-1."""
        m = self.matrix()
        return RelativePose.from_matrix(m @ sonar.matrix() @ np.linalg.inv(m))

    def vehicle_covariance(self, sonar: Array) -> Array:
        """Covariance (3 x 3, forward m, starboard m, yaw rad) of ``vehicle_relative``'s
        result from that of its sonar-frame input, to first order about no motion:
        M S M^-1 turns the translation by the mount yaw and adds (l_y, -l_x) per radian
        of yaw (l the lever arm)."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        jac = np.array(
            [
                [c, -s, self.starboard_m],
                [s, c, -self.forward_m],
                [0.0, 0.0, 1.0],
            ]
        )
        return np.asarray(jac @ np.asarray(sonar, float) @ jac.T, float)

    def sonar_relative(self, vehicle: RelativePose) -> RelativePose:
        """Sonar-frame relative pose from a vehicle-frame one: M^-1 V M."""
        m = self.matrix()
        return RelativePose.from_matrix(np.linalg.inv(m) @ vehicle.matrix() @ m)


COAST_SPEED_SIGMA_MPS = 0.3
"""Without the gyro and without the chain's own velocity, how far the boat's velocity may
be from the filter's held one, per axis (m/s: a survey boat runs at 0.3-1 m/s and may
have turned since the filter last knew); the registration's gate and the survey graph's
odometry bridges take it alike."""
COAST_YAW_RATE_SIGMA_RPS = math.radians(10.0)
"""... and its turn rate from none (rad/s: a lawnmower turn of 2 m radius at 0.4 m/s is 11
degrees/s)."""


@dataclass(frozen=True, slots=True)
class RegistrationParams:
    tau_p_m: float = 0.15
    """Largest disagreement between FMT and EKF relative translation (metres)."""
    tau_a_deg: float = 3.0
    """Largest disagreement in relative yaw (degrees)."""
    min_score: float = 0.05
    """Smallest NCC of the aligned overlap for a registration to count."""
    min_overlap: float = 0.3
    max_gap_s: float = 1.5
    """Register against the last accepted frame only while it is this recent; after a
    longer run of rejections the chain restarts (the next frame is kept on its prior)."""
    keyframe_m: float = 0.3
    """Frames are registered against a keyframe, which moves on to the newest accepted
    frame once that lies this far from it (metres), turned ``keyframe_deg`` from it or
    ``keyframe_s`` after it (0: every frame against the previous one). Each frame's
    registration errs by a few millimetres and a few hundredths of a degree, partly the
    same way from one pair to the next: against the previous frame these add up once a
    frame, so over 20 s a 10 Hz chain drifted 2.7 times as far as a 2 Hz one (72 against
    27 mm). Against a keyframe they add up once a keyframe, and the edge from the previous
    frame is composed through it (the chain from the keyframe to any frame is that
    frame's one registration). Measured on the registration chain alone, error over 30 s
    of travel, no keyframes against 0.3 m and 3 degrees: 10 Hz 24.2 -> 11.1 cm and 2.66 ->
    0.66 degrees; the 0.15 m/s current at 5 Hz 16.5 -> 13.5 cm, 1.42 -> 0.64 degrees; the
    farm at 5 Hz 24.2 -> 20.7 cm, 1.83 -> 1.16 degrees. With a 5 degree turn limit on all
    11 surveys tried (2, 5, 10 Hz): 5 Hz 0.9-1.4 -> 0.4-0.6 degrees but for the farm, 2 Hz
    unchanged within noise (a frame is about a keyframe apart already); 0.5 m measured
    like 0.3 m, 0.15 m kept about half the gain at 5 Hz."""
    keyframe_deg: float = 3.0
    """The rotation estimate errs more on larger turns: keyframes 5 degrees apart made
    the farm's U-turns worse than no keyframes (30 s: 2.3 degrees against 1.8), 1 degree
    lost the gain (1.6); 2-3 degrees measured best (farm 0.9-1.2, 10 Hz 1.0-0.7)."""
    keyframe_s: float = 1.0
    """At 0.3-0.5 m/s the distance comes first; a boat that holds still renews its
    keyframe each second (longer was not tried)."""
    coast_accel_sigma_mps2: float = 0.1
    """Without the gyro between two frames (the autopilot link silent, an IMU gap), the
    filter dead-reckons at a constant heading and its relative motion says nothing of a
    turn: the motion expected is then the chain's own, its velocity and turn rate over
    the last ``coast_rate_window_s`` held, and this is the sigma of the boat's
    acceleration such a prediction does not know of (waves, thrust), m/s^2. Measured with
    the navigation up (every accepted registration against the chain's prediction from
    the steps before it, quadrats seeds 5, 1, 7 at 2, 5 and 10 Hz, 2,779 registrations):
    the acceleration the residual implies is 0.04-0.06 m/s^2 at the median, 0.17-0.22 at
    the 99th percentile and 0.22-0.25 at the 99.9th, alike at every rate; the gates take
    ``coast_gate_sigmas`` of it."""
    coast_yaw_accel_sigma_rps2: float = math.radians(5.0)
    """Likewise the turn rate's change, rad/s^2: 1.6-2.3 degrees/s^2 at the median,
    8.7-10.8 at the 99th percentile, 13.6-14.2 at the 99.9th (a turn's start and end)."""
    coast_rate_window_s: float = 1.0
    """The chain's velocity and turn rate are its registered steps' over this long (the
    last step alone: one registration gone wrong set the rate, the frames after it were
    refused against it, and the chain restarted a metre off)."""
    coast_speed_sigma_mps: float = COAST_SPEED_SIGMA_MPS
    """When the chain has no recent velocity either (it restarted inside the gap)."""
    coast_yaw_rate_sigma_rps: float = COAST_YAW_RATE_SIGMA_RPS
    coast_gate_sigmas: float = 3.0
    """Without the gyro the gates are tau_p and tau_a widened in quadrature by this many
    sigmas of the prediction's error above."""


@dataclass
class FrameOutcome:
    """What happened to one frame. ``edge`` links it to the previous accepted frame
    (vehicle frame); ``measured`` is the registration itself, from the frame it was
    registered against (the keyframe, or the previous accepted frame) to this one;
    ``reason`` says why it was rejected, "" when accepted."""

    index: int
    time: float
    accepted: bool
    reason: str = ""
    edge: Edge | None = None
    measured: Edge | None = None
    registration: Registration | None = None
    delta_p_m: float = math.nan
    delta_a_deg: float = math.nan


_ORIGIN = np.zeros(3)


@dataclass(slots=True)
class _Kept:
    """An accepted frame as the registration keeps it: its frame on the registration grid,
    prepared for the registrar (``FmtRegistrar.prepare``) when a registration here first
    needs it (one computed ahead, elsewhere, does not)."""

    index: int
    time: float
    prior: Array
    coarse: npt.NDArray[np.float32]
    coarse_mask: npt.NDArray[np.bool_] | None
    registrar: FmtRegistrar
    odometry: Array | None
    gyro: int | None = 0
    """Gyro epoch (``NavFilter.gyro_epoch_at``; None without a fresh IMU sample)."""
    _prepared: PreparedFrame | None = None

    @property
    def prepared(self) -> PreparedFrame:
        if self._prepared is None:
            self._prepared = self.registrar.prepare(self.coarse, self.coarse_mask)
        return self._prepared


@dataclass(frozen=True, slots=True)
class PairJob:
    """A registration of two frames on the registration grid, as ``LocalRegistration``
    asks for it (``FmtRegistrar.register`` of the two prepared frames): a pure task
    (``mapping.tasks``), its answer the same wherever it runs."""

    earlier: int
    later: int
    earlier_coarse: npt.NDArray[np.float32]
    earlier_mask: npt.NDArray[np.bool_] | None
    later_coarse: npt.NDArray[np.float32]
    later_mask: npt.NDArray[np.bool_] | None
    expected: RelativePose
    prior_sigma_m: float
    yaw_known: bool
    grid: SonarGrid
    fan: npt.NDArray[np.bool_]
    fmt: FmtParams


_PREPARED: OrderedDict[tuple[object, ...], PreparedFrame] = OrderedDict()
_PREPARED_BY: list[FmtRegistrar | None] = [None]
PREPARED_KEPT = 6
"""Frames a process keeps prepared for ``register_pair_job`` (a few MB each): a frame
registered as the later of a pair is the earlier one of the pairs after it once it is
their keyframe, and a keyframe serves several frames in a row."""


def _prepared(
    registrar: FmtRegistrar,
    index: int,
    coarse: npt.NDArray[np.float32],
    mask: npt.NDArray[np.bool_] | None,
) -> PreparedFrame:
    """Frame ``index`` prepared, from this process's last few when the same frame (its
    pixels' digest) on the same registrar was prepared here before."""
    digest = hashlib.blake2b(np.ascontiguousarray(coarse).data, digest_size=16)
    if mask is not None:
        digest.update(np.ascontiguousarray(mask).data)
    if _PREPARED_BY[0] is not registrar:  # another grid, fan or settings
        _PREPARED.clear()
        _PREPARED_BY[0] = registrar
    key = (index, coarse.shape, digest.digest())
    prepared = _PREPARED.get(key)
    if prepared is not None:
        _PREPARED.move_to_end(key)
        return prepared
    prepared = registrar.prepare(coarse, mask)
    _PREPARED[key] = prepared
    while len(_PREPARED) > PREPARED_KEPT:
        _PREPARED.popitem(last=False)
    return prepared


def register_pair_job(job: PairJob) -> Registration:
    """The registration ``job`` asks for (``PairJob``), on a registrar this process keeps
    for the grid; the frames prepared once in this process serve the pairs after (the
    answer is the same: preparing a frame is a pure function of it)."""
    registrar = cached_registrar(job.grid, job.fan, job.fmt)
    return registrar.register(
        _prepared(registrar, job.earlier, job.earlier_coarse, job.earlier_mask),
        _prepared(registrar, job.later, job.later_coarse, job.later_mask),
        job.expected,
        prior_sigma_m=job.prior_sigma_m,
        yaw_known=job.yaw_known,
    )


@dataclass(frozen=True, slots=True)
class PrepareJob:
    """A ping to preprocess as ``LocalRegistration.frame`` would (``prepare_frame_job``),
    with what that carries from the pings before it: the fan, the histogram reference the
    first frame set, and the ping's attitude. A pure task (``mapping.tasks``): its answer
    depends on the job alone, the same frame to the bit wherever it runs."""

    ping: Ping
    fan: FanGeometry
    tilt_deg: float
    params: PreprocessParams
    attitude: Attitude | None
    reference_cdf: npt.NDArray[np.float64] | None


_PREPROCESSORS: list[tuple[tuple[object, ...], Preprocessor]] = []
PREPROCESSORS_KEPT = 2
"""Preprocessors a process keeps for ``prepare_frame_job`` (one per sonar geometry)."""


def prepare_frame_job(job: PrepareJob) -> SonarFrame:
    """The frame ``job`` asks for (``PrepareJob``), on a preprocessor this process keeps
    for the fan, settings and reference (its tables built once)."""
    reference = job.reference_cdf
    key = (job.fan, job.tilt_deg, job.params, None if reference is None else reference.tobytes())
    preprocessor = next((kept for known, kept in _PREPROCESSORS if known == key), None)
    if preprocessor is None:
        preprocessor = Preprocessor(job.fan, job.tilt_deg, job.params, reference_cdf=reference)
        _PREPROCESSORS.insert(0, (key, preprocessor))
        del _PREPROCESSORS[PREPROCESSORS_KEPT:]
    return preprocessor(job.ping.image, job.attitude, job.ping.time)


def prepared_frames(
    pings: Iterable[tuple[int, Ping]], local: LocalRegistration, pool: TaskPool | None
) -> Iterator[tuple[int, Ping, SonarFrame | TaskHandle[SonarFrame], Preprocessor]]:
    """The pings (index, ping) with their frames, in order: preprocessed in ``pool``
    (``prepare_frame_job``, a few pings ahead) where ``local.prepare_job`` says the pool
    gives the frame ``local.frame`` would, else here (the first, a new geometry, a flat
    field; the pings before are then already handed out with their own tables). Each comes
    with the preprocessor whose grid it is on. ``local`` only preprocesses (no chain)."""
    lead = 2 * pool.workers + 2 if pool is not None else 0
    out: deque[tuple[int, Ping, SonarFrame | TaskHandle[SonarFrame], Preprocessor]] = deque()
    for index, ping in pings:
        job = local.prepare_job(ping) if pool is not None else None
        got: SonarFrame | TaskHandle[SonarFrame]
        if job is not None:
            assert pool is not None
            got = pool.submit(prepare_frame_job, job)
        else:
            got = local.frame(ping)
        assert local.preprocessor is not None
        out.append((index, ping, got, local.preprocessor))
        while len(out) > lead:
            yield out.popleft()
    yield from out


PairLookup = Callable[[int, int, RelativePose, float, bool], "Registration | None"]
"""What ``LocalRegistration.ahead`` answers: the registration of frame ``later`` against
``earlier`` with this prior, sigma and ``yaw_known`` when it was computed ahead, else None."""


@dataclass
class LocalRegistration:
    """Streaming local registration: feed frames in order with their EKF priors."""

    mount: SonarMount
    preprocess: PreprocessParams = field(default_factory=PreprocessParams)
    fmt: FmtParams = field(default_factory=FmtParams)
    params: RegistrationParams = field(default_factory=RegistrationParams)
    attitude: Callable[[float], Attitude | None] | None = None
    """The boat's roll and pitch at a ping's stamp (None: project every ping level)."""
    yaw_from_gyro: bool = False
    """Between frames the filter's gyro joins (one gyro epoch), take the turn from it and
    search no rotation (``FmtRegistrar.register``'s ``yaw_known``): the live engine's
    choice (``StreamingParams.live_yaw_from_gyro``); the survey-end pass searches."""

    def __post_init__(self) -> None:
        self.preprocessor: Preprocessor | None = None
        self.registrar: FmtRegistrar | None = None
        self._fine: FmtRegistrar | None = None
        self._fan: FanGeometry | None = None
        self._fan_of: tuple[npt.NDArray[np.float64], int, float] | None = None
        """The last ping's bearings, range count and resolution, whose ``_fan`` it is."""
        self._last: _Kept | None = None
        self._key: _Kept | None = None
        self._from_key: RelativePose | None = None
        """The last accepted frame from the keyframe (vehicle frame); None when it is the
        keyframe."""
        self._steps: deque[tuple[float, float, float, float, float]] = deque()
        """The chain's registered steps (from time, to time, forward, starboard, yaw) of
        the last ``coast_rate_window_s``: its velocity and turn rate."""
        self.ahead: PairLookup | None = None
        """Registrations computed ahead (``mapping.pipeline``'s survey-end pass hands them
        to worker processes): asked first, computed here when it has none."""
        self._rate: tuple[tuple[float, float, float], float, float] | None = None
        """The chain's velocity and turn rate (vehicle frame: forward, starboard m/s, yaw
        rad/s), the time of the last step it was measured with, and the span it covers;
        kept through a chain restart."""

    def frame(self, ping: Ping) -> SonarFrame:
        """Preprocess one ping; tables are rebuilt only when the sonar's geometry changes."""
        if self._fan is not None and self._same_geometry(ping):
            fan = self._fan  # the same geometry as the last ping's (0.5 ms a ping to rebuild)
        else:
            fan = FanGeometry.of(
                ping.bearings_rad,
                ping.n_ranges,
                ping.range_resolution_m,
                self.mount.altitude_m,
                self.mount.tilt_rad,
                lever_arm_m=(self.mount.forward_m, self.mount.starboard_m, self.mount.down_m),
                mount_yaw_rad=self.mount.yaw_rad,
            )
            self._fan_of = (
                np.array(ping.bearings_rad, np.float64),
                ping.n_ranges,
                ping.range_resolution_m,
            )
        if self.preprocessor is None or fan != self._fan:
            reference = self.preprocessor.reference_cdf if self.preprocessor else None
            self.preprocessor = Preprocessor(
                fan, math.degrees(self.mount.tilt_rad), self.preprocess, reference_cdf=reference
            )
            self.registrar = FmtRegistrar(
                self.preprocessor.registration_grid,
                self.preprocessor.registration_tables.mask,
                self.fmt,
            )
            self._fine = None
            self._fan = fan
            self._last = self._key = None  # a new geometry cannot be registered against the old
        attitude = self.attitude(ping.time) if self.attitude is not None else None
        return self.preprocessor(ping.image, attitude, ping.time)

    def prepare_job(self, ping: Ping) -> PrepareJob | None:
        """The job that preprocesses ``ping`` elsewhere (``prepare_frame_job``) to the same
        frame that ``frame(ping)`` would give here, or None where only this object can: a
        ping of another geometry than the last one preprocessed here (its tables, a new
        chain), the first frame (it sets the histogram reference), or a flat field (a
        running mean over every ping, kept here)."""
        preprocessor = self.preprocessor
        if (
            preprocessor is None
            or self._fan is None
            or self.preprocess.flat_field_s > 0
            or (self.preprocess.histogram_match and preprocessor.reference_cdf is None)
            or not self._same_geometry(ping)
        ):
            return None
        attitude = self.attitude(ping.time) if self.attitude is not None else None
        return PrepareJob(
            ping,
            self._fan,
            preprocessor.tilt_deg,
            self.preprocess,
            attitude,
            preprocessor.reference_cdf,
        )

    def same_geometry(self, ping: Ping) -> bool:
        """The ping's fan is the last preprocessed one's (no new tables, no new chain)."""
        return self._same_geometry(ping)

    def _same_geometry(self, ping: Ping) -> bool:
        last = self._fan_of
        return (
            last is not None
            and last[1] == ping.n_ranges
            and last[2] == ping.range_resolution_m
            and np.array_equal(last[0], ping.bearings_rad)
        )

    def observe(self, ping: Ping) -> None:
        """A ping skipped (not preprocessed) still enters the preprocessor's flat field
        (``Preprocessor.observe``); the first ping, or one of a new geometry, sets the
        preprocessor up."""
        if self.preprocessor is None or not self._same_geometry(ping):
            self.frame(ping)
            return
        attitude = self.attitude(ping.time) if self.attitude is not None else None
        self.preprocessor.observe(ping.image, attitude, ping.time)

    @property
    def fine_registrar(self) -> FmtRegistrar:
        """A registrar on the blending grid, for the few registrations that need every
        bit of detail (loop closures between lanes)."""
        if self._fine is None:
            assert self.preprocessor is not None and self.preprocessor.grid is not None
            self._fine = FmtRegistrar(
                self.preprocessor.grid, self.preprocessor.tables.mask, self.fmt
            )
        return self._fine

    def register(
        self,
        index: int,
        time: float,
        frame: SonarFrame,
        prior: Array | None,
        odometry: Array | None = None,
        gyro_epoch: int | None = 0,
    ) -> FrameOutcome:
        """Register a preprocessed frame against the keyframe (against the last accepted
        frame when the keyframe's registration is refused) and validate it; the edge is
        from the last accepted frame, composed through the keyframe. The outcome's
        ``registration`` (its covariance, score, deltas) is the keyframe pair's.

        prior: the EKF vehicle pose (x, y, heading) at the frame time, or None when the
        filter has not started (the frame is then rejected: it cannot be placed).
        odometry: the filter's dead-reckoned path at the frame time (``NavFilter.odometry``):
        when given, the expected relative motion comes from it rather than from the
        priors, which a live filter's updates make jump (a smoothed estimate does not).
        gyro_epoch: the filter's gyro epoch at the frame time (``NavFilter.gyro_epoch_at``,
        ``navigation.gyro_epochs``; None: no fresh IMU sample). Between frames of
        different epochs the filter knows nothing of a turn, and the registration is
        checked against the chain's own motion instead (``RegistrationParams.coast_*``).
        """
        if prior is None or not np.all(np.isfinite(prior)):
            return FrameOutcome(index, time, False, "no navigation prior")
        assert self.registrar is not None
        here = _Kept(
            index, time, prior, frame.coarse, frame.coarse_mask, self.registrar, odometry,
            gyro_epoch,
        )  # fmt: skip
        last, key = self._last, self._key
        if last is None or key is None or time - last.time > self.params.max_gap_s:
            # The first frame, or a chain restart: kept on its prior alone (the rate
            # measured before stays, for the frames after).
            self._steps.clear()
            self._last = self._key = here
            self._from_key = None
            return FrameOutcome(index, time, True, "")
        from_key = self._from_key
        outcome = self._register(key, here)
        if not outcome.accepted and key is not last:
            # Turned or moved too far from the keyframe: the last frame is nearer.
            key, from_key = last, None
            outcome = self._register(key, here)
        if not outcome.accepted:
            return outcome
        assert outcome.registration is not None
        measured = self.mount.vehicle_relative(outcome.registration.relative)
        step = (
            measured
            if from_key is None
            else relative_pose(compose(_ORIGIN, from_key), compose(_ORIGIN, measured))
        )
        outcome.edge = Edge(last.index, index, step.forward_m, step.starboard_m, step.yaw_rad)
        outcome.measured = Edge(
            key.index, index, measured.forward_m, measured.starboard_m, measured.yaw_rad
        )
        self._measure_rate(last, here, step)
        p = self.params
        if (
            p.keyframe_m <= 0
            or math.hypot(measured.forward_m, measured.starboard_m) >= p.keyframe_m
            or abs(math.degrees(measured.yaw_rad)) >= p.keyframe_deg
            or time - key.time >= p.keyframe_s
        ):
            self._key, self._from_key = here, None
        else:
            self._key, self._from_key = key, measured
        self._last = here
        return outcome

    def _register(self, reference: _Kept, here: _Kept) -> FrameOutcome:
        """Register ``here`` against ``reference`` and validate it against the filter's
        relative motion; the outcome is accepted or says why not (no edge yet)."""
        assert self.registrar is not None
        p = self.params
        if here.odometry is not None and reference.odometry is not None:
            dx, dy, dyaw = here.odometry - reference.odometry
            s, c = math.sin(reference.prior[2]), math.cos(reference.prior[2])
            expected_vehicle = RelativePose(s * dx + c * dy, c * dx - s * dy, float(dyaw))
        else:
            expected_vehicle = relative_pose(reference.prior, here.prior)
        tau_p, tau_a = p.tau_p_m, p.tau_a_deg
        prior_sigma = p.tau_p_m
        if here.gyro is None or here.gyro != reference.gyro:
            expected_vehicle, sigma_p, sigma_a = self._coasting(reference, here, expected_vehicle)
            tau_p = math.hypot(tau_p, p.coast_gate_sigmas * sigma_p)
            tau_a = math.hypot(tau_a, p.coast_gate_sigmas * math.degrees(sigma_a))
            prior_sigma = math.hypot(prior_sigma, sigma_p)
        expected_sonar = self.mount.sonar_relative(expected_vehicle)
        # The whole correlation surface is searched; the prediction weighs its peaks.
        gyro = here.gyro is not None and here.gyro == reference.gyro
        yaw_known = self.yaw_from_gyro and gyro
        reg = None
        if self.ahead is not None:
            reg = self.ahead(reference.index, here.index, expected_sonar, prior_sigma, yaw_known)
        if reg is None:
            reg = self.registrar.register(
                reference.prepared,
                here.prepared,
                expected_sonar,
                prior_sigma_m=prior_sigma,
                yaw_known=yaw_known,
            )
        measured = self.mount.vehicle_relative(reg.relative)
        delta_p = math.hypot(
            measured.forward_m - expected_vehicle.forward_m,
            measured.starboard_m - expected_vehicle.starboard_m,
        )
        delta_a = abs(math.degrees(wrap_pi(measured.yaw_rad - expected_vehicle.yaw_rad)))
        outcome = FrameOutcome(
            here.index, here.time, False, registration=reg, delta_p_m=delta_p, delta_a_deg=delta_a
        )
        if delta_p > tau_p:
            outcome.reason = "translation disagrees with EKF (tau_p)"
        elif delta_a > tau_a:
            outcome.reason = "rotation disagrees with EKF (tau_a)"
        elif reg.score < p.min_score:
            outcome.reason = "low similarity score"
        elif reg.overlap < p.min_overlap:
            outcome.reason = "too little overlap"
        else:
            outcome.accepted = True
        return outcome

    @property
    def rate(self) -> tuple[tuple[float, float, float], float, float] | None:
        """The chain's velocity and turn rate (forward, starboard m/s, yaw rad/s), the
        time of the last step it was measured with and the span it covers; None before
        the first registered step."""
        return self._rate

    @property
    def key_index(self) -> int | None:
        """The frame the next registration is tried against first (the keyframe)."""
        return None if self._key is None else self._key.index

    @property
    def last_index(self) -> int | None:
        """The last frame accepted (the chain goes on from it)."""
        return None if self._last is None else self._last.index

    def plain_prior(self, earlier: Array, later: Array) -> tuple[RelativePose, float]:
        """The prior (sonar frame) and translation sigma a registration of a frame at pose
        ``later`` against one at ``earlier`` asks for where the gyro joins them and
        neither has odometry (``_register``: the survey-end pass's, from the priors)."""
        return self.mount.sonar_relative(relative_pose(earlier, later)), self.params.tau_p_m

    def chain_rate(self, time: float, max_age_s: float) -> tuple[float, float, float] | None:
        """The chain's velocity and turn rate (vehicle frame: forward, starboard m/s, yaw
        rad/s) when last measured at most ``max_age_s`` before ``time``."""
        if self._rate is None or time - self._rate[1] > max_age_s:
            return None
        return self._rate[0]

    def _measure_rate(self, last: _Kept, here: _Kept, step: RelativePose) -> None:
        """The chain's velocity and turn rate over its registered steps of the last
        ``coast_rate_window_s`` (several steps: one registration gone wrong moves it by a
        fraction, not all of it)."""
        if here.time <= last.time:
            return
        steps = self._steps
        steps.append((last.time, here.time, step.forward_m, step.starboard_m, step.yaw_rad))
        while len(steps) > 1 and here.time - steps[0][0] > self.params.coast_rate_window_s:
            steps.popleft()
        span = sum(b - a for a, b, *_ in steps)
        rate = (
            sum(f for _, _, f, _, _ in steps) / span,
            sum(st for _, _, _, st, _ in steps) / span,
            sum(y for *_, y in steps) / span,
        )
        self._rate = (rate, here.time, here.time - steps[0][0])

    def _coasting(
        self, reference: _Kept, here: _Kept, held: RelativePose
    ) -> tuple[RelativePose, float, float]:
        """The motion expected from ``reference`` to ``here`` without the gyro, and the
        sigmas of its error (metres per axis, radians): the chain's last velocity and turn
        rate held (an arc) when it has them, else the filter's ``held`` motion, whose
        turn and speed may then be anything a boat does."""
        p = self.params
        dt = max(here.time - reference.time, 0.0)
        fallback = (held, p.coast_speed_sigma_mps * dt, p.coast_yaw_rate_sigma_rps * dt)
        if self._rate is None:
            return fallback
        # From a keyframe, the way to the last frame is registered already: only the rest
        # is predicted.
        start, through = reference, None
        last = self._last
        if reference is self._key and last is not None and last is not reference:
            start, through = last, self._from_key
        dt = max(here.time - start.time, 0.0)
        (forward_v, starboard_v, yaw_rate), measured_at, span = self._rate
        # Measured over ``span`` up to ``measured_at``: a change of velocity since the
        # middle of that shows over the whole of ``dt``.
        lever = dt * (max(start.time - measured_at, 0.0) + 0.5 * (span + dt))
        sigma_p = p.coast_accel_sigma_mps2 * lever
        if sigma_p >= fallback[1]:
            return fallback  # too old to say more than a boat's speed does
        # The arc at a constant body velocity and turn rate: its chord, turned by half the
        # turn and shortened by sinc(half the turn).
        half = 0.5 * yaw_rate * dt
        chord = dt * (math.sin(half) / half if abs(half) > 1e-9 else 1.0)
        s, c = math.sin(half), math.cos(half)
        expected = RelativePose(
            (forward_v * c - starboard_v * s) * chord,
            (forward_v * s + starboard_v * c) * chord,
            yaw_rate * dt,
        )
        if through is not None:
            expected = relative_pose(_ORIGIN, compose(compose(_ORIGIN, through), expected))
        return expected, sigma_p, p.coast_yaw_accel_sigma_rps2 * lever
