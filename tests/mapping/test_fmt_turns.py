"""What a registration could save without moving its answers on pairs of known motion: no
turn made that is within the fit's own yaw uncertainty (``FmtParams.refine_tolerance_sigmas``;
off by default: on the sloping shore it doubled the lanes' disagreement)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from mapping.fmt import FmtRegistrar
from mapping.se2 import RelativePose
from tests.mapping import test_fmt_bed as bed
from tests.mapping.test_fmt_covariance import _pairs


@pytest.fixture(scope="module")
def frames() -> tuple[bed.Sonar, list[tuple[np.ndarray, np.ndarray, RelativePose]]]:
    sonar = bed.Sonar()
    seabed = bed.make_seabed(np.random.default_rng(1))
    rng = np.random.default_rng(5)
    pairs = []
    for truth in _pairs(12, 7):
        start = (rng.uniform(6.5, 7.5), rng.uniform(6.5, 7.5), rng.uniform(0, 2 * math.pi))
        earlier = sonar.frame(seabed, start, rng)
        later = sonar.frame(seabed, bed.moved(start, truth), rng)
        pairs.append((earlier, later, truth))
    return sonar, pairs


def _sigmas(covariance: np.ndarray | None) -> np.ndarray:
    assert covariance is not None
    return np.sqrt(np.diag(covariance))


def _difference(a: RelativePose, b: RelativePose) -> np.ndarray:
    return np.array(
        [a.forward_m - b.forward_m, a.starboard_m - b.starboard_m, a.yaw_rad - b.yaw_rad]
    )


def test_no_turn_within_the_fits_own_sigma_is_made(frames, monkeypatch) -> None:
    sonar, pairs = frames
    converged = sonar.registrar()  # the default: every turn to 0.02 degrees
    assert converged.params.refine_tolerance_sigmas == 0.0
    settled = FmtRegistrar(
        converged.grid, converged.mask, replace(converged.params, refine_tolerance_sigmas=1.0)
    )
    turns = {id(settled): 0, id(converged): 0}
    turned = FmtRegistrar._rotated_spectrum

    def counted(self: FmtRegistrar, *args: object) -> np.ndarray:
        turns[id(self)] += 1
        return turned(self, *args)  # type: ignore[arg-type]

    monkeypatch.setattr(FmtRegistrar, "_rotated_spectrum", counted)
    for earlier, later, truth in pairs:
        # The prior's yaw off by 0.1 degrees (two of the fit's sigmas), as a gyro's is
        # over a keyframe's second.
        prior = RelativePose(truth.forward_m, truth.starboard_m, truth.yaw_rad + 0.0017)
        answers = [
            r.register(r.prepare(earlier), r.prepare(later), prior, prior_sigma_m=0.1)
            for r in (converged, settled)
        ]
        sigma = _sigmas(answers[0].covariance)
        moved = np.abs(_difference(answers[1].relative, answers[0].relative)) / sigma
        assert np.all(moved < 1.0), moved
    assert turns[id(settled)] < turns[id(converged)], turns
