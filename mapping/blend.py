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
kept, so a pixel stores just those (``mapping.tiles``): memory is N slots a pixel however
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
