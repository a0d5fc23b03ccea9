"""Variance-based robust blending (Zhang et al., Sec. III.G, Eq. 8-11), plus plain averaging.

Per frame, in the sonar's own (Cartesian) frame:
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
kept, so a pixel stores just those (``TopNStack``): memory is N slots a pixel however
many frames pass over it, and frames can be added in any grouping, tile by tile.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

FloatImage = npt.NDArray[np.float32]


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
    """"robust" (the paper's) or "average" (plain mean, the baseline)."""


def local_variance(image: FloatImage, window: int) -> FloatImage:
    """Variance of ``image`` in a ``window`` x ``window`` box around each pixel."""
    mean = cv2.blur(image, (window, window), borderType=cv2.BORDER_REFLECT)
    mean_sq = cv2.blur(image * image, (window, window), borderType=cv2.BORDER_REFLECT)
    return np.maximum(mean_sq - mean * mean, 0.0)


def _normalise(values: FloatImage, mask: npt.NDArray[np.bool_]) -> FloatImage:
    inside = values[mask]
    if inside.size == 0:
        return np.zeros_like(values)
    lo, hi = float(inside.min()), float(inside.max())
    if hi <= lo:
        return np.zeros_like(values)
    return np.clip((values - lo) / (hi - lo), 0.0, 1.0).astype(np.float32)


class FeatureScorer:
    """Keeps the short- and long-term variance EMAs of a frame sequence (sensor frame)."""

    def __init__(self, params: BlendParams | None = None) -> None:
        self.params = params or BlendParams()
        self.short: FloatImage | None = None
        self.long: FloatImage | None = None

    def __call__(
        self, image: FloatImage, mask: npt.NDArray[np.bool_], taper: FloatImage | None = None
    ) -> FloatImage:
        """The feature score map of the next frame (float32, 0 outside ``mask``)."""
        p = self.params
        instant = local_variance(image, p.variance_window)
        if self.short is None or self.long is None or self.short.shape != instant.shape:
            # First frame: both statistics start from it (no history to be inert about).
            self.short = instant.copy()
            self.long = instant.copy()
        else:
            self.short = (p.beta_s * self.short + (1.0 - p.beta_s) * instant).astype(np.float32)
            self.long = (p.beta_l * self.long + (1.0 - p.beta_l) * instant).astype(np.float32)
        score = _normalise(self.short, mask) * np.exp(-_normalise(self.long, mask))
        if taper is not None:
            score *= taper
        score[~mask] = 0.0
        return score.astype(np.float32)


class TopNStack:
    """Per-pixel store of the N highest-scoring (intensity, score) candidates.

    Arrays are (rows, cols, N) float32; empty slots have score 0 (a real candidate has
    score > 0). ``count`` counts every candidate ever offered, for plain averaging and
    statistics; ``total`` sums their intensities.
    """

    def __init__(self, shape: tuple[int, int], n: int) -> None:
        self.intensity = np.zeros((*shape, n), np.float32)
        self.score = np.zeros((*shape, n), np.float32)
        self.total = np.zeros(shape, np.float32)
        self.count = np.zeros(shape, np.uint16)

    @property
    def shape(self) -> tuple[int, int]:
        rows, cols = self.total.shape
        return rows, cols

    def add(
        self,
        intensity: FloatImage,
        score: FloatImage,
        valid: npt.NDArray[np.bool_],
        rows: slice = slice(None),
        cols: slice = slice(None),
    ) -> None:
        """Offer one frame's warped candidates for the sub-window (rows, cols)."""
        stack_i = self.intensity[rows, cols]
        stack_s = self.score[rows, cols]
        valid = valid & (score > 0.0)
        self.total[rows, cols] += np.where(valid, intensity, 0.0)
        self.count[rows, cols] += valid
        weakest = np.argmin(stack_s, axis=2)
        weakest_score = np.take_along_axis(stack_s, weakest[..., None], axis=2)[..., 0]
        replace = valid & (score > weakest_score)
        if not replace.any():
            return
        r, c = np.nonzero(replace)
        k = weakest[r, c]
        stack_i[r, c, k] = intensity[r, c]
        stack_s[r, c, k] = score[r, c]

    def clear(self) -> None:
        self.intensity.fill(0.0)
        self.score.fill(0.0)
        self.total.fill(0.0)
        self.count.fill(0)

    def render(self, params: BlendParams) -> tuple[FloatImage, npt.NDArray[np.bool_]]:
        """The blended image (float32 [0, 1]) and where it has data."""
        if params.method == "average":
            covered = self.count > 0
            mean = np.where(covered, self.total / np.maximum(self.count, 1), 0.0)
            return mean.astype(np.float32), covered
        return robust_blend(self.intensity, self.score, params)


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
    intensity: FloatImage, score: FloatImage, params: BlendParams
) -> tuple[FloatImage, npt.NDArray[np.bool_]]:
    """Eq. 11 over candidate stacks (..., K): rho-threshold, top N, MAD trim, s^gamma mean."""
    present = score > 0.0
    best = score.max(axis=-1, keepdims=True)
    keep = present & (score >= params.rho * best)
    if intensity.shape[-1] > params.top_n:
        # Stacks wider than N: keep the N best of the retained.
        order = np.argsort(-np.where(keep, score, -1.0), axis=-1)
        rank = np.empty_like(order)
        np.put_along_axis(rank, order, np.arange(order.shape[-1]), axis=-1)
        keep &= rank < params.top_n
    median = masked_median(intensity, keep)
    deviation = np.abs(intensity - median[..., None])
    mad = masked_median(deviation, keep)[..., None]
    # With MAD = 0 (identical values, or a single candidate) nothing is an outlier.
    trimmed = keep & ((deviation <= params.eta * mad) | (mad <= 1e-6))
    weight = np.where(trimmed, score, 0.0) ** params.gamma
    total = weight.sum(axis=-1)
    covered = total > 0.0
    blended = np.where(
        covered,
        (weight * np.where(trimmed, intensity, 0.0)).sum(axis=-1) / np.where(covered, total, 1.0),
        0.0,
    )
    return blended.astype(np.float32), covered
