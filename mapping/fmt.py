"""Fourier–Mellin registration of consecutive Cartesian sonar frames.

Rotation comes from the log-polar resampled magnitude spectra (rotation of an image
rotates its magnitude spectrum about DC, whatever the translation; Reddy & Chatterji 1996,
doi:10.1109/83.506761), translation from phase correlation after de-rotation (Kuglin &
Hines 1975), both with sub-pixel peaks. FLS frames are fans: the fan edge is static in
the sonar frame and would pull every estimate towards "no motion", so each frame is
multiplied by a Hamming-tapered fan window (Hurtós et al. 2015,
doi:10.1002/rob.21516) and the lowest frequencies, where the window's own spectrum lives,
are left out of the rotation estimate. This is the paper's local registration
(Zhang et al., Sec. III.E, Algorithm 1 lines 1-11).

Frames: a Cartesian sonar frame is an image whose rows run from far (row 0) to near and
whose columns run from port to starboard; ``SonarGrid`` says where the sonar sits in it.
Results are metric relative poses in the sonar frame of the *earlier* image: forward and
starboard metres, and the yaw change in radians, clockwise (to starboard) positive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
import scipy.fft

FloatImage = npt.NDArray[np.float32]


@dataclass(frozen=True, slots=True)
class SonarGrid:
    """Geometry of a Cartesian sonar frame.

    shape: (rows, cols). res_m: pixel size (metres). forward_max_m: forward coordinate of
    the top edge of row 0. starboard_min_m: starboard coordinate of the left edge of col 0.
    Pixel (col, row) centre is at forward = forward_max_m - (row + 0.5) * res_m,
    starboard = starboard_min_m + (col + 0.5) * res_m (metres, sonar frame).
    """

    shape: tuple[int, int]
    res_m: float
    forward_max_m: float
    starboard_min_m: float

    def pixel_to_metric(self) -> npt.NDArray[np.float64]:
        """3x3 homogeneous matrix taking (col, row, 1) to (forward, starboard, 1)."""
        r = self.res_m
        return np.array(
            [
                [0.0, -r, self.forward_max_m - 0.5 * r],
                [r, 0.0, self.starboard_min_m + 0.5 * r],
                [0.0, 0.0, 1.0],
            ]
        )


@dataclass(frozen=True, slots=True)
class RelativePose:
    """Pose of a later sonar frame in the frame of an earlier one.

    forward_m, starboard_m: translation (metres, earlier sonar frame);
    yaw_rad: heading change (radians, clockwise positive).
    """

    forward_m: float
    starboard_m: float
    yaw_rad: float

    def matrix(self) -> npt.NDArray[np.float64]:
        """3x3 homogeneous matrix taking later-frame (forward, starboard) to earlier-frame."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return np.array([[c, -s, self.forward_m], [s, c, self.starboard_m], [0.0, 0.0, 1.0]])

    @classmethod
    def from_matrix(cls, m: npt.NDArray[np.float64]) -> RelativePose:
        return cls(float(m[0, 2]), float(m[1, 2]), math.atan2(m[1, 0], m[0, 0]))


@dataclass(frozen=True, slots=True)
class FmtParams:
    """Tuning of the registration.

    max_rotation_deg: largest yaw change searched between two frames.
    n_angles: angular samples of the log-polar spectrum over 180 degrees.
    n_radii: radial (log) samples. band: the spectrum band used for rotation, as fractions
    of the Nyquist radius (low end skips the window's spectrum, high end the pixel noise).
    taper_px: width of the Hamming taper at the fan edge (pixels).
    """

    max_rotation_deg: float = 8.0
    n_angles: int = 720
    n_radii: int = 96
    band: tuple[float, float] = (0.04, 0.7)
    taper_px: int = 12
    refine_step_rad: float = math.radians(0.3)
    refine_iterations: int = 6
    lowpass_sigma: float = 0.12
    prior_trust_deg: float = 0.5
    """When the spectral rotation is within this of the prior's, refinement starts at
    the prior with the fine step (four phase correlations instead of eight)."""
    """Gaussian weight on the phase-correlation spectrum, cycles per pixel."""


@dataclass(frozen=True, slots=True)
class Registration:
    """A registration result.

    relative: the later frame's pose in the earlier frame (metric, see RelativePose).
    score: normalised cross-correlation of the overlapping fan after alignment, in
    [-1, 1] (the paper's similarity score, SS). peak: phase-correlation peak height (a
    confidence in [0, 1]). overlap: fraction of the earlier fan covered by the later one.
    """

    relative: RelativePose
    score: float
    peak: float
    overlap: float


@dataclass(slots=True)
class PreparedFrame:
    """What registration keeps of one frame, computed once and reused for both pairs it
    belongs to (as the later frame, then as the earlier one)."""

    windowed: FloatImage  # zero-mean, tapered, padded to the translation transform
    image: FloatImage  # unpadded, as given
    spectrum: npt.NDArray[np.complex64]  # rfft2 of windowed
    polar_spectrum: npt.NDArray[np.complex64]  # rfft2 of the log-polar log-magnitude


def hamming_taper(mask: npt.NDArray[np.bool_], taper_px: int) -> FloatImage:
    """Window that is 1 deep inside ``mask`` and falls along a Hamming half-window over
    ``taper_px`` pixels to the mask edge, 0 outside (the paper's Sec. III.C step 5)."""
    inside = mask.astype(np.uint8)
    distance = cv2.distanceTransform(inside, cv2.DIST_L2, 5)
    ramp = np.clip(distance / max(taper_px, 1), 0.0, 1.0)
    window = 0.54 - 0.46 * np.cos(np.pi * ramp)
    window[~mask] = 0.0
    return window.astype(np.float32)


def _parabolic_offset(left: float, centre: float, right: float) -> float:
    """Sub-sample offset of a peak from three samples around it (in [-0.5, 0.5])."""
    denominator = left - 2.0 * centre + right
    if denominator >= 0.0 or not math.isfinite(denominator):
        return 0.0
    return float(np.clip(0.5 * (left - right) / denominator, -0.5, 0.5))


class FmtRegistrar:
    """Registers Cartesian sonar frames of one ``SonarGrid`` with a fixed fan ``mask``.

    Everything that depends only on the geometry (window, padding, log-polar sampling
    maps, band weights) is computed once here, so registering a pair costs a few FFTs.
    """

    def __init__(
        self, grid: SonarGrid, mask: npt.NDArray[np.bool_], params: FmtParams | None = None
    ) -> None:
        if mask.shape != grid.shape:
            raise ValueError(f"mask shape {mask.shape} differs from grid shape {grid.shape}")
        self.grid = grid
        self.params = params or FmtParams()
        self.mask = mask.astype(bool)
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
        # (x, y) of the rotation centre in the translation transform's padded image.
        self.centre = ((self.shape_t[1] - 1) / 2.0, (self.shape_t[0] - 1) / 2.0)
        fy = np.fft.fftfreq(self.shape_t[0])[:, None]
        fx = np.fft.rfftfreq(self.shape_t[1])[None, :]
        sigma = self.params.lowpass_sigma
        self._lowpass = np.exp(-(fx * fx + fy * fy) / (2 * sigma * sigma)).astype(np.float32)

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
        square = np.zeros((self.n, self.n), np.float32)
        square[self.row0 : self.row0 + rows, self.col0 : self.col0 + cols] = windowed
        padded = np.zeros(self.shape_t, np.float32)
        padded[self.row0_t : self.row0_t + rows, self.col0_t : self.col0_t + cols] = windowed
        return PreparedFrame(
            windowed=padded,
            image=frame,
            spectrum=scipy.fft.rfft2(padded, workers=1).astype(np.complex64),
            polar_spectrum=self._polar_spectrum(scipy.fft.rfft2(square, workers=1)),
        )

    def register_far(
        self,
        earlier: PreparedFrame,
        later_image: FloatImage,
        prior: RelativePose,
        search_m: float,
    ) -> Registration:
        """Register frames whose relative pose is far from identity (loop closures between
        lanes, often half a turn apart): the later frame is first moved into the earlier
        frame's grid by ``prior``, the small residual registered, and the two composed."""
        to_metric = self.grid.pixel_to_metric()
        to_pixel = np.linalg.inv(to_metric)
        prior_pixels = to_pixel @ prior.matrix() @ to_metric  # later pixel -> earlier pixel
        rows, cols = self.grid.shape
        warped = cv2.warpAffine(later_image, prior_pixels[:2], (cols, rows), flags=cv2.INTER_LINEAR)
        warped_mask = cv2.warpAffine(
            self.mask.astype(np.uint8), prior_pixels[:2], (cols, rows), flags=cv2.INTER_NEAREST
        ).astype(bool)
        if warped_mask.sum() < 0.05 * self.mask.sum():
            return Registration(prior, 0.0, 0.0, 0.0)
        residual = self.register(
            earlier, self.prepare(warped, warped_mask), RelativePose(0.0, 0.0, 0.0), search_m
        )
        total = RelativePose.from_matrix(residual.relative.matrix() @ prior.matrix())
        pixels = to_pixel @ total.matrix() @ to_metric
        score, overlap = self.similarity(earlier.image, later_image, pixels)
        return Registration(total, score, residual.peak, overlap)

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
        """Yaw change (radians, clockwise positive) from the earlier frame to the later,
        searched within ``max_rotation_deg`` of ``centre_rad``, and the normalised peak.

        The magnitude spectrum repeats every half turn, so the answer is the one of the
        two candidates half a turn apart that lies nearer ``centre_rad``.
        """
        # Plain (not phase-only) correlation along the angle axis, summed over radii:
        # whitening the polar spectra would amplify the speckle's flat spectrum.
        cross = (earlier.polar_spectrum * np.conj(later.polar_spectrum)).sum(axis=0)
        line = scipy.fft.irfft(cross, n=self.params.n_angles)
        line /= max(float(np.sqrt(self._energy(earlier) * self._energy(later))), 1e-12)
        n_angles = self.params.n_angles
        limit = math.ceil(math.radians(self.params.max_rotation_deg) / self._angle_step)
        centre = round(centre_rad / self._angle_step)
        candidates = np.arange(centre - limit, centre + limit + 1) % n_angles
        best = int(candidates[np.argmax(line[candidates])])
        offset = _parabolic_offset(
            float(line[(best - 1) % n_angles]),
            float(line[best]),
            float(line[(best + 1) % n_angles]),
        )
        angle = (best + offset) * self._angle_step
        # Nearest to the centre among angle + k * pi.
        angle += math.pi * round((centre_rad - angle) / math.pi)
        return angle, float(line[best])

    def _energy(self, frame: PreparedFrame) -> float:
        spectrum = frame.polar_spectrum
        return float((np.abs(spectrum) ** 2).sum())

    def _rotated(self, frame: PreparedFrame, angle_rad: float) -> FloatImage:
        matrix = cv2.getRotationMatrix2D(self.centre, math.degrees(angle_rad), 1.0)
        return cv2.warpAffine(
            frame.windowed,
            matrix,
            (self.shape_t[1], self.shape_t[0]),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0.0,
        )

    def translation(
        self,
        earlier_spectrum: npt.NDArray[np.complex64],
        later_image: FloatImage,
        expected_px: tuple[float, float] | None,
        search_px: float | None,
    ) -> tuple[tuple[float, float], float]:
        """Shift (dx, dy) in pixels such that later(x) ~= earlier(x + shift), by phase
        correlation; the peak is searched within ``search_px`` of ``expected_px`` when given."""
        later_spectrum = scipy.fft.rfft2(later_image, workers=1)
        cross = earlier_spectrum * np.conj(later_spectrum)
        # Phase only, then a low-pass: speckle fills the high frequencies with noise that
        # whitening would weigh as much as the seabed's texture.
        cross *= self._lowpass / (np.abs(cross) + 1e-9)
        height, width = self.shape_t
        surface = scipy.fft.irfft2(cross, s=self.shape_t, workers=1)
        if expected_px is not None and search_px is not None:
            ex, ey = expected_px
            radius = math.ceil(search_px)
            xs = np.arange(round(ex) - radius, round(ex) + radius + 1) % width
            ys = np.arange(round(ey) - radius, round(ey) + radius + 1) % height
            window = surface[np.ix_(ys, xs)]
            iy, ix = np.unravel_index(int(np.argmax(window)), window.shape)
            py, px = int(ys[iy]), int(xs[ix])
        else:
            py, px = (int(v) for v in np.unravel_index(int(np.argmax(surface)), surface.shape))
        peak = float(surface[py, px])
        dx = px + _parabolic_offset(
            float(surface[py, (px - 1) % width]), peak, float(surface[py, (px + 1) % width])
        )
        dy = py + _parabolic_offset(
            float(surface[(py - 1) % height, px]), peak, float(surface[(py + 1) % height, px])
        )
        # Shifts beyond half the transform wrap around to negative ones.
        if dx > width / 2:
            dx -= width
        if dy > height / 2:
            dy -= height
        return (float(dx), float(dy)), peak

    def _later_to_earlier_pixels(
        self, angle_rad: float, shift_px: tuple[float, float]
    ) -> npt.NDArray[np.float64]:
        """3x3 matrix taking unpadded later-frame pixel (col, row) to earlier-frame pixel."""
        pad = np.array([[1.0, 0.0, self.col0_t], [0.0, 1.0, self.row0_t], [0.0, 0.0, 1.0]])
        rotate = np.vstack(
            [cv2.getRotationMatrix2D(self.centre, math.degrees(angle_rad), 1.0), [0, 0, 1]]
        )
        shift = np.array([[1.0, 0.0, shift_px[0]], [0.0, 1.0, shift_px[1]], [0.0, 0.0, 1.0]])
        # later_rotated(x) = later(R^-1 x); later_rotated(x) ~= earlier(x + s)
        # => later(y) ~= earlier(R y + s): later pixel y maps to earlier pixel R y + s.
        return np.linalg.inv(pad) @ shift @ rotate @ pad

    def register(
        self,
        earlier: PreparedFrame,
        later: PreparedFrame,
        prior: RelativePose | None = None,
        search_m: float | None = None,
    ) -> Registration:
        """Relative pose of ``later`` in the sonar frame of ``earlier``.

        prior: the expected relative pose (e.g. from the EKF); with ``search_m`` the
        translation peak is searched only that far (metres) from the prior's prediction.
        """
        angle, _ = self.rotation(earlier, later, prior.yaw_rad if prior is not None else 0.0)
        # The spectra give the rotation to a fraction of a degree; the phase-correlation
        # peak, which sharpens as the de-rotation gets right, refines it (parabola
        # through the peak heights at three angles).
        # cv2 turns images counter-clockwise on screen for a positive angle: the opposite.
        angle = -angle
        centre = -prior.yaw_rad if prior is not None else 0.0
        search_px: float | None = None
        if prior is not None and search_m is not None:
            search_px = search_m / self.grid.res_m

        def peak_at(theta: float) -> tuple[tuple[float, float], float]:
            centre = (
                self._expected_shift(prior, theta)
                if prior is not None and search_px is not None
                else None
            )
            return self.translation(
                earlier.spectrum, self._rotated(later, theta), centre, search_px
            )

        step = self.params.refine_step_rad
        fine = step / 3.0
        if prior is not None and abs(angle - centre) <= math.radians(self.params.prior_trust_deg):
            # The spectra agree with the prior (a gyro's yaw change is good to a few
            # hundredths of a degree over a ping): start from the prior, refine finely.
            angle, step = centre, fine
        limit = math.radians(self.params.max_rotation_deg)
        shift, peak = peak_at(angle)
        left, right = peak_at(angle - step)[1], peak_at(angle + step)[1]
        for _ in range(self.params.refine_iterations):
            if peak >= left and peak >= right:
                break
            # Hill-climb: the starting estimate was more than a step off.
            direction = 1.0 if right > left else -1.0
            if abs(angle + direction * step - centre) > limit:
                break
            angle += direction * step
            if direction > 0:
                left, (shift, peak) = peak, peak_at(angle)
                right = peak_at(angle + step)[1]
            else:
                right, (shift, peak) = peak, peak_at(angle)
                left = peak_at(angle - step)[1]
        offset = _parabolic_offset(left, peak, right)
        if offset != 0.0:
            angle += offset * step
            shift, peak = peak_at(angle)
        if step > fine:
            # A finer parabola: the peak height is parabolic in the angle only near its top.
            left, right = peak_at(angle - fine)[1], peak_at(angle + fine)[1]
            offset = _parabolic_offset(left, peak, right)
            if offset != 0.0:
                angle += offset * fine
                shift, peak = peak_at(angle)
        pixels = self._later_to_earlier_pixels(angle, shift)
        to_metric = self.grid.pixel_to_metric()
        metric = to_metric @ pixels @ np.linalg.inv(to_metric)
        relative = RelativePose.from_matrix(metric)
        score, overlap = self.similarity(earlier.image, later.image, pixels)
        return Registration(relative=relative, score=score, peak=peak, overlap=overlap)

    def _expected_shift(self, prior: RelativePose, angle_rad: float) -> tuple[float, float]:
        """The phase-correlation shift that ``prior`` predicts, given the found rotation."""
        to_metric = self.grid.pixel_to_metric()
        pixels = np.linalg.inv(to_metric) @ prior.matrix() @ to_metric
        pad = np.array([[1.0, 0.0, self.col0_t], [0.0, 1.0, self.row0_t], [0.0, 0.0, 1.0]])
        rotate = np.vstack(
            [cv2.getRotationMatrix2D(self.centre, math.degrees(angle_rad), 1.0), [0, 0, 1]]
        )
        shift = pad @ pixels @ np.linalg.inv(pad) @ np.linalg.inv(rotate)
        return float(shift[0, 2]), float(shift[1, 2])

    def similarity(
        self,
        earlier: FloatImage,
        later: FloatImage,
        later_to_earlier: npt.NDArray[np.float64],
    ) -> tuple[float, float]:
        """NCC of the two fans where they overlap after alignment, and the overlap fraction."""
        rows, cols = self.grid.shape
        warp = later_to_earlier[:2].astype(np.float64)
        moved = cv2.warpAffine(later, warp, (cols, rows), flags=cv2.INTER_LINEAR)
        moved_mask = cv2.warpAffine(
            self.mask.astype(np.uint8), warp, (cols, rows), flags=cv2.INTER_NEAREST
        ).astype(bool)
        both = self.mask & moved_mask
        count = int(both.sum())
        if count < 16:
            return 0.0, 0.0
        a = earlier[both].astype(np.float64)
        b = moved[both].astype(np.float64)
        a -= a.mean()
        b -= b.mean()
        denominator = math.sqrt(float(a @ a) * float(b @ b))
        score = float(a @ b) / denominator if denominator > 0 else 0.0
        return score, count / max(int(self.mask.sum()), 1)
