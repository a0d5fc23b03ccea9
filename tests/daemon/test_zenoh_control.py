"""Survey requests over zenoh (``daemon.zenoh_control.answer``): each action's reply, and
bad requests answered in one line without touching the daemon."""

from __future__ import annotations

import asyncio
from typing import Any

from daemon.survey import SurveyState
from daemon.zenoh_control import answer
from drivers.errors import SeamapError


class FakeDaemon:
    """What a zenoh request drives, keeping what it was asked."""

    def __init__(self) -> None:
        self.survey: SurveyState | None = None
        self.calls: list[tuple[Any, ...]] = []

    async def start_survey(self, reason: str, area: dict[str, Any] | None = None) -> str:
        self.calls.append(("start", reason, area))
        if area == {"type": "Point"}:
            raise SeamapError("area: not a polygon")
        if self.survey is None:
            self.survey = SurveyState("20260101-000000", "boat1")
        return self.survey.id

    async def stop_survey(self, reason: str, *, wait: bool) -> str | None:
        self.calls.append(("stop", reason, wait))
        stopped, self.survey = self.survey, None
        return stopped.id if stopped is not None else None

    def status(self) -> dict[str, Any]:
        return {"vehicle": "boat1"}


def test_survey_requests_are_answered() -> None:
    daemon = FakeDaemon()

    async def main() -> list[dict[str, Any]]:
        return [
            await answer(daemon, {"action": "status"}),
            await answer(daemon, {"action": "start", "area": {"type": "Polygon"}}),
            await answer(daemon, {"action": "status"}),
            await answer(daemon, {"action": "stop"}),
            await answer(daemon, {"action": "stop"}),
        ]

    replies = asyncio.run(main())
    assert replies == [
        {"ok": True, "survey": None, "status": {"vehicle": "boat1"}},
        {"ok": True, "survey": "20260101-000000"},
        {"ok": True, "survey": "20260101-000000", "status": {"vehicle": "boat1"}},
        {"ok": True, "survey": "20260101-000000"},
        {"ok": True, "survey": None},
    ]
    assert daemon.calls == [
        ("start", "zenoh", {"type": "Polygon"}),
        ("stop", "zenoh", False),
        ("stop", "zenoh", False),
    ]


def test_bad_requests_are_one_line() -> None:
    daemon = FakeDaemon()

    async def main() -> list[dict[str, Any]]:
        return [
            await answer(daemon, {"action": "start", "area": "here"}),
            await answer(daemon, {"action": "start", "area": {"type": "Point"}}),
            await answer(daemon, {"action": "reboot"}),
            await answer(daemon, {}),
        ]

    replies = asyncio.run(main())
    assert replies == [
        {"ok": False, "error": "area must be a GeoJSON object"},
        {"ok": False, "error": "area: not a polygon"},
        {"ok": False, "error": "unknown action 'reboot' (start, stop, status)"},
        {"ok": False, "error": "unknown action None (start, stop, status)"},
    ]
    assert daemon.calls == [("start", "zenoh", {"type": "Point"})]  # the bad area's
    assert daemon.survey is None
