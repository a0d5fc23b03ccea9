"""Worker processes for the live engine's stages: the front (``mapping.stream_front``) in
a process of its own, so that preprocessing and registering the next pings use another
core while the engine chains, draws and re-solves the frames before them.

The worker is spawned (not forked: the daemon holds threads), takes jobs in order over a
pipe and sends each result back in the same order; the engine takes them in submission
order, so the map does not depend on how fast the worker runs. A worker that dies (killed,
out of memory) is one line in the log and a new worker: the jobs it had not answered go to
the new one, whose registration starts a new chain there (the first frame on its prior,
as after a gap), and the survey goes on.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import multiprocessing.connection
import os
import queue
import signal
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from itertools import islice
from typing import Any, Generic, TypeVar

from daemon.channel import Channel
from mapping.frames import SonarMount
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


def _front_main(
    connection: multiprocessing.connection.Connection,
    mount: SonarMount,
    params: StreamingParams,
    threads: int,
) -> None:
    """The worker: jobs in, results out, in order, until ``None`` or the pipe closes.

    A thread takes the jobs off the pipe as they come: while the worker waits for the
    engine to take a result (a result is larger than the pipe holds), the engine may be
    handing it the next job, and neither must wait for the other."""
    import cv2

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the daemon's own signals are its own
    cv2.setNumThreads(threads)
    jobs: queue.SimpleQueue[FrontJob | None] = queue.SimpleQueue()
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

    threading.Thread(target=take_jobs, name="seamap-front-jobs", daemon=True).start()
    front = Front(mount, params)
    while True:
        job = jobs.get()
        if job is None:
            return
        try:
            channel.send(front.run(job))
        except (BrokenPipeError, ConnectionResetError, OSError):
            return


class ProcessFront:
    """The front stage in a worker process (``mapping.stream_front.FrontStage``).

    ``log``: where a worker's death and restart is said (one line each)."""

    def __init__(
        self,
        mount: SonarMount,
        params: StreamingParams,
        log: Callable[[str], None] | None = None,
        threads: int | None = None,
    ) -> None:
        self.mount = mount
        self.params = params
        self.log = log or (lambda _line: None)
        self.threads = _threads(threads)
        self.restarts = 0
        self._context = multiprocessing.get_context("spawn")
        self._waiting: deque[FrontJob] = deque()
        """Jobs sent whose results have not been taken, in order."""
        self._process: Any = None
        self._connection: Channel | None = None
        self._start()

    @property
    def pid(self) -> int | None:
        """The worker's process id."""
        return None if self._process is None else int(self._process.pid)

    def _start(self) -> None:
        parent, child = self._context.Pipe()
        process = self._context.Process(
            target=_front_main,
            args=(child, self.mount, self.params, self.threads),
            name="seamap-front",
            daemon=True,
        )
        process.start()
        child.close()
        self._process, self._connection = process, Channel(parent)

    def _restart(self) -> None:
        """The worker died: say so, start another, and give it the jobs not answered."""
        process = self._process
        code = None
        if process is not None:
            process.join(timeout=1.0)
            code = process.exitcode
        first = self._waiting[0].index if self._waiting else None
        resumed = f"; frames from {first} are registered anew" if first is not None else ""
        self.log(
            f"mapping worker (front stage, pid {process.pid if process else '?'}) "
            f"ended with exit code {code}: restarted{resumed}"
        )
        if self._connection is not None:
            self._connection.close()
        self.restarts += 1
        self._start()
        for job in self._waiting:
            self._send(job)

    def _send(self, job: FrontJob) -> None:
        assert self._connection is not None
        try:
            self._connection.send(job)
        except (BrokenPipeError, ConnectionResetError, OSError):
            self._restart()

    def submit(self, job: FrontJob) -> None:
        self._waiting.append(job)
        self._send(job)

    def ready(self) -> bool:
        if not self._waiting:
            return False
        assert self._connection is not None
        try:
            if self._connection.poll(0):
                return True
        except (EOFError, OSError):
            pass
        if not self._process.is_alive():
            self._restart()
        return False

    def result(self) -> FrontResult:
        if not self._waiting:
            raise RuntimeError("no job is waiting for a result")
        while True:
            connection = self._connection
            assert connection is not None
            try:
                if connection.poll(POLL_S):
                    result: FrontResult = connection.recv()
                    job = self._waiting.popleft()
                    if result.index != job.index:
                        raise RuntimeError(
                            f"the front worker answered frame {result.index} for {job.index}"
                        )
                    return result
            except (EOFError, OSError):
                self._restart()
                continue
            if not self._process.is_alive():
                self._restart()

    def close(self) -> None:
        """Stop the worker (it finishes the job it has, drops the rest)."""
        connection, process = self._connection, self._process
        self._connection = self._process = None
        self._waiting.clear()
        if connection is not None:
            with contextlib.suppress(OSError):
                connection.send(None)
            connection.close()
        if process is not None:
            process.join(timeout=5.0)
            if process.is_alive():
                process.kill()
                process.join(timeout=5.0)


def live_front(
    mount: SonarMount,
    params: StreamingParams,
    workers: int,
    log: Callable[[str], None] | None = None,
    threads: int | None = None,
) -> ProcessFront | None:
    """Where the live engine's front runs with ``workers`` worker processes (``[daemon]
    workers``; -1: ``default_workers``): in a worker from one on, else (None) in the
    engine's own process."""
    if workers < 0:
        workers = default_workers()
    return ProcessFront(mount, params, log, threads) if workers >= 1 else None


def _pool_worker_init(threads: int) -> None:
    import cv2

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    cv2.setNumThreads(threads)


class ProcessPool:
    """Pure tasks (``mapping.tasks``) in ``workers`` worker processes, at most ``ahead``
    jobs out at once, the results in the jobs' order. A worker that dies is one line in
    the log and a new pool; the jobs it had out are run again (a pure task's answer is
    the same), so nothing is lost and nothing changes."""

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
        self.restarts = 0
        self._executor = self._start()

    def _start(self) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(
            self.workers,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_pool_worker_init,
            initargs=(self.threads,),
        )

    def run(self, task: Callable[[J], R], jobs: Iterable[J]) -> Iterator[R]:
        out: deque[_Handle[R]] = deque()
        remaining = iter(jobs)
        while True:
            out.extend(self.submit(task, job) for job in islice(remaining, self.ahead - len(out)))
            if not out:
                return
            yield out.popleft().result()

    def submit(self, task: Callable[[J], R], job: J) -> _Handle[R]:
        return _Handle(self, task, job)

    def _recover(self, broken: ProcessPoolExecutor) -> None:
        """The pool ``broken`` lost a worker: start another pool (once for all the tasks
        it had out)."""
        if self._executor is not broken:
            return
        self.restarts += 1
        self.log("a mapping worker died: the pool is started again and its tasks run again")
        broken.shutdown(wait=False, cancel_futures=True)
        self._executor = self._start()

    def pids(self) -> list[int]:
        """The worker processes' ids (for memory accounting)."""
        processes = getattr(self._executor, "_processes", None) or {}
        return [int(pid) for pid in processes]

    def close(self) -> None:
        self._executor.shutdown(wait=True, cancel_futures=True)


class _Handle(Generic[R]):
    """A task submitted to a ``ProcessPool``: run again in the new pool if a worker died."""

    def __init__(self, pool: ProcessPool, task: Callable[[J], R], job: J) -> None:
        self._pool = pool
        self._task: Callable[[Any], R] = task
        self._job: Any = job
        self._future = self._submit()

    def _submit(self) -> Future[R]:
        """Hand the task to the pool's executor; one found broken is replaced first."""
        while True:
            self._executor = self._pool._executor
            try:
                return self._executor.submit(self._task, self._job)
            except BrokenProcessPool:
                self._pool._recover(self._executor)

    def result(self) -> R:
        while True:
            try:
                return self._future.result()
            except BrokenProcessPool:
                self._pool._recover(self._executor)
                self._future = self._submit()


def task_pool(
    workers: int, log: Callable[[str], None] | None = None, threads: int | None = None
) -> ProcessPool | None:
    """The survey-end pass's pool with ``workers`` worker processes (-1: ``default_workers``;
    None for none: its tasks then run in the pass's own process)."""
    if workers < 0:
        workers = default_workers()
    return ProcessPool(workers, log, threads) if workers >= 1 else None
