"""Pure tasks, run in order: where the survey-end pass hands its independent work (the
loop closures' registrations) so that other processes can do it.

A task is a module-level function of one job, whose answer depends on the job alone: it
gives the same answer wherever it runs, and the results come back in the jobs' order, so
what is built from them does not depend on where or how fast they ran. ``InlinePool``
runs them here, one by one; ``daemon.workers.ProcessPool`` in worker processes.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from typing import Any, Generic, Protocol, TypeVar

J = TypeVar("J")
R = TypeVar("R")
R_co = TypeVar("R_co", covariant=True)


class TaskHandle(Protocol[R_co]):
    def result(self) -> R_co:
        """The task's answer (waits for it)."""
        ...


class TaskPool(Protocol):
    workers: int
    """Tasks that run at once."""

    def run(self, task: Callable[[J], R], jobs: Iterable[J]) -> Iterator[R]:
        """``task(job)`` for every job, the results in the jobs' order. The jobs are
        taken as they are needed (a few ahead of the results), not all at once."""
        ...

    def submit(self, task: Callable[[J], R], job: J) -> TaskHandle[R]:
        """Start ``task(job)``; its handle gives the answer. An answer never asked for
        is simply dropped."""
        ...


class _Done(Generic[R]):
    def __init__(self, task: Callable[[J], R], job: J) -> None:
        self._task: Callable[[Any], R] = task
        self._job: Any = job

    def result(self) -> R:
        return self._task(self._job)


class InlinePool:
    """Every task in this process, as its job comes (a submitted one when its answer is
    asked for)."""

    workers = 1

    def run(self, task: Callable[[J], R], jobs: Iterable[J]) -> Iterator[R]:
        for job in jobs:
            yield task(job)

    def submit(self, task: Callable[[J], R], job: J) -> TaskHandle[R]:
        return _Done(task, job)
