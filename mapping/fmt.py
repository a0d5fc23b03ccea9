"""Fourier–Mellin registration of consecutive Cartesian sonar frames.

Rotation comes first, coarsely, from the log-polar resampled magnitude spectra (rotation
of an image rotates its magnitude spectrum about DC, whatever the translation; Reddy &
Chatterji 1996, doi:10.1109/83.506761). The later frame is turned by it, exactly, by
Fourier shears, and translation found by phase correlation (Kuglin & Hines 1975), whose
peak is searched over the whole surface: a navigation prior only weighs the peaks (a
Gaussian log-likelihood), it never hides one. The rotation is then measured from the
motion itself: the earlier fan is split into sectors by bearing, each sector's own
correlation peak near the chosen one gives a point correspondence, and a weighted
least-squares rigid fit of those gives the pose and its covariance; the later frame is
turned again (secant steps) until the fit no longer moves. Its fixed point does not
depend on where it starts, so neither the prior's yaw nor the spectra's (which the
fan's static patterns pull towards zero) leak into the answer.

Each peak's sub-pixel position comes from the quadratic through the logarithm of the
surface at the peak (exact for the Gaussian peak the low-pass makes), its covariance
from first-order perturbation of the peak condition (grad = 0): s^2 H^-1 G H^-1 for a
surface of Hessian H at the peak and noise of standard deviation s with gradient
covariance s^2 G (G from the low-pass); the accuracy of a correlation peak is its width
over its SNR (Foroosh et al. 2002, doi:10.1109/83.988953). That first-order figure
misses errors that grow with how differently the two frames see the seabed, so the
rigid fit's covariance is scaled by the sectors' own disagreement (their chi-square per
degree of freedom, a Birge ratio) and by a factor calibrated on pairs of known motion.

FLS frames are fans: the fan edge is static in the sonar frame and would pull every
estimate towards "no motion", so each frame is multiplied by a Hamming-tapered fan
window (Hurtós et al. 2015, doi:10.1002/rob.21516) and the lowest frequencies, where the
window's own spectrum lives, are left out of the coarse rotation. This is the paper's
local registration (Zhang et al., Sec. III.E, Algorithm 1 lines 1-11).

Frames: a Cartesian sonar frame is an image whose rows run from far (row 0) to near and
whose columns run from port to starboard; ``SonarGrid`` says where the sonar sits in it.
Results are metric relative poses in the sonar frame of the *earlier* image: forward and
starboard metres, and the yaw change in radians, clockwise (to starboard) positive;
covariances are 3 x 3 over (forward m, starboard m, yaw rad) in that frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
import scipy.fft

from mapping.grid import SonarGrid
from mapping.se2 import RelativePose

FloatImage = npt.NDArray[np.float32]
Matrix = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class FmtParams:
    """Tuning of the registration.

    max_rotation_deg: largest yaw change searched between two frames (around the prior's).
    n_angles: angular samples of the log-polar spectrum over 180 degrees.
    n_radii: radial (log) samples. band: the spectrum band used for rotation, as fractions
    of the Nyquist radius (low end skips the window's spectrum, high end the pixel noise).
    taper_px: width of the Hamming taper at the fan edge (pixels).
    lowpass_sigma: Gaussian weight on the phase-correlation spectrum, cycles per pixel.
    sectors: bearing sectors of the earlier fan whose own peaks give the rotation.
    sector_blend_deg: width of the smooth hand-over between neighbouring sectors.
    refine_tolerance_deg: the later frame is turned again while the fit moves the angle
    by more than this (the fit is exact to first order in the residual turn) and more
    than ``refine_tolerance_sigmas`` of the fit's own yaw standard deviation.
    refine_tolerance_sigmas: a turn within the fit's own yaw uncertainty is not made:
    what it would change is (1 - gain) x the turn, and the fit's gain is 1 but for the
    smear of a residual rotation (a 0.04 degree one moves a 5 m fan's edge by 3.5 mm, a
    sixth of a 2 cm pixel; the fit's yaw sigma is 0.04 degrees at the median on quadrats
    seed 8 at 10 Hz). On the test bed's 200 pairs of known motion: 1.85 turns a pair to
    0.02 degrees, 1.34 to one sigma, the errors the same (2.25 / 3.77 mm, 65.6 mdeg
    against 2.24 / 3.78 mm, 65.2); single-stage lanes on 12 surveys of the matrix (one of
    each condition, the 2 Hz ones): median 3.62 -> 3.76 cm, worst 9.1 -> 9.3. Off (0) by
    default: the whole matrix at 1 (session 28) found the sloping shore, whose 12-survey
    check had one survey, twice as bad (shore seed 3 9.3 -> 20.0 cm, seed 2 14.8 -> 19.0),
    the pairs' gain there not 1: the fit's answer after a turn it did not make is not
    what the turn would have given.
    refine_iterations: most turns of the later frame.
    prior_trust_deg: the iteration starts at the prior's yaw when the spectra agree with
    it to this, at theirs otherwise.
    nms_radius_px: peaks closer than this (pixels) are one peak (non-maximum suppression).
    candidates: peaks weighed against the prior (the highest ones).
    min_sector_snr: a sector whose peak is lower than this over its surface's noise is
    left out of the fit (a sector that sees nothing of the other frame).
    covariance_scale: calibration of the covariance (a variance factor), measured on
    pairs of known motion (tests/mapping/test_fmt_covariance.py).
    covariance_prior_dof: weight, in degrees of freedom, of 1 against the sectors'
    chi-square per degree of freedom in the factor that scales the covariance.
    fallback_yaw_sigma_deg: yaw sigma when fewer than two sectors have a peak.
    known_yaw_iterations: turns of the later frame when the prior's yaw is known (a
    gyro's: ``register``'s ``yaw_known``): no spectral rotation search, the iteration
    starts at the prior's yaw. 1: the sectors' fit at that turn is the answer (exact to
    first order in the gyro's error, hundredths of a degree over a ping).
    """

    max_rotation_deg: float = 8.0
    n_angles: int = 720
    n_radii: int = 96
    band: tuple[float, float] = (0.04, 0.7)
    taper_px: int = 12
    lowpass_sigma: float = 0.12
    sectors: int = 4
    sector_blend_deg: float = 12.0
    refine_tolerance_deg: float = 0.02
    refine_tolerance_sigmas: float = 0.0
    refine_iterations: int = 4
    prior_trust_deg: float = 0.5
    nms_radius_px: int = 3
    candidates: int = 8
    min_sector_snr: float = 4.0
    covariance_scale: float = 2.0
    covariance_prior_dof: float = 2.0
    fallback_yaw_sigma_deg: float = 1.0
    known_yaw_iterations: int = 1


@dataclass(frozen=True, slots=True)
class Hypothesis:
    """One distinct correlation peak of a pair, as a motion.

    relative: the later frame's pose in the earlier frame for this peak (its own sector
    fit, after the rotation refinement of the best). covariance: 3 x 3 (forward m,
    starboard m, yaw rad). peak: its phase-correlation height. log_likelihood: how it
    ranks, up to a constant: peak against the surface's noise, plus the prior's Gaussian
    log-density when a prior sigma was given. score, overlap: as in ``Registration``
    (computed for every hypothesis only when more than one is asked for).
    """

    relative: RelativePose
    covariance: Matrix
    peak: float
    log_likelihood: float
    score: float
    overlap: float


@dataclass(frozen=True, slots=True)
class Registration:
    """A registration result.

    relative: the later frame's pose in the earlier frame (metric, see RelativePose).
    score: normalised cross-correlation of the overlapping fan after alignment, in
    [-1, 1] (the paper's similarity score, SS). peak: phase-correlation peak height (a
    confidence in [0, 1]). overlap: fraction of the earlier fan covered by the later one.
    covariance: 3 x 3 over (forward m, starboard m, yaw rad) in the earlier sonar frame,
    from the correlation surface (None when nothing was registered). hypotheses: the
    distinct peaks asked for (``n_hypotheses``), best first; the first is this result.
    """

    relative: RelativePose
    score: float
    peak: float
    overlap: float
    covariance: Matrix | None = None
    hypotheses: tuple[Hypothesis, ...] = ()


@dataclass(slots=True)
class PreparedFrame:
    """What registration keeps of one frame, computed once and reused for both pairs it
    belongs to (as the later frame, then as the earlier one)."""

    windowed: FloatImage  # zero-mean, tapered, padded to the translation transform
    image: FloatImage  # unpadded, as given
    spectrum: npt.NDArray[np.complex64]  # rfft2 of windowed
    polar_spectrum: npt.NDArray[np.complex64] | None = None
    """rfft of the log-polar log-magnitude spectrum, once a rotation search asks for it
    (``FmtRegistrar.rotation``): a pair whose turn the gyro gives never does."""
    window: FloatImage | None = None  # unpadded taper, where the frame has data
    sectors: _Sectors | None = None  # when it is the earlier frame of a pair
    rows_spectrum: npt.NDArray[np.complex64] | None = None
    """rfft of windowed's rows: the first step of its spectrum and of every turn of it
    (``FmtRegistrar._rotated_spectrum``)."""


@dataclass(frozen=True, slots=True)
class _Peak:
    """A correlation peak: sub-pixel shift (x, y) of the later frame in pixels (signed),
    its height and the covariance of (x, y) (pixels squared)."""

    x: float
    y: float
    height: float
    covariance: Matrix


@dataclass(frozen=True, slots=True)
class _Sectors:
    """An earlier frame's bearing sectors: their spectra (they add up to the frame's) and
    their energy, (frame - mean)^2 x taper^2 x sector weight, on a grid a quarter of
    the frame's (where sector centroids are taken, weighted by the overlap)."""

    spectra: npt.NDArray[np.complex64]
    energy: FloatImage


@dataclass(frozen=True, slots=True)
class _Surface:
    """A phase-correlation surface, the standard deviation of its noise and the
    covariance of the noise's gradient (per pixel squared), both measured away from its
    highest peak."""

    values: FloatImage
    noise: float
    gradient_noise: Matrix


@dataclass(frozen=True, slots=True)
class _Fit:
    relative: RelativePose
    covariance: Matrix
    peak: _Peak


def hamming_taper(mask: npt.NDArray[np.bool_], taper_px: int) -> FloatImage:
    """Window that is 1 deep inside ``mask`` and falls along a Hamming half-window over
    ``taper_px`` pixels to the mask edge, 0 outside (the paper's Sec. III.C step 5)."""
    inside = mask.astype(np.uint8)
    distance = cv2.distanceTransform(inside, cv2.DIST_L2, 5)
    ramp = np.clip(distance / max(taper_px, 1), 0.0, 1.0)
    window = 0.54 - 0.46 * np.cos(np.pi * ramp)
    window[~mask] = 0.0
    return window.astype(np.float32)


def parabolic_offset(left: float, centre: float, right: float) -> float:
    """Sub-sample offset of a peak from three samples around it (in [-0.5, 0.5])."""
    denominator = left - 2.0 * centre + right
    if denominator >= 0.0 or not math.isfinite(denominator):
        return 0.0
    return float(np.clip(0.5 * (left - right) / denominator, -0.5, 0.5))


def _phase_ramp(first: npt.ArrayLike, second: npt.ArrayLike) -> npt.NDArray[np.complex64]:
    """exp(i first[:, None] second[None, :]) in single precision."""
    phase = np.outer(np.asarray(first, np.float32), np.asarray(second, np.float32))
    ramp = np.empty(phase.shape, np.complex64)
    ramp.real = np.cos(phase)
    ramp.imag = np.sin(phase)
    return ramp


def _inverse2(m: Matrix) -> Matrix:
    """Inverse of a 2 x 2 matrix."""
    det = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
    return np.array([[m[1, 1], -m[0, 1]], [-m[1, 0], m[0, 0]]]) / det


def _compose_jacobian(residual: RelativePose, prior: RelativePose) -> Matrix:
    """d(residual o prior)/d(residual) for (forward, starboard, yaw): composing on the
    right moves only the later frame's origin, by R(yaw_residual) t_prior."""
    c, s = math.cos(residual.yaw_rad), math.sin(residual.yaw_rad)
    f, st = prior.forward_m, prior.starboard_m
    jacobian = np.eye(3)
    jacobian[0:2, 2] = (-s * f - c * st, c * f - s * st)
    return jacobian


class FmtRegistrar:
    """Registers Cartesian sonar frames of one ``SonarGrid`` with a fixed fan ``mask``.

    Everything that depends only on the geometry (window, padding, log-polar sampling
    maps, band weights, sectors) is computed once here, so registering a pair costs a few
    FFTs.
    """

    def __init__(
        self, grid: SonarGrid, mask: npt.NDArray[np.bool_], params: FmtParams | None = None
    ) -> None:
        if mask.shape != grid.shape:
            raise ValueError(f"mask shape {mask.shape} differs from grid shape {grid.shape}")
        self.grid = grid
        self.params = params or FmtParams()
        self.mask = mask.astype(bool)
        self._mask_u8 = self.mask.astype(np.uint8)
        self._mask_f32 = self.mask.astype(np.float32)
        self._mask_count = int(self.mask.sum())
        self.window = hamming_taper(self.mask, self.params.taper_px)
        rows, cols = grid.shape
        # Rotation: a square transform, since rotating an image rotates its spectrum only
        # when both frequency axes have the same scale.
        self.n = int(cv2.getOptimalDFTSize(max(rows, cols)))
        self.row0 = (self.n - rows) // 2
        self.col0 = (self.n - cols) // 2
        self._build_polar_maps()
        # Translation: a transform just larger than the frame (fans are twice as wide as
        # deep, so this is half the square's work), with a margin for what a few degrees
        # of de-rotation move past the frame's edge.
        turn = math.sin(math.radians(self.params.max_rotation_deg))
        margin = math.ceil(0.5 * max(rows, cols) * turn) + 4
        self.shape_t = (
            int(cv2.getOptimalDFTSize(rows + 2 * margin)),
            int(cv2.getOptimalDFTSize(cols + 2 * margin)),
        )
        self.row0_t = (self.shape_t[0] - rows) // 2
        self.col0_t = (self.shape_t[1] - cols) // 2
        self._pad = np.array([[1.0, 0.0, self.col0_t], [0.0, 1.0, self.row0_t], [0.0, 0.0, 1.0]])
        self._unpad = np.linalg.inv(self._pad)
        # (x, y) of the rotation centre in the translation transform's padded image.
        self.centre = ((self.shape_t[1] - 1) / 2.0, (self.shape_t[0] - 1) / 2.0)
        fy = np.fft.fftfreq(self.shape_t[0])[:, None]
        fx = np.fft.rfftfreq(self.shape_t[1])[None, :]
        sigma = self.params.lowpass_sigma
        f2 = fx * fx + fy * fy
        self._lowpass = np.exp(-f2 / (2 * sigma * sigma)).astype(np.float32)
        # Noise in the surface is the low-pass applied to random phases: its gradient has
        # covariance s^2 G with G the low-pass power's second moments (2 pi f)^2.
        power = np.broadcast_to(self._lowpass.astype(np.float64) ** 2, self._lowpass.shape)
        half = np.where((fx > 0) & (fx < 0.5), 2.0, 1.0)  # rfft keeps one of each +-fx
        total = float((power * half).sum())
        gxx = float((power * half * (2 * np.pi * fx) ** 2).sum()) / total
        gyy = float((power * half * (2 * np.pi * fy) ** 2).sum()) / total
        self._gradient_noise = np.diag([gxx, gyy])
        # The peak's own energy is left out of the noise: ~3.5 of its widths around it.
        self._exclusion_px = math.ceil(3.5 / (2 * np.pi * sigma)) + 2
        # 2 pi k / n of each axis's real spectrum, for the shears of a Fourier rotation.
        self._kx_turns = 2 * np.pi * np.fft.rfftfreq(self.shape_t[1])
        self._ky_turns = 2 * np.pi * np.fft.rfftfreq(self.shape_t[0])
        self._build_sectors()
        # The quarter grid of sector energies and its pixel -> full pixel matrix.
        self._small_shape = (max(rows // 4, 1), max(cols // 4, 1))
        sy, sx = rows / self._small_shape[0], cols / self._small_shape[1]
        self._small_from_full = np.array(
            [[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]]
        )
        rows_i, cols_i = np.nonzero(self.mask)
        self._fan_centre = np.array([cols_i.mean(), rows_i.mean(), 1.0]) if rows_i.size else None

    def _build_polar_maps(self) -> None:
        p = self.params
        n = self.n
        nyquist = n / 2.0
        r_lo, r_hi = p.band[0] * nyquist, p.band[1] * nyquist
        radii = np.exp(np.linspace(math.log(r_lo), math.log(r_hi), p.n_radii))
        # Half a turn of angles is enough: the magnitude spectrum of a real image is
        # point-symmetric. Angles measured in the padded image's (x, y) pixel axes.
        angles = -np.pi / 2 + np.arange(p.n_angles) * (np.pi / p.n_angles)
        kx = radii[:, None] * np.cos(angles)[None, :]
        ky = radii[:, None] * np.sin(angles)[None, :]
        # rfft2 keeps kx >= 0 only: sample (kx, ky) there, ky shifted so DC is row n/2.
        self._map_x = kx.astype(np.float32)
        self._map_y = (ky + n // 2).astype(np.float32)
        self._angle_step = math.pi / p.n_angles

    def _build_sectors(self) -> None:
        """Smooth partition of unity of the padded translation image by bearing from the
        sonar (equal shares of the fan), one weight image per sector."""
        count = max(int(self.params.sectors), 1)
        height, width = self.shape_t
        cols = np.arange(width, dtype=np.float64)[None, :] - self.col0_t
        rows = np.arange(height, dtype=np.float64)[:, None] - self.row0_t
        to_metric = self.grid.pixel_to_metric()
        forward = to_metric[0, 1] * rows + to_metric[0, 2] + 0.0 * cols
        starboard = to_metric[1, 0] * cols + to_metric[1, 2] + 0.0 * rows
        bearing = np.arctan2(starboard, forward)
        inside = np.zeros(self.shape_t, bool)
        rows_m, cols_m = self.grid.shape
        inside[self.row0_t : self.row0_t + rows_m, self.col0_t : self.col0_t + cols_m] = self.mask
        fan = bearing[inside]
        if fan.size == 0:
            count = 1  # no fan pixel on the grid (a fan shorter than a grid row): one sector
        edges = np.quantile(fan, np.arange(1, count) / count) if fan.size else np.array([])
        blend = math.radians(self.params.sector_blend_deg)
        weights = np.empty((count, height, width), np.float32)
        below = np.ones(self.shape_t)
        for k in range(count):
            if k < count - 1:
                u = np.clip((bearing - edges[k]) / blend + 0.5, 0.0, 1.0)
                above = 0.5 - 0.5 * np.cos(np.pi * u)  # 0 before the edge, 1 after
                weights[k] = below - above
                below = above
            else:
                weights[k] = below
        self._sector_weights = weights

    def prepare(
        self,
        image: npt.NDArray[np.floating] | npt.NDArray[np.integer],
        mask: npt.NDArray[np.bool_] | None = None,
    ) -> PreparedFrame:
        """Window, pad and transform one frame (``image`` on this registrar's grid).

        mask: where the frame has data, when not the registrar's fan (a frame warped into
        another frame's grid); its edge gets the same Hamming taper.
        """
        if image.shape != self.grid.shape:
            raise ValueError(f"frame shape {image.shape} differs from grid {self.grid.shape}")
        frame = image.astype(np.float32, copy=False)
        if mask is None:
            mask, window = self.mask, self.window
        else:
            window = hamming_taper(mask, self.params.taper_px)
        values = frame[mask]
        mean = float(values.mean()) if values.size else 0.0
        rows, cols = self.grid.shape
        windowed = (frame - mean) * window
        padded = np.zeros(self.shape_t, np.float32)
        padded[self.row0_t : self.row0_t + rows, self.col0_t : self.col0_t + cols] = windowed
        rows_spectrum = scipy.fft.rfft(padded, axis=1, workers=1)
        return PreparedFrame(
            windowed=padded,
            image=frame,
            spectrum=scipy.fft.fft(rows_spectrum, axis=0, workers=1).astype(np.complex64),
            window=window,
            rows_spectrum=rows_spectrum,
        )

    def _polar(self, frame: PreparedFrame) -> npt.NDArray[np.complex64]:
        """The frame's log-polar spectrum (``PreparedFrame.polar_spectrum``), computed once
        when a rotation search first asks for it: the windowed frame on the square
        transform."""
        if frame.polar_spectrum is None:
            rows, cols = self.grid.shape
            inner = frame.windowed[
                self.row0_t : self.row0_t + rows, self.col0_t : self.col0_t + cols
            ]
            square = np.zeros((self.n, self.n), np.float32)
            square[self.row0 : self.row0 + rows, self.col0 : self.col0 + cols] = inner
            frame.polar_spectrum = self._polar_spectrum(scipy.fft.rfft2(square, workers=1))
        return frame.polar_spectrum

    def _sectors(self, frame: PreparedFrame) -> _Sectors:
        """The frame's bearing sectors, computed once, when the frame is first the earlier
        one of a pair."""
        if frame.sectors is None:
            count = self._sector_weights.shape[0]
            spectra = np.empty((count, *frame.spectrum.shape), np.complex64)
            energy = np.empty((count, *self._small_shape), np.float32)
            rows, cols = self.grid.shape
            inner = (slice(self.row0_t, self.row0_t + rows), slice(self.col0_t, self.col0_t + cols))
            power = frame.windowed[inner] ** 2
            rest = frame.spectrum.copy()
            for k in range(count):
                weight = self._sector_weights[k]
                if k < count - 1:
                    spectra[k] = scipy.fft.rfft2(frame.windowed * weight, workers=1)
                    rest -= spectra[k]
                else:
                    spectra[k] = rest
                energy[k] = self._shrink(power * weight[inner])
            frame.sectors = _Sectors(spectra, energy)
        return frame.sectors

    def _shrink(self, image: FloatImage) -> FloatImage:
        """Area-average to the quarter grid."""
        small = cv2.resize(image, self._small_shape[::-1], interpolation=cv2.INTER_AREA)
        return np.asarray(small, np.float32)

    def _centroids(
        self, sectors: _Sectors, later: PreparedFrame, later_to_earlier: Matrix
    ) -> Matrix:
        """Each sector's centroid (unpadded col, row, 1) over what the later frame also
        sees there: its energy weighted by the later frame's taper moved into the earlier
        frame. At the fit's fixed point any point of a sector would do; these make the
        lever arms, and so the yaw's covariance, those of the shared seabed."""
        window = later.window if later.window is not None else self.window
        small = self._small_from_full
        moved = cv2.warpAffine(
            self._shrink(window),
            (np.linalg.inv(small) @ later_to_earlier @ small)[:2],
            self._small_shape[::-1],
            flags=cv2.INTER_LINEAR,
        )
        mass = sectors.energy * moved[None]
        totals = mass.sum(axis=(1, 2))
        rows = np.arange(self._small_shape[0], dtype=np.float64)
        cols = np.arange(self._small_shape[1], dtype=np.float64)
        centroids = np.ones((mass.shape[0], 3))
        centroids[:, 0] = mass.sum(axis=1) @ cols / np.maximum(totals, 1e-12)
        centroids[:, 1] = mass.sum(axis=2) @ rows / np.maximum(totals, 1e-12)
        return (small @ centroids.T).T

    def register_far(
        self,
        earlier: PreparedFrame,
        later_image: FloatImage,
        prior: RelativePose,
        search_m: float | None = None,
        *,
        prior_sigma_m: float | None = None,
        n_hypotheses: int = 1,
        later_mask: npt.NDArray[np.bool_] | None = None,
    ) -> Registration:
        """Register frames whose relative pose is far from identity (loop closures between
        lanes, often half a turn apart): the later frame is first moved into the earlier
        frame's grid by ``prior``, the small residual registered (``register``, same
        arguments), and the two composed. Hypotheses are composed the same way and scored
        on the original frames. ``later_mask``: where the later frame has data, when not
        this registrar's fan (``SonarFrame.own_mask``)."""
        to_metric = self.grid.pixel_to_metric()
        to_pixel = np.linalg.inv(to_metric)
        prior_pixels = to_pixel @ prior.matrix() @ to_metric  # later pixel -> earlier pixel
        rows, cols = self.grid.shape
        warped = cv2.warpAffine(later_image, prior_pixels[:2], (cols, rows), flags=cv2.INTER_LINEAR)
        source_mask = self._mask_u8 if later_mask is None else later_mask.view(np.uint8)
        warped_mask = cv2.warpAffine(
            source_mask, prior_pixels[:2], (cols, rows), flags=cv2.INTER_NEAREST
        ).astype(bool)
        if warped_mask.sum() < 0.05 * self.mask.sum():
            return Registration(prior, 0.0, 0.0, 0.0)
        residual = self.register(
            earlier,
            self.prepare(warped, warped_mask),
            RelativePose(0.0, 0.0, 0.0),
            search_m,
            prior_sigma_m=prior_sigma_m,
            n_hypotheses=n_hypotheses,
        )

        def compose(relative: RelativePose) -> RelativePose:
            return RelativePose.from_matrix(relative.matrix() @ prior.matrix())

        def rescore(relative: RelativePose) -> tuple[float, float]:
            pixels = to_pixel @ relative.matrix() @ to_metric
            return self.similarity(earlier.image, later_image, pixels)

        total = compose(residual.relative)
        score, overlap = rescore(total)
        hypotheses = []
        for k, h in enumerate(residual.hypotheses):
            relative = total if k == 0 else compose(h.relative)
            h_score, h_overlap = (score, overlap) if k == 0 else rescore(relative)
            j = _compose_jacobian(h.relative, prior)
            h_cov = j @ h.covariance @ j.T
            hypotheses.append(
                Hypothesis(relative, h_cov, h.peak, h.log_likelihood, h_score, h_overlap)
            )
        covariance = None
        if residual.covariance is not None:
            j = _compose_jacobian(residual.relative, prior)
            covariance = j @ residual.covariance @ j.T
        return Registration(total, score, residual.peak, overlap, covariance, tuple(hypotheses))

    def _polar_spectrum(
        self, spectrum: npt.NDArray[np.complexfloating]
    ) -> npt.NDArray[np.complex64]:
        magnitude = np.log1p(np.abs(spectrum)).astype(np.float32)
        magnitude = np.fft.fftshift(magnitude, axes=0)
        polar = cv2.remap(
            magnitude, self._map_x, self._map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
        )
        polar -= polar.mean(axis=1, keepdims=True)
        return scipy.fft.rfft(polar, axis=1, workers=1).astype(np.complex64)

    def rotation(
        self, earlier: PreparedFrame, later: PreparedFrame, centre_rad: float = 0.0
    ) -> tuple[float, float]:
        """Coarse yaw change (radians, clockwise positive) from the earlier frame to the
        later, searched within ``max_rotation_deg`` of ``centre_rad``, and the normalised
        peak. Only a starting point: ``register`` refines it from the motion itself.

        The magnitude spectrum repeats every half turn, so the answer is the one of the
        two candidates half a turn apart that lies nearer ``centre_rad``.
        """
        # Plain (not phase-only) correlation along the angle axis, summed over radii:
        # whitening the polar spectra would amplify the speckle's flat spectrum.
        cross = (self._polar(earlier) * np.conj(self._polar(later))).sum(axis=0)
        line = scipy.fft.irfft(cross, n=self.params.n_angles)
        line /= max(float(np.sqrt(self._energy(earlier) * self._energy(later))), 1e-12)
        n_angles = self.params.n_angles
        limit = math.ceil(math.radians(self.params.max_rotation_deg) / self._angle_step)
        centre = round(centre_rad / self._angle_step)
        candidates = np.arange(centre - limit, centre + limit + 1) % n_angles
        best = int(candidates[np.argmax(line[candidates])])
        offset = parabolic_offset(
            float(line[(best - 1) % n_angles]),
            float(line[best]),
            float(line[(best + 1) % n_angles]),
        )
        angle = (best + offset) * self._angle_step
        # Nearest to the centre among angle + k * pi.
        angle += math.pi * round((centre_rad - angle) / math.pi)
        return angle, float(line[best])

    def _energy(self, frame: PreparedFrame) -> float:
        spectrum = self._polar(frame)
        return float((np.abs(spectrum) ** 2).sum())

    def _rotated_spectrum(
        self, frame: PreparedFrame, angle_rad: float
    ) -> npt.NDArray[np.complex64]:
        """rfft2 of the frame turned by ``angle_rad`` about ``centre`` (cv2's convention,
        counter-clockwise on screen), by three Fourier shears (Larkin et al. 1997,
        doi:10.1016/S0030-4018(97)00097-7): exact for the band-limited image. A spatial
        interpolator would do: but its phase error, which a small turn does not average
        out over the frame, bends the fan (linear: rotations over-estimated by 2.5 % at
        0.3 degrees a pair, cubic under-estimated by 2 %)."""
        height, width = self.shape_t
        cx, cy = self.centre
        # dst(p) = src(c + A (p - c)), A = Sx(a) Sy(b) Sx(a) the inverse of cv2's turn;
        # a shear moves each row (column) by a phase ramp on its spectrum.
        a, b = -math.tan(angle_rad / 2.0), math.sin(angle_rad)
        x_ramp = _phase_ramp((np.arange(height) - cy) * a, self._kx_turns)
        y_ramp = _phase_ramp(self._ky_turns, (np.arange(width) - cx) * b)
        rows = frame.rows_spectrum
        if rows is None:
            rows = scipy.fft.rfft(frame.windowed, axis=1, workers=1)
        image = scipy.fft.irfft(rows * x_ramp, n=width, axis=1, workers=1)
        columns = scipy.fft.rfft(image, axis=0, workers=1)
        image = scipy.fft.irfft(columns * y_ramp, n=height, axis=0, workers=1)
        rows = scipy.fft.rfft(image, axis=1, workers=1) * x_ramp
        return scipy.fft.fft(rows, axis=0, workers=1).astype(np.complex64, copy=False)

    def _surfaces(
        self, sector_spectra: npt.NDArray[np.complex64], later_spectrum: npt.NDArray[np.complex64]
    ) -> tuple[list[_Surface], _Surface]:
        """Phase-correlation surfaces of each earlier sector against the later image, and
        their mean, the frame's surface. Each sector is whitened by its own cross-power:
        whitening all by the frame's would couple them and push their peaks apart."""
        # Phase only, then a low-pass: speckle fills the high frequencies with noise that
        # whitening would weigh as much as the seabed's texture.
        cross = sector_spectra * np.conj(later_spectrum)[None]
        cross *= self._lowpass[None] / (np.abs(cross) + 1e-9)
        values = scipy.fft.irfft2(cross, s=self.shape_t, axes=(-2, -1), workers=1)
        sectors = [self._surface(v) for v in values]
        return sectors, self._surface(values.mean(axis=0, dtype=np.float32))

    def _surface(self, values: FloatImage) -> _Surface:
        """The surface with its noise: the RMS of every other pixel of every other row,
        less the neighbourhood of the highest peak (whose energy would count as noise),
        and the noise's gradient covariance s^2 G (G the low-pass power's moments)."""
        width = values.shape[1]
        top = int(np.argmax(values))
        sample = values[::2, ::2]
        power = sample * sample
        radius = self._exclusion_px // 2 + 1
        rows = (top // width // 2 + np.arange(-radius, radius + 1)) % power.shape[0]
        cols = (top % width // 2 + np.arange(-radius, radius + 1)) % power.shape[1]
        power[np.ix_(rows, cols)] = 0.0
        count = max(power.size - rows.size * cols.size, 1)
        noise = max(math.sqrt(float(power.sum(dtype=np.float64)) / count), 1e-12)
        return _Surface(values, noise, noise * noise * self._gradient_noise)

    def _peak(self, surface: _Surface, px: int, py: int) -> _Peak:
        """Sub-pixel peak at integer (px, py): the quadratic through the logarithm of the
        3 x 3 neighbourhood (central differences; exact for the Gaussian peak that the
        Gaussian low-pass gives a translation), or through the values when some are not
        positive; covariance s^2 H^-1 G H^-1 with H the surface's Hessian at the peak."""
        values = surface.values
        height, width = values.shape
        # In scalars: numpy's overhead on 3 x 3 and 2 x 2 arrays was most of a peak's time.
        if 0 < py < height - 1 and 0 < px < width - 1:
            patch: list[list[float]] = values[py - 1 : py + 2, px - 1 : px + 2].tolist()
        else:
            rows = ((py - 1) % height, py, (py + 1) % height)
            cols = ((px - 1) % width, px, (px + 1) % width)
            patch = [[float(values[r, c]) for c in cols] for r in rows]
        centre = patch[1][1]
        logarithmic = min(min(row) for row in patch) > 0.02 * centre > 0.0
        f = [[math.log(v) for v in row] for row in patch] if logarithmic else patch
        gx, gy = (f[1][2] - f[1][0]) / 2.0, (f[2][1] - f[0][1]) / 2.0
        hxy = (f[2][2] - f[2][0] - f[0][2] + f[0][0]) / 4.0
        hxx = f[1][2] - 2.0 * f[1][1] + f[1][0]
        hyy = f[2][1] - 2.0 * f[1][1] + f[0][1]
        det = hxx * hyy - hxy * hxy
        if hxx < 0.0 and det > 0.0:
            ox = min(max(-(hyy * gx - hxy * gy) / det, -1.0), 1.0)
            oy = min(max(-(hxx * gy - hxy * gx) / det, -1.0), 1.0)
            top = (
                f[1][1]
                + gx * ox
                + gy * oy
                + 0.5 * (hxx * ox * ox + 2.0 * hxy * ox * oy + hyy * oy * oy)
            )
            value = math.exp(top) if logarithmic else top
            if logarithmic:
                # Of the surface at its maximum (gradient 0).
                hxx, hxy, hyy, det = value * hxx, value * hxy, value * hyy, value * value * det
            inverse = np.array([[hyy, -hxy], [-hxy, hxx]]) / det
            covariance = inverse @ surface.gradient_noise @ inverse
        else:
            # A ridge or a saddle, not a peak: the pixel itself, a pixel's spread.
            ox, oy, value, covariance = 0.0, 0.0, centre, np.eye(2)
        x, y = px + ox, py + oy
        # Shifts beyond half the transform wrap around to negative ones.
        x -= width if x > width / 2 else 0
        y -= height if y > height / 2 else 0
        return _Peak(x, y, value, covariance)

    def _local_peak(self, surface: _Surface, x: float, y: float, radius: int) -> _Peak:
        """The highest pixel within ``radius`` of shift (x, y), refined (``_peak``)."""
        height, width = surface.values.shape
        cx, cy = round(x) % width, round(y) % height
        if radius <= cy < height - radius and radius <= cx < width - radius:
            window = surface.values[cy - radius : cy + radius + 1, cx - radius : cx + radius + 1]
            iy, ix = divmod(int(np.argmax(window)), 2 * radius + 1)
            return self._peak(surface, cx - radius + ix, cy - radius + iy)
        xs = (cx + np.arange(-radius, radius + 1)) % width
        ys = (cy + np.arange(-radius, radius + 1)) % height
        window = surface.values[np.ix_(ys, xs)]
        row, col = divmod(int(np.argmax(window)), 2 * radius + 1)
        return self._peak(surface, int(xs[col]), int(ys[row]))

    def _candidates(
        self,
        surface: _Surface,
        expected: tuple[float, float] | None,
        sigma_px: float | None,
        count: int,
    ) -> list[tuple[float, _Peak]]:
        """The highest distinct peaks of the whole surface with their log-likelihood, best
        first: the matched-filter term h h_max / s^2 (a peak of height h in noise s, the
        true peak's height taken as the highest's), plus -d^2 / (2 sigma^2) for a peak d
        from the prior's prediction when a prior sigma is given."""
        r = max(int(self.params.nms_radius_px), 1)
        values = surface.values
        dilated = cv2.dilate(values, np.ones((2 * r + 1, 2 * r + 1), np.uint8))
        maxima = np.flatnonzero((values >= dilated) & (values > 0.0))
        if maxima.size == 0:
            maxima = np.array([int(np.argmax(values))])
        if maxima.size > count:
            maxima = maxima[np.argpartition(values.ravel()[maxima], -count)[-count:]]
        height, width = values.shape
        peaks = [self._peak(surface, int(i % width), int(i // width)) for i in maxima]
        top = max(peak.height for peak in peaks)
        noise = surface.noise
        scored = []
        for peak in peaks:
            log_likelihood = peak.height * top / (noise * noise)
            if expected is not None and sigma_px is not None:
                dx = (peak.x - expected[0] + width / 2) % width - width / 2
                dy = (peak.y - expected[1] + height / 2) % height - height / 2
                log_likelihood -= 0.5 * (dx * dx + dy * dy) / (sigma_px * sigma_px)
            scored.append((float(log_likelihood), peak))
        scored.sort(key=lambda item: -item[0])
        return scored

    def _later_to_earlier_pixels(self, angle_rad: float, shift_px: tuple[float, float]) -> Matrix:
        """3x3 matrix taking unpadded later-frame pixel (col, row) to earlier-frame pixel."""
        rotate = np.vstack(
            [cv2.getRotationMatrix2D(self.centre, math.degrees(angle_rad), 1.0), [0, 0, 1]]
        )
        shift = np.array([[1.0, 0.0, shift_px[0]], [0.0, 1.0, shift_px[1]], [0.0, 0.0, 1.0]])
        # later_rotated(x) = later(R^-1 x); later_rotated(x) ~= earlier(x + s)
        # => later(y) ~= earlier(R y + s): later pixel y maps to earlier pixel R y + s.
        return self._unpad @ shift @ rotate @ self._pad

    def _relative(self, angle_rad: float, shift_px: tuple[float, float]) -> RelativePose:
        to_metric = self.grid.pixel_to_metric()
        pixels = self._later_to_earlier_pixels(angle_rad, shift_px)
        return RelativePose.from_matrix(to_metric @ pixels @ np.linalg.inv(to_metric))

    def _fit(
        self,
        surfaces: list[_Surface],
        sectors: _Sectors,
        later: PreparedFrame,
        angle_rad: float,
        mode: _Peak,
    ) -> _Fit:
        """Rigid fit (weighted least squares, metric) of the correspondences that each
        sector's peak near ``mode`` gives: the sector's centroid in the earlier frame and
        where the later frame has it. Fewer than two usable sectors: the mode's pose, its
        translation covariance and the fallback yaw sigma."""
        p = self.params
        to_metric = self.grid.pixel_to_metric()
        jacobian = to_metric[:2, :2]  # pixel displacement -> metric displacement
        mode_pixels = self._later_to_earlier_pixels(angle_rad, (mode.x, mode.y))
        centroids = self._centroids(sectors, later, mode_pixels)
        earlier_points, later_points, weights = [], [], []
        for surface, centroid in zip(surfaces, centroids, strict=True):
            peak = self._local_peak(surface, mode.x, mode.y, 3)
            if peak.height < p.min_sector_snr * surface.noise:
                continue
            # The later frame's pixel that the sector's centroid came from: y = P^-1 c.
            pixels = self._later_to_earlier_pixels(angle_rad, (peak.x, peak.y))
            earlier_points.append(to_metric @ centroid)
            later_points.append(to_metric @ np.linalg.solve(pixels, centroid))
            weights.append(_inverse2(jacobian @ peak.covariance @ jacobian.T))
        relative = self._relative(angle_rad, (mode.x, mode.y))
        if len(weights) < 2:
            covariance = np.zeros((3, 3))
            # The translation is measured where the fan is: an unknown yaw swings the
            # sonar's origin about it.
            lever = self._lever(relative)
            yaw_var = math.radians(p.fallback_yaw_sigma_deg) ** 2
            translation = jacobian @ mode.covariance @ jacobian.T * p.covariance_scale
            covariance[:2, :2] = translation + yaw_var * np.outer(lever, lever)
            covariance[:2, 2] = covariance[2, :2] = yaw_var * lever
            covariance[2, 2] = yaw_var
            return _Fit(relative, covariance, mode)
        # Gauss-Newton in scalars (2-4 points: numpy's overhead was most of the time).
        points = [
            (ep[0], ep[1], lp[0], lp[1], wt[0][0], wt[0][1], wt[1][1])
            for ep, lp, wt in zip(
                np.array(earlier_points).tolist(),
                np.array(later_points).tolist(),
                np.array(weights).tolist(),
                strict=True,
            )
        ]
        tx, ty, yaw = relative.forward_m, relative.starboard_m, relative.yaw_rad
        normal = np.eye(3)
        for _ in range(4):
            c, s = math.cos(yaw), math.sin(yaw)
            n00 = n01 = n02 = n11 = n12 = n22 = g0 = g1 = g2 = 0.0
            for ex, ey, yx, yy, w00, w01, w11 in points:
                ux, uy = c * yx - s * yy, s * yx + c * yy  # R y
                rx, ry = ex - ux - tx, ey - uy - ty
                # J = [[1, 0, -uy], [0, 1, ux]] (d(R y + t)/d(t, yaw)); W symmetric.
                a2 = -uy * w00 + ux * w01  # (W J)[0, 2]
                b2 = -uy * w01 + ux * w11  # (W J)[1, 2]
                n00 += w00
                n01 += w01
                n11 += w11
                n02 += a2
                n12 += b2
                n22 += -uy * a2 + ux * b2
                g0 += w00 * rx + w01 * ry
                g1 += w01 * rx + w11 * ry
                g2 += a2 * rx + b2 * ry
            normal = np.array([[n00, n01, n02], [n01, n11, n12], [n02, n12, n22]])
            step = np.linalg.solve(normal, np.array([g0, g1, g2]))
            tx, ty, yaw = tx + float(step[0]), ty + float(step[1]), yaw + float(step[2])
            if abs(step[2]) < 1e-9 and float(np.abs(step[:2]).max()) < 1e-7:
                break
        c, s = math.cos(yaw), math.sin(yaw)
        chi2 = 0.0
        for ex, ey, yx, yy, w00, w01, w11 in points:
            rx = ex - (c * yx - s * yy) - tx
            ry = ey - (s * yx + c * yy) - ty
            chi2 += w00 * rx * rx + 2.0 * w01 * rx * ry + w11 * ry * ry
        # The sectors' disagreement scales the covariance (a Birge ratio, shrunk towards 1
        # by ``covariance_prior_dof``): the first-order peak covariance misses errors that
        # grow with how differently the two frames see the seabed.
        dof = 2 * len(weights) - 3
        birge = (p.covariance_prior_dof + chi2) / (p.covariance_prior_dof + dof)
        fitted = np.asarray(np.linalg.inv(normal) * (p.covariance_scale * birge), np.float64)
        return _Fit(RelativePose(tx, ty, yaw), fitted, mode)

    def _turned(self, fit: _Fit, yaw_rad: float) -> _Fit:
        """The fit turned by a small ``yaw_rad`` about the fan's centre (where the
        translation is measured)."""
        if yaw_rad == 0.0:
            return fit
        r = fit.relative
        lever = self._lever(r)
        relative = RelativePose(
            r.forward_m + lever[0] * yaw_rad,
            r.starboard_m + lever[1] * yaw_rad,
            r.yaw_rad + yaw_rad,
        )
        return _Fit(relative, fit.covariance, fit.peak)

    def _lever(self, relative: RelativePose) -> npt.NDArray[np.float64]:
        """d(translation)/d(yaw) of a pose turned about the fan's centre q, where the
        translation is measured: t = q - R(yaw) q' with q' = R^-1 (q - t) held, so
        dt/dyaw = -R'(yaw) q' = -J (q - t), J the quarter turn."""
        if self._fan_centre is None:
            return np.zeros(2)
        centre = (self.grid.pixel_to_metric() @ self._fan_centre)[:2]
        arm = centre - np.array([relative.forward_m, relative.starboard_m])
        return np.array([arm[1], -arm[0]])

    def register(
        self,
        earlier: PreparedFrame,
        later: PreparedFrame,
        prior: RelativePose | None = None,
        search_m: float | None = None,
        *,
        prior_sigma_m: float | None = None,
        n_hypotheses: int = 1,
        yaw_known: bool = False,
    ) -> Registration:
        """Relative pose of ``later`` in the sonar frame of ``earlier``, its covariance
        and, when ``n_hypotheses`` > 1, that many distinct peaks as hypotheses (best
        first, each with its own similarity score and overlap).

        prior: the expected relative pose (e.g. from the EKF): centres the rotation
        search and, with ``prior_sigma_m`` (its translation sigma, metres), weighs the
        translation peaks by a Gaussian log-likelihood. The whole correlation surface is
        searched either way. search_m: the former search radius, now taken as
        ``prior_sigma_m`` when that is not given (nothing is confined any more).
        yaw_known: the prior's yaw is a gyro's: no spectral rotation search, the later
        frame turned by it and the sectors' fit refined ``known_yaw_iterations`` times.
        """
        p = self.params
        sigma_m = prior_sigma_m if prior_sigma_m is not None else search_m
        sigma_px = sigma_m / self.grid.res_m if prior is not None and sigma_m else None
        iterations = max(p.refine_iterations, 1)
        if yaw_known and prior is not None:
            yaw = prior.yaw_rad
            iterations = max(p.known_yaw_iterations, 1)
        else:
            yaw, _ = self.rotation(earlier, later, prior.yaw_rad if prior is not None else 0.0)
        if prior is not None and abs(yaw - prior.yaw_rad) <= math.radians(p.prior_trust_deg):
            # Only where the iteration starts (the answer is its fixed point, whatever the
            # start): a gyro's yaw change is nearer than the spectra's, which static
            # patterns pull towards zero, so it ends sooner.
            yaw = prior.yaw_rad
        # cv2 turns images counter-clockwise on screen for a positive angle: the opposite.
        angle = -yaw
        sectors = self._sectors(earlier)
        count = max(p.candidates, n_hypotheses)
        tolerance = math.radians(p.refine_tolerance_deg)
        # The fit's angle as a function of the turn it was measured at has its fixed point
        # at the answer; secant steps find it whatever the fit's gain.
        previous: tuple[float, float] | None = None
        for iteration in range(iterations):
            surfaces, surface = self._surfaces(
                sectors.spectra, self._rotated_spectrum(later, angle)
            )
            expected = self._expected_shift(prior, angle) if sigma_px is not None else None
            ranked = self._candidates(surface, expected, sigma_px, count)
            fit = self._fit(surfaces, sectors, later, angle, ranked[0][1])
            turn = -fit.relative.yaw_rad - angle
            slope = -1.0  # d(turn)/d(angle) of a fit whose gain is 1
            if previous is not None and turn != previous[1]:
                measured = (turn - previous[1]) / (angle - previous[0])
                slope = measured if -3.0 < measured < -0.3 else slope
            settled = max(tolerance, p.refine_tolerance_sigmas * math.sqrt(fit.covariance[2, 2]))
            if abs(turn) <= settled or iteration == iterations - 1:
                # What is left of the turn, at the fit's measured gain (0 at gain 1).
                fit = self._turned(fit, turn * (1.0 + 1.0 / slope))  # yaw is -angle
                break
            previous = (angle, turn)
            angle -= turn / slope
        relative = fit.relative
        to_metric = self.grid.pixel_to_metric()
        to_pixel = np.linalg.inv(to_metric)
        score, overlap = self.similarity(
            earlier.image, later.image, to_pixel @ relative.matrix() @ to_metric
        )
        hypotheses = [
            Hypothesis(relative, fit.covariance, fit.peak.height, ranked[0][0], score, overlap)
        ]
        # Peaks whose fits land on one already kept (a peak's shoulder, split in two)
        # are not distinct hypotheses.
        distinct_m = p.nms_radius_px * self.grid.res_m
        for log_likelihood, peak in ranked[1:]:
            if len(hypotheses) >= n_hypotheses:
                break
            other_fit = self._fit(surfaces, sectors, later, angle, peak)
            other = other_fit.relative
            if any(
                math.hypot(
                    other.forward_m - h.relative.forward_m,
                    other.starboard_m - h.relative.starboard_m,
                )
                < distinct_m
                for h in hypotheses
            ):
                continue
            h_score, h_overlap = self.similarity(
                earlier.image, later.image, to_pixel @ other.matrix() @ to_metric
            )
            hypotheses.append(
                Hypothesis(
                    other, other_fit.covariance, peak.height, log_likelihood, h_score, h_overlap
                )
            )
        return Registration(
            relative, score, fit.peak.height, overlap, fit.covariance, tuple(hypotheses)
        )

    def _expected_shift(self, prior: RelativePose | None, angle_rad: float) -> tuple[float, float]:
        """The phase-correlation shift that ``prior`` predicts once the later frame is
        turned by ``angle_rad``: where it puts the fan's centre, less where the turn does."""
        if prior is None or self._fan_centre is None:
            return 0.0, 0.0
        to_metric = self.grid.pixel_to_metric()
        pixels = np.linalg.inv(to_metric) @ prior.matrix() @ to_metric
        rotate = np.vstack(
            [cv2.getRotationMatrix2D(self.centre, math.degrees(angle_rad), 1.0), [0, 0, 1]]
        )
        later_centre = self._pad @ self._fan_centre
        predicted = self._pad @ pixels @ self._fan_centre
        shift = predicted - rotate @ later_centre
        return float(shift[0]), float(shift[1])

    def similarity(
        self,
        earlier: FloatImage,
        later: FloatImage,
        later_to_earlier: Matrix,
    ) -> tuple[float, float]:
        """NCC of the two fans where they overlap after alignment, and the overlap fraction."""
        rows, cols = self.grid.shape
        warp = later_to_earlier[:2].astype(np.float64)
        moved = cv2.warpAffine(later, warp, (cols, rows), flags=cv2.INTER_LINEAR)
        moved_mask = cv2.warpAffine(self._mask_u8, warp, (cols, rows), flags=cv2.INTER_NEAREST)
        both = np.where(moved_mask > 0, self._mask_f32, np.float32(0.0))
        count = float(both.sum())
        if count < 16:
            return 0.0, 0.0
        a = earlier * both
        b = moved * both
        sa, sb = float(a.sum(dtype=np.float64)), float(b.sum(dtype=np.float64))
        saa = float(np.sum(a * earlier, dtype=np.float64))
        sbb = float(np.sum(b * moved, dtype=np.float64))
        sab = float(np.sum(a * moved, dtype=np.float64))
        var_a, var_b = saa - sa * sa / count, sbb - sb * sb / count
        denominator = math.sqrt(max(var_a, 0.0) * max(var_b, 0.0))
        score = (sab - sa * sb / count) / denominator if denominator > 0 else 0.0
        return float(score), count / max(self._mask_count, 1)


_REGISTRARS: dict[tuple[SonarGrid, FmtParams, bytes], FmtRegistrar] = {}


def cached_registrar(
    grid: SonarGrid, mask: npt.NDArray[np.bool_], params: FmtParams
) -> FmtRegistrar:
    """A registrar for this grid, fan and settings, built once per process (a worker
    process's pure tasks share it; a new geometry replaces it)."""
    key = (grid, params, mask.tobytes())
    registrar = _REGISTRARS.get(key)
    if registrar is None:
        _REGISTRARS.clear()
        registrar = FmtRegistrar(grid, mask, params)
        _REGISTRARS[key] = registrar
    return registrar
