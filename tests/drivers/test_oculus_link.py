"""The live sonar link against the emulated M1200d on loopback sockets."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator

import numpy as np
import pytest

from drivers.oculus import FireFlags, OculusFramer, PingRate, SimpleFire, parse_simple_ping
from drivers.oculus.link import FireSettings, LinkTiming, OculusLink
from mapping.samples import Ping
from tests.drivers.test_oculus_protocol import make_ping
from tests.ports import free_udp_port
from tools.emulators.sonar import SonarEmulator, encode_ping

TIMEOUT_S = 5.0
FAST = LinkTiming(
    fire_interval_s=0.1,
    silence_timeout_s=1.0,
    connect_timeout_s=1.0,
    idle_flush_s=0.05,
    backoff_initial_s=0.05,
    backoff_max_s=0.2,
)


def source(count: int = 1000) -> Iterator[Ping]:
    """Small pings with ids 0, 1, 2... (and images seeded by the id)."""
    for k in range(count):
        yield make_ping(n_beams=32, n_ranges=20, seed=k, ping_id=k)


def run(test: Callable[[], Awaitable[None]]) -> None:
    """Run an async test with a deadline; fail if it leaves tasks behind."""

    async def bounded() -> None:
        await asyncio.wait_for(test(), TIMEOUT_S)
        await asyncio.sleep(0)  # let cancelled tasks finish
        leftover = asyncio.all_tasks() - {asyncio.current_task()}
        assert not leftover, f"tasks left running: {leftover}"

    asyncio.run(bounded())


def emulator(
    status_to: tuple[str, int] | None = None, fire_timeout_s: float = 0.5
) -> SonarEmulator:
    """An emulator pinging at 100 Hz whatever the fired rate, status every 50 ms."""
    return SonarEmulator(
        source(),
        status_to=status_to,
        status_interval_s=0.05,
        fire_timeout_s=fire_timeout_s,
        rate_hz=100.0,
    )


async def take(pings: AsyncIterator[Ping], count: int) -> list[Ping]:
    return [await anext(pings) for _ in range(count)]


@pytest.mark.parametrize(
    "fire", [FireSettings(), FireSettings(data_16bit=True, send_gain=True, gain_percent=30.0)]
)
def test_discovers_fires_and_receives_the_source_pings_exactly(fire: FireSettings) -> None:
    status_port = free_udp_port()
    recorded: list[tuple[bytes, float]] = []

    async def main() -> None:
        async with emulator(status_to=("127.0.0.1", status_port)) as sonar:
            link = OculusLink(
                "auto",
                tcp_port=sonar.tcp_port,
                status_port=status_port,
                status_host="127.0.0.1",
                fire=fire,
                timing=FAST,
                on_message=lambda message, t: recorded.append((message, t)),
            )
            async with contextlib.aclosing(link.pings()) as pings:
                got = await take(pings, 30)
            assert sonar.last_fire == fire.to_message()

        assert link.stats.sonar_address == "127.0.0.1"
        assert link.stats.last_status is not None and link.stats.last_status.part_number == 1042
        sent_fire = fire.to_message()
        for ping, want in zip(got, source(30), strict=True):
            expected = parse_simple_ping(encode_ping(want, sent_fire), ping.time)
            assert ping.ping_id == want.ping_id
            np.testing.assert_array_equal(ping.bearings_rad, expected.bearings_rad)
            np.testing.assert_allclose(ping.bearings_rad, want.bearings_rad, atol=1e-12)
            assert ping.image.dtype == (np.uint16 if fire.data_16bit else np.uint8)
            scale = 257 if fire.data_16bit else 1
            np.testing.assert_array_equal(ping.image, want.image.astype(ping.image.dtype) * scale)
            assert (ping.gains is not None) == fire.send_gain
            assert ping.gain_percent == fire.gain_percent
        assert link.stats.pings == 30 and link.stats.connects == 1
        assert link.stats.bytes_skipped == 0 and link.stats.parse_errors == 0
        # Every message reached the recorder, stamped on receipt, before the pings were parsed.
        assert [parse_simple_ping(m, t).ping_id for m, t in recorded[:30]] == list(range(30))
        assert [p.time for p in got] == [t for _, t in recorded[:30]]

    run(main)


def test_emulator_stops_pinging_when_not_refired() -> None:
    async def main() -> None:
        async with emulator(fire_timeout_s=0.3) as sonar:
            reader, writer = await asyncio.open_connection("127.0.0.1", sonar.tcp_port)
            framer = OculusFramer()

            async def pings_within(seconds: float) -> int:
                count = 0
                loop = asyncio.get_running_loop()
                end = loop.time() + seconds
                while (left := end - loop.time()) > 0:
                    with contextlib.suppress(TimeoutError):
                        count += len(framer.feed(await asyncio.wait_for(reader.read(65536), left)))
                return count

            assert await pings_within(0.2) == 0  # not fired yet
            fire = SimpleFire(ping_rate=PingRate.HZ40, flags=int(FireFlags.DATA_16BIT))
            writer.write(fire.pack())
            assert await pings_within(0.2) > 5
            await asyncio.sleep(0.3)  # fire_timeout_s passes without a new fire
            framer.reset()
            with contextlib.suppress(TimeoutError):  # drain what was already in flight
                await asyncio.wait_for(reader.read(1 << 20), 0.05)
            assert not sonar.pinging
            assert await pings_within(0.3) == 0
            writer.write(fire.pack())
            assert await pings_within(0.2) > 5  # fired again: pinging again
            writer.close()
            await writer.wait_closed()

    run(main)


def test_link_reconnects_after_a_dropped_connection() -> None:
    async def main() -> None:
        async with emulator() as sonar:
            link = OculusLink("127.0.0.1", tcp_port=sonar.tcp_port, timing=FAST)
            async with contextlib.aclosing(link.pings()) as pings:
                before = await take(pings, 5)
                sonar.drop_connection()
                after = await take(pings, 20)
        ids = [p.ping_id for p in before + after]
        assert ids == sorted(set(ids)), "pings come once and in order"
        assert link.stats.reconnects == 1 and sonar.connections == 2
        assert link.stats.parse_errors == 0

    run(main)


def test_a_ping_held_back_by_the_framer_keeps_its_arrival_stamp() -> None:
    """A ping whose last byte is 0x53 (the first byte of the magic) waits in the framer
    for the next bytes; its stamp is still the time its own bytes arrived."""
    fire = FireSettings().to_message()
    pings = []
    for k in range(4):
        ping = make_ping(n_beams=32, n_ranges=20, seed=k, ping_id=k)
        ping.image[-1, -1] = 0x53
        pings.append(encode_ping(ping, fire))
    assert all(message.endswith(b"\x53") for message in pings)
    slow = LinkTiming(idle_flush_s=5.0, silence_timeout_s=10.0)

    async def main() -> None:
        sent: list[float] = []
        handlers: list[asyncio.Task[object]] = []

        async def serve(_: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            handlers.append(asyncio.current_task())  # type: ignore[arg-type]
            for message in pings:
                sent.append(time.time())
                writer.write(message)
                await writer.drain()
                await asyncio.sleep(0.2)
            await asyncio.sleep(1.0)
            writer.close()

        server = await asyncio.start_server(serve, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        link = OculusLink("127.0.0.1", tcp_port=port, timing=slow)
        async with server, contextlib.aclosing(link.pings()) as stream:
            got = await take(stream, 3)  # the 4th waits for bytes that never come
        for handler in handlers:
            handler.cancel()
        await asyncio.gather(*handlers, return_exceptions=True)
        errors = [ping.time - t for ping, t in zip(got, sent, strict=False)]
        assert [p.ping_id for p in got] == [0, 1, 2]
        assert max(abs(e) for e in errors) < 0.1, errors  # not the 0.2 s until the next ping

    run(main)


def test_link_reconnects_when_the_sonar_falls_silent() -> None:
    async def main() -> None:
        sonar = SonarEmulator(source(3), status_to=None, rate_hz=100.0)
        async with sonar:
            timing = LinkTiming(silence_timeout_s=0.2, idle_flush_s=0.05, backoff_initial_s=0.05)
            link = OculusLink("127.0.0.1", tcp_port=sonar.tcp_port, timing=timing)
            async with contextlib.aclosing(link.pings()) as pings:
                assert len(await take(pings, 3)) == 3
                pending = asyncio.ensure_future(anext(pings))
                while link.stats.silences < 1 or link.stats.reconnects < 1:
                    await asyncio.sleep(0.02)
                pending.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await pending
        assert link.stats.reconnects >= 1

    run(main)


def test_garbage_in_the_stream_is_skipped_and_counted() -> None:
    async def main() -> None:
        async with emulator() as sonar:
            link = OculusLink("127.0.0.1", tcp_port=sonar.tcp_port, timing=FAST)
            async with contextlib.aclosing(link.pings()) as pings:
                before = await take(pings, 3)
                sonar.inject_garbage(1000)
                after = await take(pings, 10)
        ids = [p.ping_id for p in before + after]
        assert ids == list(range(13)), "no ping lost to the garbage"
        assert link.stats.bytes_skipped == 1000
        assert link.stats.parse_errors == 0 and link.stats.reconnects == 0

    run(main)


def test_corrupt_messages_are_recorded_before_the_parser_rejects_them() -> None:
    """A flipped message id and a ping with impossible geometry reach ``on_message`` (the
    recording) like every framed message; only the parser drops them."""
    from drivers.oculus.protocol import SIMPLE_FIRE_V2_SIZE

    fire = FireSettings().to_message()
    messages = [
        bytearray(encode_ping(make_ping(n_beams=32, n_ranges=20, seed=k, ping_id=k), fire))
        for k in range(6)
    ]
    messages[1][6:8] = (0x5A5A).to_bytes(2, "little")  # no such message id
    n_beams_at = SIMPLE_FIRE_V2_SIZE + 83
    assert int.from_bytes(messages[3][n_beams_at : n_beams_at + 2], "little") == 32
    messages[3][n_beams_at : n_beams_at + 2] = bytes(2)  # a ping of zero beams
    sent = [bytes(m) for m in messages]

    async def main() -> None:
        handlers: list[asyncio.Task[object]] = []

        async def serve(_: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            handlers.append(asyncio.current_task())  # type: ignore[arg-type]
            for message in sent:
                writer.write(message)
                await writer.drain()
                await asyncio.sleep(0.02)
            await asyncio.sleep(5.0)

        server = await asyncio.start_server(serve, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        recorded: list[bytes] = []
        link = OculusLink(
            "127.0.0.1", tcp_port=port, timing=FAST,
            on_message=lambda message, _: recorded.append(message),
        )  # fmt: skip
        async with server, contextlib.aclosing(link.pings()) as stream:
            got = await take(stream, 4)
        for handler in handlers:
            handler.cancel()
        await asyncio.gather(*handlers, return_exceptions=True)
        assert [p.ping_id for p in got] == [0, 2, 4, 5]
        assert recorded == sent
        assert link.stats.parse_errors == 1 and link.stats.bytes_skipped == 0

    run(main)


def test_a_sonar_back_from_a_cut_is_pinging_within_a_second_of_its_status() -> None:
    """A 4.5 s power cut (TCP and status gone) has grown the backoff to 4 s; the sonar's
    first status after it brings the link back at once, not when the backoff ends."""
    status_port = free_udp_port()
    timing = LinkTiming(
        fire_interval_s=0.1, silence_timeout_s=1.0, connect_timeout_s=0.5, idle_flush_s=0.05
    )  # the default backoff: 0.5 s doubling to 10 s

    async def main() -> tuple[float, float]:
        first = SonarEmulator(
            source(), status_to=("127.0.0.1", status_port), status_interval_s=0.2, rate_hz=50.0
        )
        await first.start()
        port = first.tcp_port
        link = OculusLink("127.0.0.1", tcp_port=port, status_port=status_port, timing=timing)
        async with contextlib.aclosing(link.pings()) as pings:
            await take(pings, 3)
            await first.close()  # the cut: no TCP, no status
            waiting = asyncio.ensure_future(anext(pings))
            await asyncio.sleep(4.5)
            assert not waiting.done()
            back = SonarEmulator(
                source(), tcp_port=port, status_to=("127.0.0.1", status_port),
                status_interval_s=1.0, rate_hz=50.0,
            )  # fmt: skip
            async with back:
                started = time.monotonic()
                await asyncio.wait_for(waiting, 6.0)
                return time.monotonic() - started, link.stats.last_status_time or 0.0

    delay, heard = asyncio.run(asyncio.wait_for(main(), 30.0))
    # Its first status goes out as it starts; the connect follows it, then the first ping.
    assert delay < 1.0, f"{delay:.2f} s from the sonar's return to its first ping"
    assert heard > 0
