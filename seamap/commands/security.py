"""``seamap security init [--router] --out DIR --vehicle ID [--host NAME_OR_IP ...]
[--shores N]``: a working set of certificates, keys and zenoh files for the boat and its
shore stations, or (``--router``, ``--vehicle`` repeated) for a fleet's router, its boats
and shores (``seamap.security``)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "security",
        help="make the keys, certificates and zenoh files that secure the boat's link",
        description="Secure the zenoh link between the boat and its shore stations.",
    )
    actions = parser.add_subparsers(dest="security_action", required=True, metavar="ACTION")
    init = actions.add_parser(
        "init",
        help="write a CA, the boat's and the shores' certificates and keys and zenoh files",
        description=(
            "Write a working set into DIR: a CA (keep ca.key off the boat), boat/ (its "
            "certificate and key, the shores' users file, boat.json5 and the [zenoh] lines "
            "of its site file) and shore-N/ for each shore (certificate, key, shore-N.json5, "
            "[zenoh] lines). With it, only a peer with a shore's certificate and password "
            "joins the boat, and it may only follow it and start or stop surveys. With "
            "--router: router/ (its certificate, every user, router.json5 with a policy per "
            "boat and one for the shores), boat-ID/ for each --vehicle and shore-N/, each a "
            "client of the router; a boat may only publish under its own seamap/ID/**."
        ),
    )
    init.add_argument(
        "--router", action="store_true",
        help="a set for a fleet through one `seamap router` (boats and shores its clients)",
    )  # fmt: skip
    init.add_argument("--out", type=Path, required=True, help="the folder to write")
    init.add_argument(
        "--vehicle", action="append", required=True, metavar="ID",
        help="the boat's vehicle id ([daemon] vehicle); with --router, repeat it for each boat",
    )  # fmt: skip
    init.add_argument(
        "--host", action="append", default=[], metavar="NAME_OR_IP",
        help="a name or address the shores reach the boat (with --router: the router) by "
        "(repeat; the first is the one the clients' files connect to; default: localhost and "
        "127.0.0.1)",
    )  # fmt: skip
    init.add_argument("--shores", type=int, default=1, help="shore stations (default 1)")
    init.add_argument(
        "--port", type=int, default=7447, help="the boat's (the router's) TLS port (7447)"
    )
    init.add_argument(
        "--install-dir", type=Path, default=None, metavar="DIR",
        help="where each side's folder (boat/, router/, boat-ID/, shore-N/) will be installed, "
        "e.g. /etc/seamap/security: the paths inside the files (default: where they are "
        "written)",
    )  # fmt: skip
    init.set_defaults(handler=run_init)


def run_init(args: argparse.Namespace) -> int:
    from drivers.errors import SeamapError
    from seamap.security import init_security

    if args.router:
        return _run_init_fleet(args)
    if len(args.vehicle) > 1:
        raise SeamapError("--vehicle: one boat without --router (give --router for a fleet)")
    vehicle = args.vehicle[0]
    written = init_security(args.out, vehicle, args.host, args.shores, args.install_dir, args.port)
    print(f"security set for {vehicle!r} in {written.out}:")
    print(f"  {written.out / 'ca.key'}  the CA's key: keep it off the boat")
    print(f"  {written.boat}/  for the boat: its site file takes {written.boat / 'zenoh.toml'}")
    for folder in written.shores:
        print(f"  {folder}/  for {folder.name}: its site file takes {folder / 'zenoh.toml'}")
    return 0


def _run_init_fleet(args: argparse.Namespace) -> int:
    from seamap.security import init_fleet_security

    written = init_fleet_security(
        args.out, args.vehicle, args.host, args.shores, args.install_dir, args.port
    )
    print(f"fleet security set for {', '.join(args.vehicle)} in {written.out}:")
    print(f"  {written.out / 'ca.key'}  the CA's key: keep it off the boats and the router")
    print(f"  {written.router}/  for the router: `seamap router --config` takes its zenoh.toml")
    for folder in [*written.boats.values(), *written.shores]:
        print(f"  {folder}/  for {folder.name}: its site file takes {folder / 'zenoh.toml'}")
    return 0
