"""The survey recorder: every sonar message and MAVLink packet on disk, first.

Each recorder opens one new *segment* in the survey folder (CONTRACT: the folder
``state_dir/surveys/{survey}/`` holds ``.oculus`` and ``.tlog`` files, one or more segments
each): ``sonar-{NNN}.oculus`` (Oculus v1 log) and ``nav-{NNN}.tlog`` (each MAVLink packet
preceded by its 8-byte big-endian UNIX-microsecond receive time), NNN the next number free
in the folder. Files are opened exclusively, so a restart after a crash or ``kill -9``
starts a new segment and never touches the old ones.

Items are appended at once into a buffer that is pushed to the operating system whenever
``flush_interval_s`` has passed since the last push (checked on every item and by
``poll``), and ``os.fsync``-ed at most once a second: a power cut loses about a second.
With ``fsync_in_background`` the fsync runs on a worker thread (one at a time), so a slow
SD card never stalls the event loop that stamps the next messages.
Both file formats tolerate a cut tail (the readers report it), so a file is always
readable up to the last complete item.

Full disk: free space on the survey's filesystem is probed (cached ~1 s) before writing;
below ``min_free_bytes``, or on any OSError from the files (ENOSPC, EIO, ...), recording
stops cleanly: buffers flushed as far as possible, files closed, ``stats.full`` /
``stats.stop_reason`` set, one warning logged. Only the "stop" policy exists (no
rotation or deletion of old segments). The recorder never raises into its caller after
construction; ``record_*`` return whether the item was recorded.
"""

from __future__ import annotations

import errno
import logging
import os
import re
import shutil
import struct
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Literal

from drivers.oculus.logfile import OculusLogWriter
from drivers.oculus.protocol import OculusFormatError

log = logging.getLogger(__name__)

MIN_FREE_BYTES = 200 * 1024 * 1024
FSYNC_INTERVAL_S = 1.0
DISK_CHECK_INTERVAL_S = 1.0
SONAR_PATTERN = re.compile(r"sonar-(\d{3,})\.oculus")
NAV_PATTERN = re.compile(r"nav-(\d{3,})\.tlog")
_STAMP = struct.Struct(">Q")


def sonar_name(segment: int) -> str:
    """File name of segment ``segment``'s sonar log."""
    return f"sonar-{segment:03d}.oculus"


def nav_name(segment: int) -> str:
    """File name of segment ``segment``'s MAVLink log."""
    return f"nav-{segment:03d}.tlog"


def _numbered(survey_dir: Path, pattern: re.Pattern[str]) -> list[tuple[int, Path]]:
    try:
        entries = list(survey_dir.iterdir())
    except FileNotFoundError:
        return []
    found = []
    for path in entries:
        match = pattern.fullmatch(path.name)
        if match:
            found.append((int(match.group(1)), path))
    return sorted(found)


def segments(survey_dir: str | os.PathLike[str]) -> tuple[list[Path], list[Path]]:
    """(sonar logs, nav logs) of a survey folder, each in segment order (for replay)."""
    folder = Path(survey_dir)
    sonar = [path for _, path in _numbered(folder, SONAR_PATTERN)]
    nav = [path for _, path in _numbered(folder, NAV_PATTERN)]
    return sonar, nav


def next_segment(survey_dir: str | os.PathLike[str]) -> int:
    """The first segment number above every sonar or nav segment in the folder (from 1)."""
    folder = Path(survey_dir)
    used = [n for n, _ in _numbered(folder, SONAR_PATTERN) + _numbered(folder, NAV_PATTERN)]
    return max(used, default=0) + 1


def free_bytes(path: Path) -> int:
    """Bytes free to an unprivileged writer on ``path``'s filesystem."""
    return shutil.disk_usage(path).free


class TlogWriter:
    """Append-only ``.tlog`` writer: 8-byte big-endian UNIX µs stamp, then the packet.

    Refuses to replace an existing file. One ``write`` per record keeps the file a
    sequence of whole records as far as the OS allows.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.items_written = 0
        self._file: BinaryIO = open(self.path, "xb")  # noqa: SIM115 - closed by close()

    def write(self, packet: bytes, time: float) -> int:
        """Append one packet received at ``time`` (UNIX s); the bytes written."""
        record = _STAMP.pack(round(time * 1e6)) + bytes(packet)
        self._file.write(record)
        self.items_written += 1
        return len(record)

    def flush(self) -> None:
        """Push buffered records to the operating system."""
        self._file.flush()

    def close(self) -> None:
        """Flush and close (the file is closed even if the flush fails)."""
        self._file.close()


@dataclass
class StreamStats:
    """What one stream (sonar or nav) has recorded in this segment.

    items / bytes count what was accepted into the write buffer (file bytes, headers
    included); after a failed flush the last second of them may not be on disk.
    """

    items: int = 0
    bytes: int = 0
    rejected: int = 0
    """Items refused as malformed (sonar: not one whole Oculus message)."""
    dropped: int = 0
    """Items offered after recording stopped."""


@dataclass
class RecorderStats:
    """Counters of one recorder, for the daemon's status."""

    segment: int = 0
    """This recorder's segment number (0: none opened)."""
    segments: int = 0
    """Segments in the survey folder, this one included."""
    sonar: StreamStats = field(default_factory=StreamStats)
    nav: StreamStats = field(default_factory=StreamStats)
    flushes: int = 0
    fsyncs: int = 0
    errors: int = 0
    """OSErrors met (write, flush, fsync, free-space probe, open)."""
    full: bool = False
    """Recording stopped because the disk is (nearly) full."""
    stopped: bool = False
    stop_reason: str | None = None


class SurveyRecorder:
    """Record one survey segment: sonar messages to an .oculus, MAVLink packets to a .tlog.

    ``clock`` (monotonic seconds) paces flushes, fsyncs and free-space probes; item times
    are the UNIX receive times the caller passes. ``free_space(path)`` gives the free bytes
    of ``path``'s filesystem (default ``shutil.disk_usage``). ``on_full``: only "stop".
    The segment is opened here; if that fails (or the disk is already full) the recorder
    is stopped from the start, with ``stats.stop_reason`` saying why.
    """

    def __init__(
        self,
        survey_dir: str | os.PathLike[str],
        *,
        flush_interval_s: float = 1.0,
        min_free_bytes: int = MIN_FREE_BYTES,
        on_full: Literal["stop"] = "stop",
        clock: Callable[[], float] = time.monotonic,
        free_space: Callable[[Path], int] = free_bytes,
        start_time: float | None = None,
        fsync_in_background: bool = False,
    ) -> None:
        if on_full != "stop":
            raise ValueError(f"on_full {on_full!r}: only 'stop' is implemented")
        if flush_interval_s < 0:
            raise ValueError("flush_interval_s must be >= 0")
        self.survey_dir = Path(survey_dir)
        self.flush_interval_s = flush_interval_s
        self.min_free_bytes = min_free_bytes
        self.stats = RecorderStats()
        self.sonar_path: Path | None = None
        self.nav_path: Path | None = None
        self._clock = clock
        self._free_space = free_space
        self._sonar: OculusLogWriter | None = None
        self._nav: TlogWriter | None = None
        self._dirty = False
        self._unsynced = False
        self._fsyncer = (
            ThreadPoolExecutor(1, thread_name_prefix="seamap-fsync")
            if fsync_in_background
            else None
        )
        self._fsync_job: Future[None] | None = None
        self._free_probe_at = -float("inf")
        self._free_at_probe = 0
        self._written_since_probe = 0
        now = clock()
        self._last_flush = self._last_fsync = now
        try:
            self.survey_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            self._fail(f"cannot create {self.survey_dir}: {exc.strerror or exc}")
            return
        if not self._space_ok(0):
            return
        self._open(start_time)

    # --- public ---------------------------------------------------------------------------

    @property
    def recording(self) -> bool:
        """Whether items are still being recorded."""
        return not self.stats.stopped

    def record_sonar(self, message: bytes, time: float) -> bool:
        """Append one raw Oculus message received at ``time`` (UNIX s); whether recorded."""
        stream = self.stats.sonar
        if self._sonar is None:
            stream.dropped += 1
            return False
        size = len(message) + 40  # RmLogItem header + payload
        if not self._space_ok(size):
            stream.dropped += 1
            return False
        try:
            self._sonar.write(message, time)
        except OculusFormatError:
            stream.rejected += 1
            return False
        except OSError as exc:
            self._write_failed("sonar", exc)
            stream.dropped += 1
            return False
        self._wrote(stream, size)
        return not self.stats.stopped  # False if the flush it triggered failed

    def record_mavlink(self, packet: bytes, time: float) -> bool:
        """Append one raw MAVLink packet received at ``time`` (UNIX s); whether recorded."""
        stream = self.stats.nav
        if self._nav is None:
            stream.dropped += 1
            return False
        size = len(packet) + _STAMP.size
        if not self._space_ok(size):
            stream.dropped += 1
            return False
        try:
            self._nav.write(packet, time)
        except OSError as exc:
            self._write_failed("nav", exc)
            stream.dropped += 1
            return False
        self._wrote(stream, size)
        return not self.stats.stopped  # False if the flush it triggered failed

    def poll(self) -> None:
        """Flush (and fsync) what is due; call this on a timer so a pause in items is safe."""
        now = self._clock()
        flush_due = self._dirty and now - self._last_flush >= self.flush_interval_s
        fsync_due = self._unsynced and now - self._last_fsync >= FSYNC_INTERVAL_S
        if flush_due or fsync_due:
            self.flush()

    def flush(self) -> None:
        """Push buffered items to the OS now, and fsync if a second has passed since the last."""
        if self.stats.stopped:
            return
        try:
            self._flush_files()
        except OSError as exc:
            self._write_failed("flush", exc)

    def close(self) -> None:
        """Flush, fsync and close the segment; later items are dropped."""
        if not self.stats.stopped:
            self._stop("closed", full=False, level=logging.DEBUG)

    def __enter__(self) -> SurveyRecorder:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # --- internals ------------------------------------------------------------------------

    def _open(self, start_time: float | None) -> None:
        """Open the next free segment (exclusive create; retries past a racing writer)."""
        for _ in range(100):
            segment = next_segment(self.survey_dir)
            sonar_path = self.survey_dir / sonar_name(segment)
            nav_path = self.survey_dir / nav_name(segment)
            try:
                sonar = OculusLogWriter(sonar_path, start_time=start_time)
            except FileExistsError:
                continue
            except OSError as exc:
                self._fail(f"cannot create {sonar_path}: {exc.strerror or exc}")
                return
            try:
                nav = TlogWriter(nav_path)
            except OSError as exc:
                sonar.close()
                if isinstance(exc, FileExistsError):
                    continue  # leave the lone sonar file: the next number is above it
                self._fail(f"cannot create {nav_path}: {exc.strerror or exc}")
                return
            self._sonar, self._nav = sonar, nav
            self.sonar_path, self.nav_path = sonar_path, nav_path
            self.stats.segment = segment
            self.stats.segments = len(segments(self.survey_dir)[0])
            self._dirty = True
            try:  # file headers and directory entries survive a power cut
                self._flush_files(force_fsync=True)
                _fsync_dir(self.survey_dir)
            except OSError as exc:
                self._write_failed("open", exc)
            log.info("recording survey segment %03d in %s", segment, self.survey_dir)
            return
        self._fail(f"no free segment number in {self.survey_dir}")

    def _wrote(self, stream: StreamStats, size: int) -> None:
        stream.items += 1
        stream.bytes += size
        self._written_since_probe += size
        self._dirty = True
        self.poll()

    def _space_ok(self, size: int) -> bool:
        """Whether ``size`` more bytes keep ``min_free_bytes`` free; stops recording if not."""
        now = self._clock()
        if now - self._free_probe_at >= DISK_CHECK_INTERVAL_S:
            try:
                self._free_at_probe = self._free_space(self.survey_dir)
            except OSError as exc:
                self.stats.errors += 1
                log.warning("free-space probe of %s failed: %s", self.survey_dir, exc)
                self._free_at_probe = self.min_free_bytes + (1 << 62)  # unknown: keep going
            self._free_probe_at = now
            self._written_since_probe = 0
        free = self._free_at_probe - self._written_since_probe
        if free - size >= self.min_free_bytes:
            return True
        mb = 1024 * 1024
        self._stop(
            f"disk full: {max(free, 0) / mb:.0f} MB free on {self.survey_dir}'s filesystem, "
            f"below the {self.min_free_bytes / mb:.0f} MB reserve",
            full=True,
        )
        return False

    def _flush_files(self, force_fsync: bool = False) -> None:
        """Flush if anything is buffered; fsync if forced or a second has passed since."""
        now = self._clock()
        if self._dirty:
            for writer in (self._sonar, self._nav):
                if writer is not None:
                    writer.flush()
            self._dirty = False
            self._unsynced = True
            self._last_flush = now
            self.stats.flushes += 1
        job = self._fsync_job
        if job is not None and (force_fsync or job.done()):
            self._fsync_job = None
            job.result()  # waits when forced; re-raises the background fsync's OSError
        if self._unsynced and (force_fsync or now - self._last_fsync >= FSYNC_INTERVAL_S):
            paths = [path for path in (self.sonar_path, self.nav_path) if path is not None]
            if self._fsyncer is not None and not force_fsync:
                if self._fsync_job is not None:
                    return  # the disk is slow: one fsync at a time, the next one later
                self._fsync_job = self._fsyncer.submit(_fsync_paths, paths)
            else:
                _fsync_paths(paths)
            self._unsynced = False
            self._last_fsync = now
            self.stats.fsyncs += 1

    def _write_failed(self, what: str, exc: OSError) -> None:
        self.stats.errors += 1
        full = exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
        self._stop(f"{what} write failed: {exc.strerror or exc}", full=full)

    def _fail(self, reason: str) -> None:
        self.stats.errors += 1
        self.stats.stopped, self.stats.stop_reason = True, reason
        log.error("survey recording not started: %s", reason)

    def _stop(self, reason: str, *, full: bool, level: int = logging.WARNING) -> None:
        """Flush what can be flushed, close both files, record why; never raises."""
        if self.stats.stopped:
            return
        self.stats.stopped, self.stats.stop_reason = True, reason
        self.stats.full = self.stats.full or full
        try:
            self._flush_files(force_fsync=True)
        except OSError as exc:
            self.stats.errors += 1
            log.debug("final flush failed: %s", exc)
        for writer in (self._sonar, self._nav):
            if writer is None:
                continue
            try:
                writer.close()
            except OSError as exc:  # the buffer could not be written: the file is closed
                self.stats.errors += 1
                log.debug("closing %s failed: %s", writer.path, exc)
        self._sonar = self._nav = None
        if self._fsyncer is not None:
            self._fsyncer.shutdown(wait=True)
        log.log(level, "survey recording stopped (segment %03d): %s", self.stats.segment, reason)


def _fsync_paths(paths: list[Path]) -> None:
    for path in paths:
        _fsync_path(path)


def _fsync_path(path: Path) -> None:
    """fsync a file through a second descriptor (Linux syncs the file, not the descriptor)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(path: Path) -> None:
    """Make new directory entries durable (no-op where directories cannot be opened)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
