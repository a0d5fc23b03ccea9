"""Registration baselines the paper compares FMT with (Zhang et al., Sec. IV, Table II).

Three classical pairwise registrations of the same Cartesian frames FMT registers
(``SonarFrame.coarse`` on ``Preprocessor.registration_grid``, with
``registration_tables.mask`` as the fan), each from no prior (the identity), as plain
pairwise registrations:

- ORB + RANSAC: oriented FAST keypoints and rotated BRIEF descriptors (Rublee et al.
  2011, doi:10.1109/ICCV.2011.6126544), matched by Hamming distance with Lowe's ratio
  test, and a similarity transform fitted by RANSAC (Fischler & Bolles 1981,
  doi:10.1145/358669.358692).
- SIFT + RANSAC: difference-of-Gaussian keypoints and SIFT descriptors (Lowe 2004,
  doi:10.1023/B:VISI.0000029664.99615.94), matched by L2 distance with the ratio test
  at 0.75, and the same RANSAC fit.
- ECC: enhanced correlation coefficient maximisation over a Euclidean warp (Evangelidis
  & Psarakis 2008, doi:10.1109/TPAMI.2008.113), ``cv2.findTransformECC``, coarse to fine
  over an image pyramid, with the fan as its mask.

Feature methods fit a similarity (4 degrees of freedom, ``cv2.estimateAffinePartial2D``:
OpenCV has no RANSAC for 3) and report its scale, but the pose is rigid: the two frames
are metric images of one flat seabed on the same grid, so any scale is fitting error.
The pose is the least-squares rigid transform (rotation and translation, Kabsch/Umeyama)
of the RANSAC inliers.

The fan edge is static in the sonar frame and would pull every method towards "no
motion": outside the fan the frames are filled with the fan's median intensity (no step
for a detector or a gradient to see), keypoints are detected only a margin inside the
fan, and ECC takes the fan as its mask.

Frames and units follow ``mapping.fmt``: images have rows from far to near and columns
from port to starboard; results are the later frame's pose in the sonar frame of the
*earlier* one: forward and starboard metres, yaw in radians, clockwise (to starboard)
positive (``RelativePose``). Pixel transforms take later-frame pixels (col, row) to
earlier-frame pixels and become metric through ``SonarGrid.pixel_to_metric``, exactly as
FMT's own (``relative_from_pixels``).

The settings were chosen on the FMT test bed's sonar and seabed
(tests/mapping/test_fmt_bed.py: its preprocessed 2 cm frames, speckle of gamma shape 2),
16 pairs of random motion up to 0.3 m forward, 0.15 m starboard and 4 degrees; the
parameters' docstrings quote what the alternatives measured there. With them (median
and largest error of translation, then of yaw): ORB 9.2 and 21.7 mm, 0.09 and 0.23
degrees; SIFT answered 10 of the 16 pairs, 25 and 37 mm, 0.38 and 0.86 degrees; ECC 3.5
and 8.5 mm, 0.03 and 0.12 degrees; FMT on the same pairs 3.5 and 7.9 mm, 0.04 and 0.11
degrees. ECC from the identity can settle on a wrong optimum when the fan's texture
moves by 20 pixels or more: at 0.3 m forward, 0.1 m starboard and 3 degrees, 9 of 36
pairs (6 starting poses, 2 seabeds, 2 speckles) ended 0.24-0.51 m off.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np
import numpy.typing as npt

from mapping.fmt import FloatImage, Matrix
from mapping.grid import SonarGrid
from mapping.se2 import RelativePose

U8Image = npt.NDArray[np.uint8]
BoolImage = npt.NDArray[np.bool_]


@dataclass(frozen=True, slots=True)
class BaselineResult:
    """One baseline registration of a pair.

    relative: the later frame's pose in the earlier frame's sonar frame (forward m,
    starboard m, yaw rad clockwise; ``RelativePose``). matches: feature matches kept as
    RANSAC inliers (ECC: 0). score: the method's own quality: the inlier ratio (inliers
    over ratio-test matches) for ORB and SIFT, the final correlation coefficient for ECC.
    seconds: wall time of the ``register`` call (both frames' features and the fit).
    scale: the similarity's scale that RANSAC fitted (not used in the pose; ECC: 1).
    """

    relative: RelativePose
    matches: int
    score: float
    seconds: float
    scale: float = 1.0


def relative_from_pixels(grid: SonarGrid, later_to_earlier: npt.ArrayLike) -> RelativePose:
    """The metric relative pose of a rigid pixel transform.

    later_to_earlier: 2 x 3 or 3 x 3 matrix taking a later-frame pixel (col, row) to the
    earlier-frame pixel that sees the same seabed. Returns the later frame's pose in the
    earlier sonar frame (forward m, starboard m, yaw rad clockwise), as FMT does
    (``FmtRegistrar._relative``): M P M^-1 with M = ``grid.pixel_to_metric()``.
    """
    pixels = np.eye(3)
    matrix = np.asarray(later_to_earlier, np.float64)
    pixels[: matrix.shape[0], :] = matrix[:3]
    to_metric = grid.pixel_to_metric()
    return RelativePose.from_matrix(to_metric @ pixels @ np.linalg.inv(to_metric))


def rigid_fit(later_px: npt.ArrayLike, earlier_px: npt.ArrayLike) -> Matrix:
    """Least-squares rigid transform (3 x 3, rotation and translation, no scale) taking
    ``later_px`` points (N x 2, pixels) to ``earlier_px`` (Kabsch/Umeyama in 2-D)."""
    src = np.asarray(later_px, np.float64).reshape(-1, 2)
    dst = np.asarray(earlier_px, np.float64).reshape(-1, 2)
    src_mean, dst_mean = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - src_mean, dst - dst_mean
    # The angle that maximises sum(b . R a): atan2 of the summed cross and dot products.
    angle = math.atan2(
        float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])),
        float(np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])),
    )
    c, s = math.cos(angle), math.sin(angle)
    rotation = np.array([[c, -s], [s, c]])
    transform = np.eye(3)
    transform[:2, :2] = rotation
    transform[:2, 2] = dst_mean - rotation @ src_mean
    return transform


def fill_outside(image: FloatImage, mask: BoolImage) -> FloatImage:
    """``image`` with the pixels outside ``mask`` set to the median inside it (float32):
    the fan edge then has no step for a detector or an image gradient to see."""
    inside = image[mask]
    fill = float(np.median(inside)) if inside.size else 0.0
    return np.where(mask, image, np.float32(fill)).astype(np.float32)


def to_uint8(image: FloatImage, mask: BoolImage, clip_percent: float) -> U8Image:
    """``image`` stretched to 8 bits between the fan's ``clip_percent`` and 100 -
    ``clip_percent`` percentiles, the outside filled with the fan's median."""
    inside = image[mask]
    if inside.size == 0:
        return np.zeros(image.shape, np.uint8)
    low, high = np.percentile(inside, [clip_percent, 100.0 - clip_percent])
    span = max(float(high - low), 1e-6)
    stretched = (fill_outside(image, mask) - np.float32(low)) * np.float32(255.0 / span)
    return np.clip(np.rint(stretched), 0, 255).astype(np.uint8)


@dataclass(frozen=True, slots=True)
class OrbParams:
    """Settings of ORB + RANSAC (measured as the module says)."""

    n_features: int = 5000
    """Most keypoints kept per frame. The fan of a 2 cm grid holds about 58,000 pixels;
    OpenCV's default 500 leaves RANSAC a handful of true matches among the speckle's
    false ones. 5000 (one per 12 pixels) against 3000: 1.7 times the correct matches."""
    scale_factor: float = 1.2
    """ORB's pyramid step (OpenCV's default)."""
    n_levels: int = 3
    """ORB's pyramid levels. Two frames on one metric grid differ by no scale, and a
    keypoint of a coarse level is placed only to its level's pixel: 8 levels (OpenCV's
    default) erred 13.7 mm and 0.17 degrees at the median, 3 levels 9.2 mm and 0.09."""
    fast_threshold: int = 10
    """FAST's intensity step (grey levels of the stretched 8-bit frame): half OpenCV's
    20 finds more corners on the fan's soft texture (a few more correct matches)."""
    patch_px: int = 31
    """The BRIEF patch and the border FAST keeps clear of (OpenCV's default, pixels)."""
    presmooth_sigma_px: float = 0.0
    """Gaussian blur before detection (pixels). None: 1-2 pixels lost correct matches."""
    ratio: float = 0.9
    """Lowe's ratio test (best over second-best Hamming distance). Speckle makes binary
    descriptors' distances close: 0.8 kept 26 correct matches of 51 a pair, 0.9 kept 76
    of 416; RANSAC's 2-point samples find a model among 20 % inliers in ~100 draws."""
    edge_margin_px: int = 16
    """Keypoints are kept only this far inside the fan (pixels): half the BRIEF patch,
    so no descriptor sees the fan edge, which is static in the sonar frame."""
    clip_percent: float = 0.5
    """The fan's intensities are stretched to 8 bits between this percentile and its
    complement (speckle's rare bright pixels would otherwise set the scale)."""
    ransac_threshold_m: float = 0.06
    """Largest distance of a RANSAC inlier from where the model puts it (metres; 3
    pixels of the 2 cm grid, a keypoint placed to about a pixel in each frame). 2 and
    1.5 pixels kept fewer inliers and erred more."""
    ransac_max_iters: int = 2000
    """RANSAC's most draws (OpenCV's default)."""
    ransac_confidence: float = 0.99
    """RANSAC's confidence of having drawn one all-inlier sample (OpenCV's default)."""
    refine_iters: int = 10
    """Levenberg-Marquardt steps on the similarity's inliers (OpenCV's default)."""
    min_inliers: int = 6
    """Fewer inliers: no answer (a similarity takes 2 points; 4 more confirm it)."""
    max_scale_change: float = 0.05
    """The similarity's scale must be within this of 1, or no answer: the two frames are
    on one metric grid, and true pairs measured 0.976-1.007 (SIFT's few inliers the
    widest). Between frames of two different seabeds RANSAC still gathered 7-9 chance
    inliers of ~650 matches, at scales 0.25-0.9: a free scale lets chance agree."""


@dataclass(frozen=True, slots=True)
class SiftParams:
    """Settings of SIFT + RANSAC (measured as the module says)."""

    n_features: int = 0
    """Most keypoints kept per frame (0: all above the contrast threshold, a few
    hundred a fan)."""
    contrast_threshold: float = 0.01
    """The detector's contrast threshold: a quarter of OpenCV's 0.04, for the blurred
    frame's low contrast (2.7 times the keypoints, more correct matches)."""
    edge_threshold: float = 10.0
    """Lowe's edge-response threshold (OpenCV's default)."""
    sigma: float = 1.6
    """Lowe's base scale (OpenCV's default)."""
    n_octave_layers: int = 3
    """Scales per octave (Lowe's 3; 5 measured alike)."""
    presmooth_sigma_px: float = 3.0
    """Gaussian blur before detection (pixels). Speckle independent from ping to ping
    makes SIFT's finest keypoints and its gradient histograms differ between frames: on
    the unblurred frames 0-1 of a pair's ratio-test matches were correct, at 3 pixels
    4-15 (2 and 4 pixels: fewer)."""
    ratio: float = 0.75
    """Lowe's ratio test (best over second-best L2 distance; Lowe 2004 proposes 0.8,
    0.75 is the usual stricter choice)."""
    edge_margin_px: int = 8
    """Keypoints are kept only this far inside the fan (pixels): the fan edge is static
    in the sonar frame, and its keypoints would match at "no motion"."""
    clip_percent: float = 0.5
    """As ``OrbParams.clip_percent``."""
    ransac_threshold_m: float = 0.06
    """As ``OrbParams.ransac_threshold_m``."""
    ransac_max_iters: int = 2000
    ransac_confidence: float = 0.99
    refine_iters: int = 10
    min_inliers: int = 6
    """As ``OrbParams.min_inliers``."""
    max_scale_change: float = 0.05
    """As ``OrbParams.max_scale_change``."""


@dataclass(frozen=True, slots=True)
class EccParams:
    """Settings of ECC maximisation (measured as the module says)."""

    pyramid_levels: int = 3
    """ECC is a Gauss-Newton ascent from the identity, which converges only while the
    motion is within about the smoothed texture's correlation length (a few pixels);
    frames a survey registers are up to 15 pixels of the 2 cm grid apart, so the warp is
    found coarse to fine on a pyramid, each level half the last's size. On 40 pairs of
    the bed, the pairs that ended more than 5 cm off: 1 level 20, 2 levels 17, 3 levels
    none, 4 levels 8 (up to 0.84 m)."""
    gauss_filter_px: int = 5
    """Size of the Gaussian ECC smooths both images and the mask with at each level
    (pixels; OpenCV's default): it takes the speckle's pixel noise out of the image
    gradients."""
    max_iterations: int = 100
    """Most Gauss-Newton iterations per level; ``epsilon`` ends a level sooner once it
    has converged."""
    epsilon: float = 1e-5
    """Stop when the correlation coefficient rises by less than this (1e-6 gave the
    same poses at 1.5 times the time)."""
    mask_erode_px: int = 3
    """The fan mask ECC takes is eroded this far (pixels, at full size): its smoothing
    smears the fan edge into the pixels next to it."""


def _erode(mask: BoolImage, margin_px: int) -> BoolImage:
    if margin_px <= 0:
        return mask.astype(bool)
    size = 2 * margin_px + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    return cv2.erode(mask.astype(np.uint8), kernel).astype(bool)


class _FeatureParams(Protocol):
    """What ``OrbParams`` and ``SiftParams`` share (read-only, as they are frozen)."""

    @property
    def presmooth_sigma_px(self) -> float: ...
    @property
    def ratio(self) -> float: ...
    @property
    def edge_margin_px(self) -> int: ...
    @property
    def clip_percent(self) -> float: ...
    @property
    def ransac_threshold_m(self) -> float: ...
    @property
    def ransac_max_iters(self) -> int: ...
    @property
    def ransac_confidence(self) -> float: ...
    @property
    def refine_iters(self) -> int: ...
    @property
    def min_inliers(self) -> int: ...
    @property
    def max_scale_change(self) -> float: ...


class _FeatureRegistrar:
    """Keypoints, descriptors, ratio-test matches and a RANSAC similarity, shared by ORB
    and SIFT (``_detector`` and ``_norm`` say which)."""

    name = ""

    def __init__(self, grid: SonarGrid, mask: BoolImage, params: _FeatureParams) -> None:
        if mask.shape != grid.shape:
            raise ValueError(f"mask shape {mask.shape} differs from grid shape {grid.shape}")
        self.grid = grid
        self.mask = mask.astype(bool)
        self._params = params
        self._detect_mask = _erode(self.mask, params.edge_margin_px).astype(np.uint8) * 255
        self._threshold_px = params.ransac_threshold_m / grid.res_m

    def _detector(self) -> cv2.Feature2D:
        raise NotImplementedError

    def _norm(self) -> int:
        raise NotImplementedError

    def _features(
        self, detector: cv2.Feature2D, image: FloatImage
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.generic] | None]:
        """Keypoint positions (N x 2, pixels (col, row)) and descriptors of one frame."""
        frame = to_uint8(image, self.mask, self._params.clip_percent)
        sigma = self._params.presmooth_sigma_px
        if sigma > 0:
            frame = cv2.GaussianBlur(frame, (0, 0), sigma)
        keypoints, descriptors = detector.detectAndCompute(frame, self._detect_mask)
        points = np.array([k.pt for k in keypoints], np.float32).reshape(-1, 2)
        return points, descriptors

    def register(self, earlier: FloatImage, later: FloatImage) -> BaselineResult | None:
        """The later frame's pose in the earlier frame's sonar frame, or None when too
        few matches survive the ratio test or RANSAC finds no consensus of
        ``min_inliers``. Both frames: float32 images on this registrar's grid."""
        start = time.perf_counter()
        p = self._params
        detector = self._detector()
        earlier_points, earlier_descriptors = self._features(detector, earlier)
        later_points, later_descriptors = self._features(detector, later)
        if (
            earlier_descriptors is None
            or later_descriptors is None
            or len(earlier_points) < 2
            or len(later_points) < 2
        ):
            return None
        matcher = cv2.BFMatcher(self._norm(), crossCheck=False)
        pairs = matcher.knnMatch(later_descriptors, earlier_descriptors, k=2)
        kept = [
            pair[0]
            for pair in pairs
            if len(pair) == 2 and pair[0].distance < p.ratio * pair[1].distance
        ]
        if len(kept) < p.min_inliers:
            return None
        src = later_points[[m.queryIdx for m in kept]]
        dst = earlier_points[[m.trainIdx for m in kept]]
        similarity, inliers = cv2.estimateAffinePartial2D(
            src,
            dst,
            method=cv2.RANSAC,
            ransacReprojThreshold=self._threshold_px,
            maxIters=p.ransac_max_iters,
            confidence=p.ransac_confidence,
            refineIters=p.refine_iters,
        )
        if similarity is None or inliers is None:
            return None
        inlier = inliers.ravel().astype(bool)
        count = int(inlier.sum())
        if count < p.min_inliers:
            return None
        scale = math.hypot(float(similarity[0, 0]), float(similarity[1, 0]))
        if abs(scale - 1.0) > p.max_scale_change:
            return None
        pixels = rigid_fit(src[inlier], dst[inlier])
        return BaselineResult(
            relative_from_pixels(self.grid, pixels),
            count,
            count / len(kept),
            time.perf_counter() - start,
            scale,
        )


class OrbRegistrar(_FeatureRegistrar):
    """ORB + RANSAC (Rublee et al. 2011; Fischler & Bolles 1981) on one ``SonarGrid``
    with a fixed fan ``mask``."""

    name = "orb"

    def __init__(self, grid: SonarGrid, mask: BoolImage, params: OrbParams | None = None) -> None:
        self.params = params or OrbParams()
        super().__init__(grid, mask, self.params)

    def _detector(self) -> cv2.Feature2D:
        p = self.params
        return cv2.ORB.create(
            nfeatures=p.n_features,
            scaleFactor=p.scale_factor,
            nlevels=p.n_levels,
            edgeThreshold=p.patch_px,
            patchSize=p.patch_px,
            fastThreshold=p.fast_threshold,
        )

    def _norm(self) -> int:
        return int(cv2.NORM_HAMMING)


class SiftRegistrar(_FeatureRegistrar):
    """SIFT + RANSAC (Lowe 2004; Fischler & Bolles 1981) on one ``SonarGrid`` with a
    fixed fan ``mask``."""

    name = "sift"

    def __init__(self, grid: SonarGrid, mask: BoolImage, params: SiftParams | None = None) -> None:
        self.params = params or SiftParams()
        super().__init__(grid, mask, self.params)

    def _detector(self) -> cv2.Feature2D:
        p = self.params
        return cv2.SIFT.create(
            nfeatures=p.n_features,
            nOctaveLayers=p.n_octave_layers,
            contrastThreshold=p.contrast_threshold,
            edgeThreshold=p.edge_threshold,
            sigma=p.sigma,
        )

    def _norm(self) -> int:
        return int(cv2.NORM_L2)


_COARSE_TO_FINE = np.array([[2.0, 0.0, 0.5], [0.0, 2.0, 0.5], [0.0, 0.0, 1.0]])
"""A pixel (col, row) of a ``cv2.pyrDown`` level to the pixel of the level above: the
coarse pixel's centre sits between the fine pixels 2 i and 2 i + 1, so fine = 2 coarse +
0.5 (pixel centres at integers)."""


def finer_warp(warp: npt.ArrayLike) -> Matrix:
    """A 3 x 3 pixel transform of a ``cv2.pyrDown`` level as the same transform of the
    level above (twice the size)."""
    return np.asarray(
        _COARSE_TO_FINE @ np.asarray(warp, np.float64) @ np.linalg.inv(_COARSE_TO_FINE),
        np.float64,
    )


class EccRegistrar:
    """ECC maximisation over a Euclidean warp (Evangelidis & Psarakis 2008), coarse to
    fine, on one ``SonarGrid`` with a fixed fan ``mask``."""

    name = "ecc"

    def __init__(self, grid: SonarGrid, mask: BoolImage, params: EccParams | None = None) -> None:
        if mask.shape != grid.shape:
            raise ValueError(f"mask shape {mask.shape} differs from grid shape {grid.shape}")
        self.grid = grid
        self.mask = mask.astype(bool)
        self.params = params or EccParams()
        levels = max(int(self.params.pyramid_levels), 1)
        # The masks of each level, finest first: the fan eroded at full size, then halved.
        self._masks = [_erode(self.mask, self.params.mask_erode_px).astype(np.uint8)]
        for _ in range(levels - 1):
            finer = self._masks[-1]
            half = cv2.resize(
                finer,
                ((finer.shape[1] + 1) // 2, (finer.shape[0] + 1) // 2),
                interpolation=cv2.INTER_AREA,
            )
            self._masks.append(half)

    def _pyramid(self, image: FloatImage) -> list[FloatImage]:
        levels = [fill_outside(image, self.mask)]
        for _ in range(len(self._masks) - 1):
            levels.append(cv2.pyrDown(levels[-1]))
        return levels

    def register(self, earlier: FloatImage, later: FloatImage) -> BaselineResult | None:
        """The later frame's pose in the earlier frame's sonar frame, or None when ECC
        fails at some level (OpenCV raises when the correlation degenerates). Both
        frames: float32 images on this registrar's grid."""
        start = time.perf_counter()
        p = self.params
        criteria = (
            cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
            int(p.max_iterations),
            float(p.epsilon),
        )
        # Template = later, input = earlier: ECC's warp W then takes template (later)
        # pixels to input (earlier) pixels, the transform ``relative_from_pixels`` wants,
        # and the mask ECC takes (the input's) is the earlier fan.
        later_levels = self._pyramid(later)
        earlier_levels = self._pyramid(earlier)
        count = len(later_levels)
        warp = np.eye(3, dtype=np.float32)  # the identity at the coarsest level: no prior
        correlation = 0.0
        for level in range(count - 1, -1, -1):
            try:
                correlation, found = cv2.findTransformECC(
                    later_levels[level],
                    earlier_levels[level],
                    warp[:2].copy(),
                    cv2.MOTION_EUCLIDEAN,
                    criteria,
                    self._masks[level],
                    int(p.gauss_filter_px),
                )
            except cv2.error:
                return None
            warp = np.vstack([found, [0.0, 0.0, 1.0]]).astype(np.float32)
            if level > 0:
                warp = finer_warp(warp).astype(np.float32)
        if not math.isfinite(float(correlation)):
            return None
        return BaselineResult(
            relative_from_pixels(self.grid, warp.astype(np.float64)),
            0,
            float(correlation),
            time.perf_counter() - start,
        )


BaselineRegistrar = OrbRegistrar | SiftRegistrar | EccRegistrar

REGISTRATION_BASELINES: dict[str, type[BaselineRegistrar]] = {
    "orb": OrbRegistrar,
    "sift": SiftRegistrar,
    "ecc": EccRegistrar,
}
"""The paper's registration baselines by name (Table II)."""
