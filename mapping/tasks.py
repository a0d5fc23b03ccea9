"""Pure tasks, run in order: where the survey-end pass hands its independent work (the
loop closures' registrations) so that other processes can do it.

A task is a module-level function of one job, whose answer depends on the job alone: it
gives the same answer wherever it runs, and the results come back in the jobs' order, so
what is built from them does not depend on where or how fast they ran. ``InlinePool``
runs them here, one by one; ``daemon.workers.ProcessPool`` in worker processes.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from typing import Protocol, TypeVar

J = TypeVar("J")
R = TypeVar("R")


class TaskPool(Protocol):
    def run(self, task: Callable[[J], R], jobs: Iterable[J]) -> Iterator[R]:
        """``task(job)`` for every job, the results in the jobs' order. The jobs are
        taken as they are needed (a few ahead of the results), not all at once."""
        ...


class InlinePool:
    """Every task in this process, as its job comes."""

    def run(self, task: Callable[[J], R], jobs: Iterable[J]) -> Iterator[R]:
        for job in jobs:
            yield task(job)
