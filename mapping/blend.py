"""Blending frames into the mosaic: the paper's variance-based robust blending (Zhang et
al., Sec. III.G, Eq. 8-11) and the three baselines it is compared with (Sec. IV, Table V):
plain averaging, Hurtós et al.'s distance-based blending and Su et al.'s variance-based
blending with fixed windows. ``BlendParams.method`` chooses; each method is a per-frame
score map (``make_scorer``, in the sonar's own Cartesian frame) and a per-pixel rule over
the candidates the tiles keep (``mapping.tiles``).

"robust" (the paper's). Per frame:
  v~_i   = local variance of the frame (box window),
  v_i,s  = beta_s v_i-1,s + (1 - beta_s) v~_i        (short-term EMA, Eq. 8)
  v_i,l  = beta_l v_i-1,l + (1 - beta_l) v~_i        (long-term EMA, Eq. 9)
  s_i    = norm(v_i,s) * exp(-norm(v_i,l))           (feature score, Eq. 10),
normalised within the fan. The long-term statistic remembers what the sensor always shows
in a place of its fan (ring artefacts, the near-field edge) and the score discounts it;
the short-term statistic rewards texture seen now. The score is multiplied by the
Hamming edge taper so fan edges fade out of the mosaic.

Per mosaic pixel, over the frames that cover it: keep candidates with
s >= rho * max s, at most the N best; trim intensities farther than eta * MAD from their
median; output the s^gamma-weighted mean (Eq. 11). Only the N best candidates can ever be
kept, so a pixel stores just those (``mapping.tiles``): memory is N slots a pixel however
many frames pass over it, and frames can be added in any grouping, tile by tile.

"average": the same candidates (the robust score's N best), their plain mean.

"hurtos" (Hurtós, Cufí, Salvi, "Blending forward-looking sonar images for mosaicing",
2013): every frame that covers a pixel counts, weighted by where the pixel lies in that
frame's fan, most at the fan's centre and nothing at its edges (``hurtos_weight``); the
mosaic pixel is the weighted mean over all of them (no selection).

"su" (Su et al., "A blending method for forward-looking sonar mosaicing handling intra-
and inter-frame artifacts", Ocean Engineering 2024, doi:10.1016/j.oceaneng.2024.117249):
Eq. 10's score from plain moving averages of v~ over fixed windows of the last Ns and Nl
frames (``WindowScorer``) instead of the EMAs, candidates with s >= rho * max s kept, and
their unweighted mean: no MAD trimming, no s^gamma. These are the two limitations the
paper names ("reliance on fixed temporal windows and simple averaging"); everything else
(variance window, taper, rho, N) is the robust method's, so that the comparison isolates
them.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np
import numpy.typing as npt

FloatImage = npt.NDArray[np.float32]
Mask = npt.NDArray[np.bool_]

BLEND_METHODS = ("robust", "average", "hurtos", "su")

HURTOS_FLOOR = np.float32(1e-4)
"""Least Hurtós weight of a pixel inside the fan: its place weighs next to nothing, but a
seabed patch only a fan's rim saw still shows (no holes where frames cover)."""


@dataclass(frozen=True, slots=True)
class BlendParams:
    """The paper's defaults: beta_s 0.60, beta_l 0.97, rho 0.68, N 16, eta 2.7, gamma 1.4."""

    beta_s: float = 0.60
    beta_l: float = 0.97
    rho: float = 0.68
    top_n: int = 16
    eta: float = 2.7
    gamma: float = 1.4
    variance_window: int = 7
    """Side of the box window of the local variance (pixels)."""
    method: str = "robust"
    """"robust" (the paper's), "average" (plain mean), "hurtos" (Hurtós et al. 2013:
    weighted by the place in the fan) or "su" (Su et al. 2024: fixed windows, plain mean
    of the kept candidates); see the module docstring."""
    su_short_frames: int = 4
    """Su's short window Ns (frames): the box window equivalent to the paper's beta_s =
    0.60. An EMA with decay beta averages noise as a box of (1 + beta) / (1 - beta)
    frames does (the same variance reduction, and the same mean age beta / (1 - beta) =
    (N - 1) / 2): 4.0 frames for 0.60, so Su's statistics see as far back as the
    paper's and only the window's shape differs."""
    su_long_frames: int = 66
    """Su's long window Nl (frames): (1 + 0.97) / (1 - 0.97) = 65.7, the box equivalent
    of beta_l = 0.97. The scorer holds that many float32 variance maps of the blending
    grid: 27 MB for a 130 degree fan at 5 m range and 2 cm pixels (233 x 456), 110 MB
    at 10 m."""

    def __post_init__(self) -> None:
        if self.method not in BLEND_METHODS:
            raise ValueError(
                f"unknown blending method {self.method!r} ({', '.join(BLEND_METHODS)})"
            )
        if self.su_short_frames < 1 or self.su_long_frames < 1:
            raise ValueError("Su's windows must hold at least one frame")


def local_variance(image: FloatImage, window: int) -> FloatImage:
    """Variance of ``image`` in a ``window`` x ``window`` box around each pixel."""
    mean = cv2.blur(image, (window, window), borderType=cv2.BORDER_REFLECT)
    mean_sq = cv2.blur(image * image, (window, window), borderType=cv2.BORDER_REFLECT)
    return np.maximum(mean_sq - mean * mean, 0.0)


def _normalise(values: FloatImage, mask: Mask) -> FloatImage:
    inside = values[mask]
    if inside.size == 0:
        return np.zeros_like(values)
    lo, hi = float(inside.min()), float(inside.max())
    if hi <= lo:
        return np.zeros_like(values)
    return np.clip((values - lo) / (hi - lo), 0.0, 1.0).astype(np.float32)


def _variance_score(
    short: FloatImage, long: FloatImage, mask: Mask, taper: FloatImage | None
) -> FloatImage:
    """Eq. 10 from the two statistics, normalised within ``mask``, times the taper."""
    score = _normalise(short, mask) * np.exp(-_normalise(long, mask))
    if taper is not None:
        score *= taper
    score[~mask] = 0.0
    return score.astype(np.float32)


class FrameScorer(Protocol):
    """A frame's score map (float32, 0 outside ``mask``): what its pixels offer the tiles.

    image, mask, taper: the preprocessed frame, its fan mask and Hamming edge taper
    (``mapping.preprocess.SonarFrame``); fan_weight: its Hurtós weight map
    (``SonarFrame.fan_weight``), used by "hurtos" only."""

    def __call__(
        self,
        image: FloatImage,
        mask: Mask,
        taper: FloatImage | None = None,
        fan_weight: FloatImage | None = None,
    ) -> FloatImage: ...


class FeatureScorer:
    """Keeps the short- and long-term variance EMAs of a frame sequence (sensor frame)."""

    def __init__(self, params: BlendParams | None = None) -> None:
        self.params = params or BlendParams()
        self.short: FloatImage | None = None
        self.long: FloatImage | None = None

    def __call__(
        self,
        image: FloatImage,
        mask: Mask,
        taper: FloatImage | None = None,
        fan_weight: FloatImage | None = None,
    ) -> FloatImage:
        """The feature score map of the next frame (float32, 0 outside ``mask``);
        ``fan_weight`` is not used."""
        p = self.params
        instant = local_variance(image, p.variance_window)
        if self.short is None or self.long is None or self.short.shape != instant.shape:
            # First frame: both statistics start from it (no history to be inert about).
            self.short = instant.copy()
            self.long = instant.copy()
        else:
            self.short = (p.beta_s * self.short + (1.0 - p.beta_s) * instant).astype(np.float32)
            self.long = (p.beta_l * self.long + (1.0 - p.beta_l) * instant).astype(np.float32)
        return _variance_score(self.short, self.long, mask, taper)


class WindowScorer:
    """Su et al.'s statistics: plain moving averages of the instantaneous local variance
    over the last ``su_short_frames`` (Ns) and ``su_long_frames`` (Nl) frames, this one
    included (sensor frame); until a window is full, the mean of the frames so far. A
    frame older than Nl no longer counts at all, where the EMA forgets it only
    gradually. Running sums (float64) keep a frame's cost to adding the newest map and
    taking out the one that leaves."""

    def __init__(self, params: BlendParams | None = None) -> None:
        self.params = params or BlendParams()
        p = self.params
        self._history: deque[FloatImage] = deque(
            maxlen=max(p.su_short_frames, p.su_long_frames) + 1
        )
        self._short_sum: npt.NDArray[np.float64] | None = None
        self._long_sum: npt.NDArray[np.float64] | None = None
        self.short: FloatImage | None = None
        self.long: FloatImage | None = None

    def __call__(
        self,
        image: FloatImage,
        mask: Mask,
        taper: FloatImage | None = None,
        fan_weight: FloatImage | None = None,
    ) -> FloatImage:
        """The score map of the next frame (float32, 0 outside ``mask``); ``fan_weight``
        is not used."""
        p = self.params
        instant = local_variance(image, p.variance_window)
        if (
            self._short_sum is None
            or self._long_sum is None
            or self._short_sum.shape != instant.shape
        ):
            self._history.clear()
            self._short_sum = np.zeros(instant.shape, np.float64)
            self._long_sum = np.zeros(instant.shape, np.float64)
        self._history.append(instant)
        seen = len(self._history)
        self._short_sum += instant
        self._long_sum += instant
        if seen > p.su_short_frames:
            self._short_sum -= self._history[-p.su_short_frames - 1]
        if seen > p.su_long_frames:
            self._long_sum -= self._history[-p.su_long_frames - 1]
        self.short = (self._short_sum / min(seen, p.su_short_frames)).astype(np.float32)
        self.long = (self._long_sum / min(seen, p.su_long_frames)).astype(np.float32)
        return _variance_score(self.short, self.long, mask, taper)


def hurtos_weight(
    bearing_rad: npt.NDArray[np.floating],
    slant_m: npt.NDArray[np.floating],
    mask: Mask,
    bearing_limits: tuple[float, float],
    range_limits: tuple[float, float],
) -> FloatImage:
    """Hurtós et al.'s weight of each pixel of a frame by its place in the fan: 1 at the
    fan's centre, falling to 0 at its edges (float32, 0 outside ``mask``).

    bearing_rad, slant_m: each Cartesian pixel's beam bearing (radians, positive to
    starboard) and slant range (metres); bearing_limits: the outer beams; range_limits:
    the near (first lit) and far ends of the range band. With u the normalised distance
    to the nearer lateral edge, 2 min(b - b0, b1 - b) / (b1 - b0), and v the same in
    range, the weight is u * v: the product of the two distances in the sonar's own
    polar coordinates. Polar, because what degrades a pixel of a forward-looking sonar
    follows its beam and its range, not the Cartesian picture: the beam pattern and the
    fan's side lobes fade towards the outer beams, the near field is lit at the edge of
    the vertical beam and the far field fades with spreading and grazing. A product,
    because it reaches 0 on all four edges (the lateral edges and both range limits)
    and has its one maximum at the middle beam and the middle of the band; the fan
    mask's Euclidean distance transform would also vanish at the edges, but it is
    largest along the whole mid-range arc of a wide fan (a 130 degree fan's lateral
    edges are farther than its range edges) and so does not favour the middle beams.
    Pixels inside the fan weigh at least ``HURTOS_FLOOR``."""
    b0, b1 = bearing_limits
    r0, r1 = range_limits
    lateral = 2.0 * np.minimum(bearing_rad - b0, b1 - bearing_rad) / max(b1 - b0, 1e-12)
    radial = 2.0 * np.minimum(slant_m - r0, r1 - slant_m) / max(r1 - r0, 1e-12)
    weight = np.clip(lateral, 0.0, 1.0) * np.clip(radial, 0.0, 1.0)
    weight = np.maximum(weight, HURTOS_FLOOR)
    return np.where(mask, weight, 0.0).astype(np.float32)


class FanWeigher:
    """Hurtós et al.'s frame weights: the fan position weight (``hurtos_weight``) of each
    pixel, the same for every frame (no memory of other frames, no variance)."""

    def __init__(self, params: BlendParams | None = None) -> None:
        self.params = params or BlendParams()

    def __call__(
        self,
        image: FloatImage,
        mask: Mask,
        taper: FloatImage | None = None,
        fan_weight: FloatImage | None = None,
    ) -> FloatImage:
        """The weight map of a frame: ``fan_weight`` inside ``mask`` (the Hamming taper
        is not applied: the weight already falls to 0 at the fan's edges)."""
        if fan_weight is None:
            raise ValueError(
                "Hurtós blending weighs pixels by their place in the fan: the frame's "
                "fan_weight (mapping.preprocess.SonarFrame.fan_weight) is needed"
            )
        return np.where(mask, fan_weight, np.float32(0.0)).astype(np.float32)


def make_scorer(params: BlendParams | None = None) -> FrameScorer:
    """The frame scorer of ``params.method``: the variance EMAs ("robust", "average"),
    the fixed windows ("su") or the fan position weight ("hurtos")."""
    params = params or BlendParams()
    if params.method == "su":
        return WindowScorer(params)
    if params.method == "hurtos":
        return FanWeigher(params)
    return FeatureScorer(params)


def masked_median(values: FloatImage, keep: npt.NDArray[np.bool_]) -> FloatImage:
    """Median over the last axis of the kept values (0 where none is kept)."""
    ordered = np.sort(np.where(keep, values, np.inf), axis=-1)
    count = keep.sum(axis=-1)
    low = np.clip((count - 1) // 2, 0, None)[..., None]
    high = np.clip(count // 2, 0, None)[..., None]
    a = np.take_along_axis(ordered, low, axis=-1)[..., 0]
    b = np.take_along_axis(ordered, np.minimum(high, values.shape[-1] - 1), axis=-1)[..., 0]
    median = 0.5 * (a + b)
    return np.where(count > 0, median, 0.0).astype(np.float32)


def robust_blend(
    intensity: FloatImage,
    score: FloatImage,
    params: BlendParams,
    weight: FloatImage | None = None,
) -> tuple[FloatImage, npt.NDArray[np.bool_]]:
    """Eq. 11 over candidate stacks (..., K): rho-threshold, top N, MAD trim, s^gamma mean.

    weight: s^gamma when the caller has it already (a lookup table on quantised scores
    is ten times faster than the power). Returns the blended intensities and where there
    was any candidate."""
    shape = score.shape[:-1]
    k = score.shape[-1]
    flat_score = score.reshape(-1, k)
    best = flat_score.max(axis=1)
    # Work only on pixels with candidates: a tile is often half empty.
    rows = np.flatnonzero(best > 0.0)
    s = flat_score[rows]
    values = intensity.reshape(-1, k)[rows]
    keep = (s > 0.0) & (s >= np.float32(params.rho) * best[rows, None])
    if k > params.top_n:
        # Stacks wider than N: keep the N best of the retained.
        order = np.argsort(-np.where(keep, s, -1.0), axis=-1)
        rank = np.empty_like(order)
        np.put_along_axis(rank, order, np.arange(k), axis=-1)
        keep &= rank < params.top_n
    median = masked_median(values, keep)
    deviation = np.abs(values - median[:, None])
    mad = masked_median(deviation, keep)[:, None]
    # With MAD = 0 (identical values, or a single candidate) nothing is an outlier.
    trimmed = keep & ((deviation <= np.float32(params.eta) * mad) | (mad <= 1e-6))
    if weight is None:
        w = np.power(np.where(trimmed, s, np.float32(0.0)), np.float32(params.gamma))
    else:
        w = np.where(trimmed, weight.reshape(-1, k)[rows], np.float32(0.0))
    total = w.sum(axis=1)
    blended = np.zeros(flat_score.shape[0], np.float32)
    covered = np.zeros(flat_score.shape[0], bool)
    ok = total > 0.0
    blended[rows[ok]] = (w[ok] * values[ok]).sum(axis=1) / total[ok]
    covered[rows[ok]] = True
    return blended.reshape(shape), covered.reshape(shape)


def weighted_mean_blend(
    intensity: FloatImage,
    weight: FloatImage,
    rest_weight: FloatImage | None = None,
    rest_value: FloatImage | None = None,
) -> tuple[FloatImage, Mask]:
    """Hurtós et al.'s blend over candidate stacks (..., K): the weighted mean of every
    candidate, sum(w I) / sum(w), w 0 for empty slots. ``rest_weight`` and
    ``rest_value`` (...): the sums of w and w I of candidates held outside the stacks
    (``mapping.tiles`` keeps those a full stack pushed out). Returns the blended
    intensities and where any weight was."""
    total = weight.sum(axis=-1, dtype=np.float64)
    weighted = (weight * intensity).sum(axis=-1, dtype=np.float64)
    if rest_weight is not None and rest_value is not None:
        total = total + rest_weight
        weighted = weighted + rest_value
    covered = total > 0.0
    blended = np.where(covered, weighted / np.where(covered, total, 1.0), 0.0)
    return blended.astype(np.float32), covered


def su_blend(
    intensity: FloatImage, score: FloatImage, params: BlendParams
) -> tuple[FloatImage, Mask]:
    """Su et al.'s blend over candidate stacks (..., K): candidates with s >= rho * max s
    (s 0: an empty slot), their plain mean (no trimming, no weights). Returns the
    blended intensities and where there was any candidate."""
    best = score.max(axis=-1, keepdims=True)
    keep = (score > 0.0) & (score >= np.float32(params.rho) * best)
    count = keep.sum(axis=-1)
    covered = count > 0
    total = np.where(keep, intensity, np.float32(0.0)).sum(axis=-1, dtype=np.float64)
    blended = np.where(covered, total / np.maximum(count, 1), 0.0)
    return blended.astype(np.float32), covered
