"""Settings of the fuzz tests: a few hundred inputs each in ``make test``, as many as
``SEAMAP_FUZZ_EXAMPLES`` asks in ``make fuzz`` (100,000 each: the framer and message
parsers, the log readers and the config loader, in-process)."""

from __future__ import annotations

import os

from hypothesis import HealthCheck, settings

FUZZ_ENV = "SEAMAP_FUZZ_EXAMPLES"


def fuzz(default: int = 150) -> settings:
    """Hypothesis settings for a fuzz test (mark it ``@pytest.mark.fuzz`` too)."""
    examples = int(os.environ.get(FUZZ_ENV, default))
    if examples > default:  # at depth: no example database to grow on disk
        return settings(
            max_examples=examples, deadline=None, database=None,
            suppress_health_check=list(HealthCheck),
        )  # fmt: skip
    return settings(max_examples=examples, deadline=None, suppress_health_check=list(HealthCheck))
