"""Survey requests that come over zenoh (``seamap/{vehicle}/control/survey``): one JSON
object ``{"action": "start"|"stop"|"status"}``, answered ``{"ok": true, ...}`` or
``{"ok": false, "error": "..."}``. The publisher (``daemon.publisher``) hands each to
``answer`` on the event loop; ``seamap survey`` and the shore are its clients. The local
control socket (``daemon.control``) drives the daemon the same way with its own keys.
"""

from __future__ import annotations

from typing import Any, Protocol

from daemon.control import Controllable
from daemon.survey import SurveyState
from drivers.errors import SeamapError


class SurveyControl(Controllable, Protocol):
    """What a zenoh request drives (``daemon.service.Daemon``)."""

    @property
    def survey(self) -> SurveyState | None: ...


async def answer(daemon: SurveyControl, request: dict[str, Any]) -> dict[str, Any]:
    """The reply to a survey request from zenoh: ``{"action": "start"|"stop"|"status"}``
    (a start may carry ``"area"``, a GeoJSON geometry in WGS84)."""
    action = request.get("action")
    if action == "start":
        area = request.get("area")
        if area is not None and not isinstance(area, dict):
            return {"ok": False, "error": "area must be a GeoJSON object"}
        try:
            return {"ok": True, "survey": await daemon.start_survey("zenoh", area)}
        except SeamapError as exc:
            return {"ok": False, "error": str(exc)}
    if action == "stop":
        return {"ok": True, "survey": await daemon.stop_survey("zenoh", wait=False)}
    if action == "status":
        survey = daemon.survey
        return {
            "ok": True,
            "survey": survey.id if survey is not None else None,
            "status": daemon.status(),
        }
    return {"ok": False, "error": f"unknown action {action!r} (start, stop, status)"}
