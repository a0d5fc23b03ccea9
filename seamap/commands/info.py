"""``seamap info FILE [--json]``: what an Oculus or MAVLink log holds."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from drivers.errors import SeamapError


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "info",
        help="tell what a sonar (.oculus) or MAVLink (.tlog/.bin) log holds",
        description="Tell what an Oculus sonar log or a MAVLink log (.tlog, DataFlash .bin) holds.",
    )
    parser.add_argument("file", type=Path, help="an .oculus, .tlog or .bin log")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.set_defaults(handler=run)


def detect_log_kind(path: Path) -> str:
    """ "oculus" or "mavlink", from the file's first bytes (not its name)."""
    try:
        with path.open("rb") as stream:
            head = stream.read(16)
    except FileNotFoundError:
        raise SeamapError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise SeamapError(f"{path}: is a directory, not a log") from None
    except OSError as exc:
        raise SeamapError(f"{path}: cannot read ({exc.strerror})") from None
    if head.startswith(b"\x44\x33\x22\x11") or head.startswith(b"SQLite format 3\x00"):
        return "oculus"
    from drivers.oculus.logfile import is_raw_capture, is_raw_capture_start

    if is_raw_capture_start(head):
        return "oculus"  # a raw network capture: Oculus messages, no log framing
    if head.startswith(b"\xa3\x95") or (len(head) > 8 and head[8] in (0xFE, 0xFD)):
        return "mavlink"
    if not head:
        raise SeamapError(f"{path}: empty file, not a log")
    if is_raw_capture(path):
        return "oculus"  # a capture joined mid-message: whole messages further on
    raise SeamapError(
        f"{path}: not an Oculus log or capture, nor a MAVLink log (unrecognised first bytes "
        f"{head[:8].hex(' ')})"
    )


def summarize(path: Path) -> dict[str, Any]:
    kind = detect_log_kind(path)
    if kind == "oculus":
        from drivers.oculus.logfile import summarize_oculus_log

        return summarize_oculus_log(path)
    from drivers.mavlink.navlog import summarize_nav_log

    return summarize_nav_log(path)


def _fmt_time(t: float | None) -> str:
    if t is None:
        return "-"
    import datetime as dt

    stamp = dt.datetime.fromtimestamp(t, tz=dt.UTC)
    return f"{t:.3f} ({stamp.isoformat(timespec='milliseconds').replace('+00:00', 'Z')})"


def format_summary(path: Path, summary: dict[str, Any]) -> str:
    lines = [f"{path}: {summary.get('format', summary['kind'])}"]
    first, last = summary.get("first_time"), summary.get("last_time")
    span = f"{last - first:.1f} s" if first is not None and last is not None else "-"
    if summary.get("format") == "oculus-raw":
        lines.append(f"  {'times:':<15} none (a raw capture has no receipt stamps)")
    else:
        lines.append(f"  {'first time:':<15} {_fmt_time(first)}")
        lines.append(f"  {'last time:':<15} {_fmt_time(last)}  (span {span})")
    if summary["kind"] == "oculus":
        lines.append(f"  {'pings:':<15} {summary['count']}")
        for key, label in (
            ("beams", "beams"),
            ("ranges", "ranges"),
            ("range_m", "range (m)"),
            ("bearings_deg", "bearings (deg)"),
            ("modes", "modes"),
            ("frequencies_hz", "frequency (Hz)"),
            ("sample_bits", "sample bits"),
            ("gain_rows", "gain rows"),
            ("msg_versions", "msgVersion"),
        ):
            value = summary.get(key)
            if key in ("bearings_deg", "range_m") and value:
                low, high = value
                sign = "+" if key == "bearings_deg" else ""
                text = f"{low:{sign}.3f}" if low == high else f"{low:{sign}.3f} .. {high:{sign}.3f}"
                lines.append(f"  {label + ':':<15} {text}")
            elif key in summary:
                lines.append(f"  {label + ':':<15} {value}")
    else:
        lines.append(f"  {'messages:':<15} {summary['count']}")
        if "autopilot" in summary:
            lines.append(f"  {'autopilot:':<15} {summary['autopilot']}")
        if summary.get("soundings_source"):
            lines.append(
                f"  {'soundings:':<15} {summary['soundings']} "
                f"({summary['soundings_source']}, downward)"
            )
    messages = summary.get("messages") or {}
    if messages:
        width = max(len(name) for name in messages)
        lines.append("  message counts:")
        for name, count in sorted(messages.items()):
            lines.append(f"    {name:<{width}}  {count}")
    for key in ("skipped", "truncated", "bytes_skipped", "bad_bytes"):
        value = summary.get(key)
        if value:
            lines.append(f"  {key}: {value}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    summary = summarize(args.file)
    if args.json:
        print(json.dumps(summary, sort_keys=True))
    else:
        print(format_summary(args.file, summary))
    return 0
