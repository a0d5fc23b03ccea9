"""Worker processes: the live engine's front (``mapping.stream_front``) in a process of
its own, so that preprocessing and registering the next pings use another core while the
engine chains, draws and re-solves the frames before them; from two workers the live loop
closures' registrations in a second; and the survey-end pass's pure tasks
(``mapping.tasks``) in a pool.

Each worker is spawned (not forked: the daemon holds threads), takes jobs in order over a
pipe whose arrays travel through shared memory (``daemon.channel``) and sends each result
back in the same order; the engine takes them in submission order, so the map does not
depend on how fast a worker runs. A worker that dies (killed, out of memory) is one line
in the log and a new worker: the jobs it had not answered go to the new one (the front's
registration starts a new chain there, the first frame on its prior, as after a gap; a
pure task's answer is the same), and the survey goes on.
"""

from __future__ import annotations

import contextlib
import functools
import multiprocessing
import multiprocessing.connection
import os
import pickle
import queue
import signal
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, replace
from itertools import islice
from typing import Any, Generic, TypeVar

from daemon.channel import Channel
from daemon.memory import keep_heap
from mapping.fmt import Registration
from mapping.frames import SonarMount
from mapping.live_closures import ClosureJob, ClosureRegistrar
from mapping.stream_front import Front, FrontJob, FrontResult
from mapping.stream_params import StreamingParams

J = TypeVar("J")
R = TypeVar("R")

POLL_S = 0.5
"""How often a wait for a result checks that the worker is alive."""


def _threads(threads: int | None) -> int:
    """OpenCV's thread count for a worker: as asked, else this process's own. Its sums'
    last bits depend on it, so a worker counts as its parent does for the map to be the
    same with and without workers."""
    if threads is not None:
        return threads
    import cv2

    return int(cv2.getNumThreads())


def default_workers() -> int:
    """``[daemon] workers = -1``: the cores this process may use, less one (the daemon's)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(cores - 1, 0)


def _serve(
    connection: multiprocessing.connection.Connection,
    make: Callable[[], Callable[[Any], Any]],
    threads: int,
) -> None:
    """A worker: ``make()`` builds what runs the jobs (a front, a closure registrar); jobs
    in, results out, in order, until ``None`` or the pipe closes.

    A thread takes the jobs off the pipe as they come: while the worker waits for the
    engine to take a result, the engine may be handing it the next job, and neither must
    wait for the other."""
    import cv2

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the daemon's own signals are its own
    cv2.setNumThreads(threads)
    keep_heap()  # the same buffers again and again, not mapped and zeroed afresh
    jobs: queue.SimpleQueue[Any] = queue.SimpleQueue()
    channel = Channel(connection)

    def take_jobs() -> None:
        while True:
            try:
                job = channel.recv()
            except (EOFError, OSError):
                job = None
            jobs.put(job)
            if job is None:
                return

    threading.Thread(target=take_jobs, name="seamap-worker-jobs", daemon=True).start()
    run = make()
    while True:
        job = jobs.get()
        if job is None:
            return
        try:
            result: Any = run(job)
        except Exception as error:  # the job's own failure, for the engine to raise
            result = Failed.of(error)
        try:
            channel.send(result)
        except (BrokenPipeError, ConnectionResetError, OSError):
            return


@dataclass(frozen=True, slots=True)
class Failed:
    """A job that raised in its worker: the engine raises ``error`` where it takes the
    result, as if the job had run in its own process. (Before, the worker ended with it,
    was started again, was given the same job and ended again, without end.)"""

    error: BaseException

    @classmethod
    def of(cls, error: BaseException) -> Failed:
        try:
            pickle.loads(pickle.dumps(error))
        except Exception:  # an exception that does not cross processes: its words do
            return cls(RuntimeError(f"{type(error).__name__}: {error}"))
        return cls(error)


def _make_front(mount: SonarMount, params: StreamingParams) -> Callable[[FrontJob], FrontResult]:
    return Front(mount, params).run


def _make_closures() -> Callable[[ClosureBatch], tuple[list[tuple[int, Registration]], float]]:
    registrar = ClosureRegistrar()

    def run(batch: ClosureBatch) -> tuple[list[tuple[int, Registration]], float]:
        started = time.perf_counter()
        answers = [(job.index, registrar.run(job)) for job in batch.jobs]
        return answers, time.perf_counter() - started

    return run


@dataclass(frozen=True, slots=True)
class ClosureBatch:
    """The live loop closures' registrations that ride with the ping ``index``."""

    index: int
    jobs: tuple[ClosureJob, ...]


class _Worker:
    """One worker process answering jobs in order (``_serve``), restarted when it dies
    with the jobs it had not answered sent again. ``index(job)`` names a job in the log."""

    def __init__(
        self,
        name: str,
        make: Callable[[], Callable[[Any], Any]],
        threads: int,
        log: Callable[[str], None],
        index: Callable[[Any], int],
        said: str | None = None,
    ) -> None:
        """``said``: the line a death is told with (else one naming the frame the
        registrations start again from)."""
        self.name = name
        self.said = said
        self.make = make
        self.threads = threads
        self.log = log
        self.index = index
        self.restarts = 0
        self._context = multiprocessing.get_context("spawn")
        self.waiting: deque[Any] = deque()
        """Jobs sent whose results have not been taken, in order."""
        self.process: Any = None
        self.channel: Channel | None = None
        self._start()

    def _start(self) -> None:
        parent, child = self._context.Pipe()
        process = self._context.Process(
            target=_serve,
            args=(child, self.make, self.threads),
            name=f"seamap-{self.name.split()[0]}",
            daemon=True,
        )
        process.start()
        child.close()
        self.process, self.channel = process, Channel(parent)

    def _restart(self) -> None:
        """The worker died: say so, start another, and give it the jobs not answered."""
        process = self.process
        code = None
        if process is not None:
            process.join(timeout=1.0)
            code = process.exitcode
        if self.said is not None:
            self.log(f"{self.said} (pid {process.pid if process else '?'}, exit code {code})")
        else:
            first = self.index(self.waiting[0]) if self.waiting else None
            resumed = f"; frames from {first} are registered anew" if first is not None else ""
            self.log(
                f"mapping worker ({self.name}, pid {process.pid if process else '?'}) "
                f"ended with exit code {code}: restarted{resumed}"
            )
        if self.channel is not None:
            self.channel.close()
        self.restarts += 1
        self._start()
        for job in self.waiting:
            self._send(job)

    def _send(self, job: Any) -> None:
        assert self.channel is not None
        try:
            self.channel.send(job)
        except (BrokenPipeError, ConnectionResetError, OSError):
            self._restart()

    def submit(self, job: Any) -> None:
        self.waiting.append(job)
        self._send(job)

    def ready(self) -> bool:
        if not self.waiting:
            return False
        assert self.channel is not None
        try:
            if self.channel.poll(0):
                return True
        except (EOFError, OSError):
            pass
        if not self.process.is_alive():
            self._restart()
        return False

    def result(self) -> Any:
        """The next job's result (waits for it)."""
        if not self.waiting:
            raise RuntimeError("no job is waiting for a result")
        while True:
            channel = self.channel
            assert channel is not None
            try:
                if channel.poll(POLL_S):
                    result = channel.recv()
                    self.waiting.popleft()
                    break
            except (EOFError, OSError):
                self._restart()
                continue
            if not self.process.is_alive():
                self._restart()
        if isinstance(result, Failed):
            raise result.error
        return result

    def close(self) -> None:
        """Stop the worker (it finishes the job it has, drops the rest)."""
        channel, process = self.channel, self.process
        self.channel = self.process = None
        self.waiting.clear()
        if channel is not None:
            with contextlib.suppress(OSError):
                channel.send(None)
            channel.close()
        if process is not None:
            process.join(timeout=5.0)
            if process.is_alive():
                process.kill()
                process.join(timeout=5.0)


class ProcessFront:
    """The front stage in a worker process (``mapping.stream_front.FrontStage``); with
    ``side``, the live loop closures' registrations in a second one (they come in lumps,
    one registration on the blending grid every second or so, that would hold up the
    pings behind them), their results joined to the front's result of the ping they rode
    with, so the engine sees the same sequence either way.

    ``log``: where a worker's death and restart is said (one line each)."""

    def __init__(
        self,
        mount: SonarMount,
        params: StreamingParams,
        log: Callable[[str], None] | None = None,
        threads: int | None = None,
        side: bool = False,
    ) -> None:
        self.mount = mount
        self.params = params
        self.log = log or (lambda _line: None)
        self.threads = _threads(threads)
        self.side = side
        """The live closures' registrations run in a worker of their own."""
        self._front = _Worker(
            "front stage",
            functools.partial(_make_front, mount, params),
            self.threads,
            self.log,
            lambda job: int(job.index),
        )
        self._side = (
            _Worker("live closures", _make_closures, self.threads, self.log, lambda b: int(b.index))
            if side
            else None
        )

    @property
    def restarts(self) -> int:
        return self._front.restarts + (self._side.restarts if self._side is not None else 0)

    @property
    def pid(self) -> int | None:
        """The front worker's process id."""
        process = self._front.process
        return None if process is None else int(process.pid)

    @property
    def pids(self) -> list[int]:
        """Every worker's process id (for memory accounting)."""
        workers = [self._front, *([self._side] if self._side is not None else [])]
        return [int(w.process.pid) for w in workers if w.process is not None]

    def submit(self, job: FrontJob) -> None:
        if self._side is not None and job.closures:
            self._side.submit(ClosureBatch(job.index, job.closures))
            job = replace(job, closures=())
        self._front.submit(job)

    def ready(self) -> bool:
        if not self._front.ready():
            return False
        side = self._side
        if (
            side is None
            or not side.waiting
            or side.waiting[0].index != self._front.waiting[0].index
        ):
            return True
        return side.ready()

    def result(self) -> FrontResult:
        expected = self._front.waiting[0].index if self._front.waiting else None
        result: FrontResult = self._front.result()
        if result.index != expected:
            raise RuntimeError(f"the front worker answered frame {result.index} for {expected}")
        side = self._side
        if side is not None and side.waiting and side.waiting[0].index == result.index:
            answers, seconds = side.result()
            result.closures = tuple(answers)
            result.seconds["closure registration"] = seconds
        return result

    def close(self) -> None:
        """Stop the workers (each finishes the job it has, drops the rest)."""
        self._front.close()
        if self._side is not None:
            self._side.close()


def live_front(
    mount: SonarMount,
    params: StreamingParams,
    workers: int,
    log: Callable[[str], None] | None = None,
    threads: int | None = None,
) -> ProcessFront | None:
    """Where the live engine's front runs with ``workers`` worker processes (``[daemon]
    workers``; -1: ``default_workers``): in a worker from one on (from two, the live
    loop closures' registrations in a second), else (None) in the engine's own
    process."""
    if workers < 0:
        workers = default_workers()
    if workers < 1:
        return None
    return ProcessFront(mount, params, log, threads, side=workers >= 2)


def _run_task(item: tuple[Callable[[Any], Any], Any]) -> Any:
    task, job = item
    return task(job)


def _make_task_runner() -> Callable[[tuple[Callable[[Any], Any], Any]], Any]:
    return _run_task


class ProcessPool:
    """Pure tasks (``mapping.tasks``) in ``workers`` worker processes (``_Worker``: their
    arrays through shared memory, not pickled through the pipe), handed out in turn, at
    most ``ahead`` jobs out at once in ``run``, the results in the jobs' order. A worker
    that dies is one line in the log and a new worker; the jobs it had out are run again
    (a pure task's answer is the same), so nothing is lost and nothing changes."""

    def __init__(
        self,
        workers: int,
        log: Callable[[str], None] | None = None,
        threads: int | None = None,
        ahead: int | None = None,
    ) -> None:
        self.workers = max(workers, 1)
        self.log = log or (lambda _line: None)
        self.threads = _threads(threads)
        self.ahead = ahead if ahead is not None else 2 * self.workers
        self._workers = [
            _Worker(
                "pool",
                _make_task_runner,
                self.threads,
                self.log,
                lambda _job: -1,
                said="a mapping worker died: it is started again and its tasks run again",
            )
            for _ in range(self.workers)
        ]
        self._handles: list[deque[_Handle[Any]]] = [deque() for _ in range(self.workers)]
        self._turn = 0

    @property
    def restarts(self) -> int:
        return sum(worker.restarts for worker in self._workers)

    def run(self, task: Callable[[J], R], jobs: Iterable[J]) -> Iterator[R]:
        out: deque[_Handle[R]] = deque()
        remaining = iter(jobs)
        while True:
            out.extend(self.submit(task, job) for job in islice(remaining, self.ahead - len(out)))
            if not out:
                return
            yield out.popleft().result()

    def submit(self, task: Callable[[J], R], job: J) -> _Handle[R]:
        which = self._turn
        self._turn = (self._turn + 1) % self.workers
        handle: _Handle[R] = _Handle(self, which)
        self._workers[which].submit((task, job))
        self._handles[which].append(handle)
        return handle

    def _answer(self, which: int, handle: _Handle[Any]) -> None:
        """Take worker ``which``'s results, in order, until ``handle``'s is in."""
        handles = self._handles[which]
        while not handle.done:
            first = handles.popleft()
            first.value = self._workers[which].result()
            first.done = True

    def pids(self) -> list[int]:
        """The worker processes' ids (for memory accounting)."""
        return [int(w.process.pid) for w in self._workers if w.process is not None]

    def close(self) -> None:
        for worker in self._workers:
            worker.close()


class _Handle(Generic[R]):
    """A task submitted to a ``ProcessPool``: its result once its worker answered."""

    def __init__(self, pool: ProcessPool, which: int) -> None:
        self._pool = pool
        self._which = which
        self.done = False
        self.value: Any = None

    def result(self) -> R:
        if not self.done:
            self._pool._answer(self._which, self)
        value: R = self.value
        return value


def task_pool(
    workers: int, log: Callable[[str], None] | None = None, threads: int | None = None
) -> ProcessPool | None:
    """The survey-end pass's pool with ``workers`` worker processes (-1: ``default_workers``;
    None for none: its tasks then run in the pass's own process)."""
    if workers < 0:
        workers = default_workers()
    return ProcessPool(workers, log, threads) if workers >= 1 else None
