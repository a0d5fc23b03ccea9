"""Table I: the preprocessing ablation (Zhang et al., Sec. IV, Table I).

Each of the paper's nine configurations (row equalisation, median or non-local-means
denoising, CLAHE, Gaussian blur) preprocesses the same frames; per configuration the mean
image metrics of the Cartesian frames (``tools.evaluation.metrics.image_metrics``: entropy,
variance, RMS contrast, Tenengrad, variance of the Laplacian, on intensities in [0, 1]
within the fan) and the similarity score, the mean FMT correlation peak of each sampled
frame registered to the next one (the paper's SS). Frames: every ``every``-th ping and its
successor.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from mapping.fmt import FmtRegistrar, PreparedFrame
from mapping.frames import LocalRegistration, SonarFrame, SonarMount
from mapping.preprocess import PreprocessParams
from mapping.samples import Ping
from tools.evaluation.metrics import image_metrics


@dataclass(frozen=True)
class Configuration:
    """One row of Table I: what is switched on, and the parameters that do it."""

    name: str
    equalize: bool
    denoise: str
    """"none", "median" or "nlm"."""
    clahe: bool
    blur: bool

    @property
    def params(self) -> PreprocessParams:
        """The preprocessing of this row; the histogram matching to the first frame that
        precedes CLAHE in the pipeline goes with CLAHE."""
        return PreprocessParams(
            equalize_rows=self.equalize,
            histogram_match=self.clahe,
            clahe=self.clahe,
            denoise=self.denoise,
            blur=self.blur,
        )


CONFIGURATIONS = (
    Configuration("raw", False, "none", False, False),
    Configuration("eq", True, "none", False, False),
    Configuration("eq+median", True, "median", False, False),
    Configuration("eq+nlm", True, "nlm", False, False),
    Configuration("clahe", False, "none", True, False),
    Configuration("eq+clahe (default)", True, "none", True, False),
    Configuration("eq+median+clahe", True, "median", True, False),
    Configuration("eq+nlm+clahe", True, "nlm", True, False),
    Configuration("eq+clahe+blur", True, "none", True, True),
)
"""The paper's nine rows, in its order."""

METRICS = ("entropy", "variance", "rms_contrast", "tenengrad", "variance_of_laplacian")


def preprocessing_table(
    pings: Callable[[], Iterable[Ping]],
    mount: SonarMount,
    every: int = 10,
) -> dict[str, dict[str, float]]:
    """Per configuration (by name): the mean metrics over the sampled frames and
    ``similarity`` (the mean FMT peak of each sampled frame against its successor),
    ``frames`` (how many were measured). One pass over the pings, every configuration
    preprocessing the sampled ones."""
    every = max(int(every), 1)
    locals_ = [LocalRegistration(mount, c.params) for c in CONFIGURATIONS]
    rows: list[list[dict[str, float]]] = [[] for _ in CONFIGURATIONS]
    scores: list[list[float]] = [[] for _ in CONFIGURATIONS]
    previous: list[PreparedFrame | None] = [None] * len(CONFIGURATIONS)
    for index, ping in enumerate(pings()):
        if index % every not in (0, 1):
            continue
        for k, local in enumerate(locals_):
            frame: SonarFrame = local.frame(ping)
            registrar = local.registrar
            assert isinstance(registrar, FmtRegistrar)
            if index % every == 0:
                rows[k].append(image_metrics(frame.image.astype(float), frame.mask))
                previous[k] = registrar.prepare(frame.coarse)
            else:
                earlier = previous[k]
                if earlier is not None:
                    later = registrar.prepare(frame.coarse)
                    scores[k].append(registrar.register(earlier, later).score)
                previous[k] = None
    table: dict[str, dict[str, float]] = {}
    for configuration, measured, similar in zip(CONFIGURATIONS, rows, scores, strict=True):
        if not measured:
            continue
        means = {key: float(np.mean([r[key] for r in measured])) for key in METRICS}
        means["similarity"] = float(np.mean(similar)) if similar else float("nan")
        means["frames"] = float(len(measured))
        table[configuration.name] = means
    return table
