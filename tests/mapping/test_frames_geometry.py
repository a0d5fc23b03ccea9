"""The fan geometry follows the pings: kept while it holds, rebuilt when the sonar's
range or beams change (the Oculus changes range mid-survey)."""

from __future__ import annotations

import numpy as np

from mapping.frames import LocalRegistration, SonarMount
from mapping.samples import Ping


def _ping(t: float, n_ranges: int, resolution_m: float, bearings: np.ndarray) -> Ping:
    rng = np.random.default_rng(int(t * 10))
    image = rng.integers(0, 255, (n_ranges, bearings.size), dtype=np.uint8)
    return Ping(t, int(t * 10), 2, 1.2e6, resolution_m, bearings, image)


def test_the_geometry_is_kept_while_the_pings_share_it_and_rebuilt_when_they_do_not() -> None:
    local = LocalRegistration(SonarMount(altitude_m=1.0, tilt_rad=0.35))
    bearings = np.linspace(-1.13, 1.13, 128)
    local.frame(_ping(0.0, 200, 0.02, bearings))
    first = local.preprocessor
    assert first is not None
    # The same geometry in new arrays (each ping decodes its own): the same tables.
    local.frame(_ping(0.1, 200, 0.02, bearings.copy()))
    assert local.preprocessor is first
    # A longer range: new tables, a longer grid.
    local.frame(_ping(0.2, 200, 0.03, bearings))
    assert local.preprocessor is not first
    longer = local.preprocessor
    assert longer is not None and longer.grid is not None and first.grid is not None
    assert longer.grid.shape[0] > first.grid.shape[0]
    # Other beams (a narrower fan) at that range: rebuilt again.
    local.frame(_ping(0.3, 200, 0.03, bearings * 0.5))
    assert local.preprocessor is not longer
    assert local.preprocessor is not None and local.preprocessor.grid is not None
    assert local.preprocessor.grid.shape[1] < longer.grid.shape[1]
