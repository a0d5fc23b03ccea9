"""Asking the boat daemon, over zenoh, to open a survey once the mission runs.

``daemon_target`` says where the daemon's survey control answers (from a site config or
an explicit endpoint and vehicle); ``request_survey_start`` asks it on
``seamap/{vehicle}/control/survey``.
"""

from __future__ import annotations

import json
import logging
import re
import time
from dataclasses import dataclass
from typing import Any

from daemon.config import SiteConfig, ZenohConfig
from drivers.errors import SeamapError
from drivers.mission.mavsdk_link import ATTEMPTS

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DaemonTarget:
    """Where the boat daemon's survey control answers: a zenoh client session and the
    vehicle id (key ``seamap/{vehicle}/control/survey``)."""

    vehicle: str
    zenoh: ZenohConfig


@dataclass(frozen=True)
class DaemonAnswer:
    survey: str | None
    """The survey the daemon opened, or None with ``problem`` saying why not."""
    problem: str | None = None


def daemon_target(
    config: SiteConfig | None, endpoint: str | None = None, vehicle: str | None = None
) -> DaemonTarget | None:
    """The daemon to tell, from a site config (its [daemon] vehicle; its [zenoh] connect
    endpoints and its listen endpoints reached on loopback: the daemon's own config on the
    boat works as is) and/or an explicit zenoh ``endpoint`` and ``vehicle``. None when
    neither config nor endpoint is given. SeamapError for a malformed endpoint or id."""
    from drivers.zenoh_io import endpoint_problem, id_problem

    if config is None and endpoint is None:
        if vehicle is not None:
            raise SeamapError("--vehicle needs --daemon ENDPOINT or --config SITE.toml")
        return None
    if vehicle is None and config is None:
        raise SeamapError("--daemon needs --vehicle ID (or --config with a [daemon] vehicle)")
    vehicle = vehicle if vehicle is not None else config.daemon.vehicle  # type: ignore[union-attr]
    if id_problem(vehicle):
        raise SeamapError(f"vehicle {vehicle!r}: {id_problem(vehicle)}")
    if endpoint is not None:
        problem = endpoint_problem(endpoint)
        if problem is not None:
            raise SeamapError(f"--daemon {endpoint!r}: not a zenoh endpoint ({problem})")
        connect = [endpoint]
    else:
        assert config is not None
        connect = [*config.zenoh.connect, *(_on_loopback(e) for e in config.zenoh.listen)]
        if not connect:
            raise SeamapError("config: [zenoh] has no endpoint to reach the daemon on")
    config_file = config.zenoh.config_file if config is not None else ""
    session = ZenohConfig(
        mode="client", listen=[], connect=connect, multicast_scouting=False,
        config_file=config_file,
    )  # fmt: skip
    return DaemonTarget(vehicle, session)


def _on_loopback(endpoint: str) -> str:
    """A listen endpoint on every interface, as this machine reaches it."""
    return endpoint.replace("/0.0.0.0:", "/127.0.0.1:").replace("/[::]:", "/[::1]:")


def request_survey_start(
    target: DaemonTarget, timeout_s: float = 10.0, area: dict[str, Any] | None = None
) -> DaemonAnswer:
    """Ask the daemon to open a survey: a zenoh ``get`` on its control key with payload
    ``{"action": "start"}`` (and ``"area"``: the GeoJSON geometry the mission covers, when
    given); its reply ``{"ok": true, "survey": ID}`` (the survey already
    open, if one is: asking again is harmless). Tried up to ATTEMPTS times while the daemon
    cannot be reached or nothing answers; blocks up to about ``timeout_s``; never raises."""
    from drivers import zenoh_io

    deadline = time.monotonic() + timeout_s
    answer = DaemonAnswer(None, "not asked")
    for _ in range(ATTEMPTS):
        answer, retry = _ask_daemon(target, deadline, area)
        if answer.survey is not None or not retry or deadline - time.monotonic() < 1.0:
            break
        log.info("daemon: %s; asking again", answer.problem)
        time.sleep(0.5)
    if answer.survey is None and answer.problem is None:
        key = zenoh_io.control_key(target.vehicle)
        answer = DaemonAnswer(None, f"nothing answered on {key} (is the daemon running?)")
    return answer


def _ask_daemon(
    target: DaemonTarget, deadline: float, area: dict[str, Any] | None = None
) -> tuple[DaemonAnswer, bool]:
    """One request; the answer (``problem`` None: nobody answered) and whether to retry."""
    from drivers import zenoh_io

    try:
        session = zenoh_io.open_session(target.zenoh)
    except SeamapError as exc:
        where = ", ".join(target.zenoh.connect)
        return DaemonAnswer(None, f"cannot reach the daemon at {where} ({_short(str(exc))})"), True
    try:
        request: dict[str, Any] = {"action": "start"}
        if area is not None:
            request["area"] = area
        payload = zenoh_io.json_bytes(request)
        key = zenoh_io.control_key(target.vehicle)
        timeout_s = max(deadline - time.monotonic(), 0.1)
        problem = None
        for reply in session.get(key, payload=payload, timeout=timeout_s):
            if reply.ok is None:
                problem = f"the daemon answered with an error: {_text(reply.err)}"
                continue
            try:
                answer = json.loads(reply.ok.payload.to_bytes())
            except ValueError:
                problem = "the daemon's answer is not JSON"
                continue
            if isinstance(answer, dict) and answer.get("ok") and answer.get("survey"):
                return DaemonAnswer(str(answer["survey"])), False
            error = answer.get("error") if isinstance(answer, dict) else answer
            problem = f"the daemon did not open a survey ({error})"
        return DaemonAnswer(None, problem), problem is None  # a refusal is not retried
    except Exception as exc:  # zenoh raises its own ZError for a session gone bad
        return DaemonAnswer(None, f"the request to the daemon failed ({_short(str(exc))})"), True
    finally:
        session.close()


def _text(error: Any) -> str:
    try:
        return str(error.payload.to_bytes().decode("utf-8", "replace"))
    except Exception:  # no payload to show
        return "?"


def _short(message: str) -> str:
    """zenoh's messages end with the Rust source position: drop it."""
    return re.sub(r"\s+at /\S+\.rs:\d+\.?", "", message).strip()
