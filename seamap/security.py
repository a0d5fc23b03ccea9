"""``seamap security init``: a working set of keys, certificates and zenoh files for one boat
and its shore stations, so that the secure link is the easy one.

The set (``OUT``):

- ``ca.crt``, ``ca.key``: the set's own certificate authority (P-256, ten years). Keep
  ``ca.key`` off the boat: whoever holds it can make certificates the boat trusts.
- ``boat/``: ``ca.crt``, ``boat.crt`` / ``boat.key`` (the boat's TLS identity, naming every
  ``--host`` it is reached by), ``zenoh-users.txt`` (one ``shore-N:password`` a line),
  ``boat.json5`` (zenoh: TLS only, mutual TLS, user/password, the access rules of
  ``systemd/zenoh-boat.json5``) and ``zenoh.toml`` (the ``[zenoh]`` lines of the boat's
  site file).
- ``shore-N/``: ``ca.crt``, ``shore-N.crt`` / ``shore-N.key`` (the shore's certificate,
  for mutual TLS), ``shore-N.json5`` (its user and password: 0600) and ``zenoh.toml``.

With the set, a peer must show a certificate of the set's CA *and* a shore's password to
join the boat, and then may only follow it (subscribe, get tiles, pose and status) and
ask for a survey to start or stop; whatever it puts or deletes never passes the boat. A
peer without the set is refused at the TLS handshake. The paths inside the files are
where the folders are written, or under ``--install-dir`` (for example
``/etc/seamap/security``: copy ``boat/`` there on the boat and ``shore-N/`` there on
shore N).

For a fleet through one ``seamap router`` (``init_fleet_security``, ``--router``) the
router is the TLS endpoint: ``router/`` holds its certificate, every user (``boat-{id}``
for each boat, ``shore-N``) and ``router.json5``; ``boat-{id}/`` and ``shore-N/`` are
clients of it. Each subject is a user *and* its certificate's common name. A boat may
only put, answer, declare queryables and be alive under its own ``seamap/{id}/**`` and
be asked what a shore may ask; a shore has the one-boat set's rights.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
import secrets
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from drivers.errors import SeamapError
from drivers.zenoh_io import id_problem

CA_DAYS = 3650
CERT_DAYS = 825
"""Certificates expire after this many days (TLS clients refuse longer ones)."""


@dataclass(frozen=True)
class SecuritySet:
    """What ``init_security`` wrote: the folders and the shores' user names."""

    out: Path
    boat: Path
    shores: list[Path]
    users: list[str]
    port: int


def _key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _name(common_name: str) -> x509.Name:
    return x509.Name(
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "seamap"),
            x509.NameAttribute(NameOID.COMMON_NAME, common_name),
        ]
    )


def _certificate(
    subject: str,
    key: ec.EllipticCurvePrivateKey,
    issuer: x509.Certificate | None,
    issuer_key: ec.EllipticCurvePrivateKey,
    days: int,
    *,
    ca: bool = False,
    hosts: list[str] | None = None,
    usage: x509.ObjectIdentifier | None = None,
) -> x509.Certificate:
    now = datetime.datetime.now(datetime.UTC)
    builder = (
        x509.CertificateBuilder()
        .subject_name(_name(subject))
        .issuer_name(issuer.subject if issuer is not None else _name(subject))
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=ca, path_length=0 if ca else None), True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), False)
    )
    # A CA signs certificates; a boat or shore signs its handshakes and agrees keys.
    builder = builder.add_extension(
        x509.KeyUsage(
            digital_signature=True, content_commitment=False, key_encipherment=False,
            data_encipherment=False, key_agreement=not ca, key_cert_sign=ca, crl_sign=ca,
            encipher_only=False, decipher_only=False,
        ),
        critical=True,
    )  # fmt: skip
    if not ca:
        assert issuer is not None and usage is not None
        builder = builder.add_extension(x509.ExtendedKeyUsage([usage]), critical=False)
        builder = builder.add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(issuer_key.public_key()), False
        )
    if hosts:
        names: list[x509.GeneralName] = []
        for host in hosts:
            try:
                names.append(x509.IPAddress(ipaddress.ip_address(host)))
            except ValueError:
                names.append(x509.DNSName(host))
        builder = builder.add_extension(x509.SubjectAlternativeName(names), critical=False)
    return builder.sign(issuer_key, hashes.SHA256())


def _write(path: Path, data: bytes | str, mode: int = 0o644) -> None:
    raw = data.encode() if isinstance(data, str) else data
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "wb") as out:
        out.write(raw)
    os.chmod(path, mode)


def _pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def _pem_key(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )


def _check_host(host: str) -> None:
    try:
        ipaddress.ip_address(host)
        return
    except ValueError:
        pass
    labels = host.rstrip(".").split(".")
    if not host or not all(
        label and len(label) <= 63 and label.replace("-", "").isalnum() for label in labels
    ):
        raise SeamapError(f"--host {host!r}: not an IP address or a DNS name")


def _tls_listener(
    mode: str, folder: Path, name: str, port: int, access_control: dict[str, object]
) -> dict[str, object]:
    """A zenoh configuration that listens in TLS only (mutual TLS, the set's users), as
    ``name`` (its ``name.crt`` / ``name.key`` in ``folder``), with ``access_control``."""
    return {
        "mode": mode,
        "listen": {"endpoints": [f"tls/0.0.0.0:{port}"]},
        "connect": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {
            "link": {
                "protocols": ["tls"],
                "tls": {
                    "root_ca_certificate": str(folder / "ca.crt"),
                    "listen_certificate": str(folder / f"{name}.crt"),
                    "listen_private_key": str(folder / f"{name}.key"),
                    "enable_mtls": True,
                },
            },
            "auth": {"usrpwd": {"dictionary_file": str(folder / "zenoh-users.txt")}},
        },
        "access_control": access_control,
    }


_SHORE_QUERIES = ["seamap/*/survey/**", "seamap/*/pose", "seamap/*/status"]
_SHORE_CONTROL = "seamap/*/control/survey"
_SHORE_RULES: list[dict[str, object]] = [  # the rules of systemd/zenoh-boat.json5
    {
        "id": "shore-subscribe",
        "messages": ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
        "flows": ["ingress"],
        "permission": "allow",
        "key_exprs": ["seamap/**"],
    },
    {
        "id": "shore-query",
        "messages": ["query"],
        "flows": ["ingress"],
        "permission": "allow",
        "key_exprs": _SHORE_QUERIES,
    },
    {
        "id": "shore-control",
        "messages": ["query"],
        "flows": ["ingress"],
        "permission": "allow",
        "key_exprs": [_SHORE_CONTROL],
    },
    {
        "id": "boat-publish",
        "messages": ["put", "delete", "reply", "declare_queryable", "liveliness_token"],
        "flows": ["egress"],
        "permission": "allow",
        "key_exprs": ["seamap/**"],
    },
    {
        "id": "shore-never-publishes",
        "messages": ["put", "delete", "declare_queryable", "liveliness_token", "reply"],
        "flows": ["ingress"],
        "permission": "deny",
        "key_exprs": ["**"],
    },
]


def boat_zenoh(folder: Path, users: list[str], port: int) -> dict[str, object]:
    """The boat's zenoh configuration (the rules of ``systemd/zenoh-boat.json5``), its
    files in ``folder``."""
    access = {
        "enabled": True,
        "default_permission": "deny",
        "rules": _SHORE_RULES,
        "subjects": [{"id": "shores", "usernames": users}],
        "policies": [
            {
                "id": "shore-stations",
                "rules": [str(rule["id"]) for rule in _SHORE_RULES],
                "subjects": ["shores"],
            },
        ],
    }
    return _tls_listener("peer", folder, "boat", port, access)


def boat_user(vehicle: str) -> str:
    """The user name a boat logs in to the fleet's router with."""
    return f"boat-{vehicle}"


def _boat_rules(vehicle: str) -> list[dict[str, object]]:
    """What the router lets boat ``vehicle`` do: publish, answer and be alive under its own
    ``seamap/{vehicle}/**`` only, and be asked what a shore may ask. The queries' rule
    names any vehicle because a shore asks ``seamap/*/...`` and the router checks the key
    as asked; the router still only hands a query to the boats whose queryables match
    it, and a boat can only declare queryables under its own key."""
    return [
        {
            "id": f"{vehicle}-publishes",
            "messages": ["put", "delete", "reply", "declare_queryable", "liveliness_token"],
            "flows": ["ingress"],
            "permission": "allow",
            "key_exprs": [f"seamap/{vehicle}/**"],
        },
        {
            "id": f"{vehicle}-is-asked",
            "messages": ["query"],
            "flows": ["egress"],
            "permission": "allow",
            "key_exprs": [*_SHORE_QUERIES, _SHORE_CONTROL],
        },
    ]


def router_zenoh(
    folder: Path, vehicles: list[str], shore_users: list[str], port: int
) -> dict[str, object]:
    """The fleet router's zenoh configuration: TLS only, mutual TLS, user/password, and
    access control (default deny; ``_boat_rules`` for each boat, ``_SHORE_RULES`` for the
    shores, as ``systemd/zenoh-boat.json5`` for one boat); its files in ``folder``."""
    rules = [rule for vehicle in vehicles for rule in _boat_rules(vehicle)] + _SHORE_RULES
    # A subject names the user *and* its certificate: a password is only good with the
    # certificate made for the same user.
    subjects: list[dict[str, object]] = []
    policies: list[dict[str, object]] = []
    for vehicle in vehicles:
        user = boat_user(vehicle)
        subjects.append({"id": user, "usernames": [user], "cert_common_names": [user]})
        rule_ids = [str(rule["id"]) for rule in _boat_rules(vehicle)]
        policies.append({"id": user, "rules": rule_ids, "subjects": [user]})
    for user in shore_users:
        subjects.append({"id": user, "usernames": [user], "cert_common_names": [user]})
    rule_ids = [str(rule["id"]) for rule in _SHORE_RULES]
    policies.append({"id": "shore-stations", "rules": rule_ids, "subjects": shore_users})
    access = {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }
    return _tls_listener("router", folder, "router", port, access)


def shore_zenoh(
    folder: Path, user: str, password: str, boat: str, port: int, mode: str = "peer"
) -> dict[str, object]:
    """A shore's zenoh configuration: TLS to the boat at ``boat`` (or to the fleet's
    router, ``mode`` "client"), its certificate, its user and password; its files in
    ``folder``."""
    return {
        "mode": mode,
        "connect": {"endpoints": [f"tls/{_bracket(boat)}:{port}"]},
        "listen": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {
            "link": {
                "protocols": ["tls"],
                "tls": {
                    "root_ca_certificate": str(folder / "ca.crt"),
                    "verify_name_on_connect": True,
                    "enable_mtls": True,
                    "connect_certificate": str(folder / f"{user}.crt"),
                    "connect_private_key": str(folder / f"{user}.key"),
                },
            },
            "auth": {"usrpwd": {"user": user, "password": password}},
        },
    }


def _bracket(host: str) -> str:
    try:
        if ipaddress.ip_address(host).version == 6:
            return f"[{host}]"
    except ValueError:
        pass
    return host


def _toml_lines(config_file: Path, listen: list[str], connect: list[str]) -> str:
    return (
        "[zenoh]\n"
        f"config_file = {json.dumps(str(config_file))}\n"
        f"listen = {json.dumps(listen)}\n"
        f"connect = {json.dumps(connect)}\n"
    )


_HEADER = (
    "// Written by `seamap security init` (seamap/security.py): TLS with mutual certificates,\n"
    "// user/password, and the access rules of systemd/zenoh-boat.json5. JSON is JSON5.\n"
)


def _check_vehicle(vehicle: str) -> None:
    problem = id_problem(vehicle)
    if problem is not None:
        raise SeamapError(f"--vehicle {vehicle!r}: {problem}")


def _check_common(shores: int, port: int, hosts: list[str]) -> list[str]:
    """The hosts (default: localhost and 127.0.0.1), once shores, port and hosts are
    checked."""
    if not 1 <= shores <= 64:
        raise SeamapError(f"--shores {shores}: must be 1..64")
    if not 1 <= port <= 65535:
        raise SeamapError(f"--port {port}: must be 1..65535")
    hosts = hosts or ["localhost", "127.0.0.1"]
    for host in hosts:
        _check_host(host)
    return hosts


def init_security(
    out: Path,
    vehicle: str,
    hosts: list[str],
    shores: int = 1,
    install_dir: Path | None = None,
    port: int = 7447,
) -> SecuritySet:
    """Write the set (module doc) into ``out`` (which must not hold one already);
    SeamapError in one line for a bad argument or an unwritable folder."""
    _check_vehicle(vehicle)
    hosts = _check_common(shores, port, hosts)
    return _into_new_folder(
        Path(out), lambda folder: _write_set(folder, vehicle, hosts, shores, install_dir, port)
    )


def _new_ca(out: Path, name: str) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    """The set's certificate authority, written to ``out`` (its key 0600)."""
    ca_key = _key()
    ca = _certificate(f"seamap CA {name}", ca_key, None, ca_key, CA_DAYS, ca=True)
    _write(out / "ca.crt", _pem(ca))
    _write(out / "ca.key", _pem_key(ca_key), 0o600)
    return ca, ca_key


def _where(folder: Path, install_dir: Path | None) -> Path:
    """Where ``folder`` is installed: as written, or under ``install_dir``."""
    return folder.resolve() if install_dir is None else Path(install_dir) / folder.name


def _identity(
    folder: Path,
    name: str,
    common_name: str,
    ca: tuple[x509.Certificate, ec.EllipticCurvePrivateKey],
    hosts: list[str] | None = None,
) -> None:
    """A TLS identity in ``folder``: ``ca.crt``, ``name.crt`` and ``name.key`` (0600); a
    server's names every host, a client's has none."""
    folder.mkdir(exist_ok=True)
    key = _key()
    usage = ExtendedKeyUsageOID.SERVER_AUTH if hosts else ExtendedKeyUsageOID.CLIENT_AUTH
    cert = _certificate(common_name, key, ca[0], ca[1], CERT_DAYS, hosts=hosts, usage=usage)
    _write(folder / "ca.crt", _pem(ca[0]))
    _write(folder / f"{name}.crt", _pem(cert))
    _write(folder / f"{name}.key", _pem_key(key), 0o600)


def _users_file(folder: Path, users: list[str]) -> dict[str, str]:
    """A fresh password for each user, written to ``folder/zenoh-users.txt`` (0600)."""
    passwords = {user: secrets.token_urlsafe(24) for user in users}
    _write(folder / "zenoh-users.txt", "".join(f"{u}:{p}\n" for u, p in passwords.items()), 0o600)
    return passwords


def _write_set(
    out: Path, vehicle: str, hosts: list[str], shores: int, install_dir: Path | None, port: int
) -> SecuritySet:
    ca = _new_ca(out, vehicle)
    boat = out / "boat"
    _identity(boat, "boat", vehicle, ca, hosts)
    users = [f"shore-{n}" for n in range(1, shores + 1)]
    passwords = _users_file(boat, users)
    boat_json5 = boat / "boat.json5"
    config = boat_zenoh(_where(boat, install_dir), users, port)
    _write(boat_json5, _HEADER + json.dumps(config, indent=2) + "\n")
    _write(
        boat / "zenoh.toml",
        "# The [zenoh] table of the boat's site file (seamap.toml):\n"
        + _toml_lines(_where(boat, install_dir) / "boat.json5", [f"tls/0.0.0.0:{port}"], []),
    )
    shore_folders = []
    for user in users:
        folder = out / user
        _identity(folder, user, user, ca)
        where = _where(folder, install_dir)
        config = shore_zenoh(where, user, passwords[user], hosts[0], port)
        _write(folder / f"{user}.json5", _HEADER + json.dumps(config, indent=2) + "\n", 0o600)
        _write(
            folder / "zenoh.toml",
            f"# The [zenoh] table of {user}'s site file (`seamap shore --config`):\n"
            + _toml_lines(where / f"{user}.json5", [], [f"tls/{_bracket(hosts[0])}:{port}"]),
        )
        shore_folders.append(folder)
    return SecuritySet(out, boat, shore_folders, users, port)


@dataclass(frozen=True)
class FleetSecuritySet:
    """What ``init_fleet_security`` wrote: the router's, each boat's (by vehicle id) and
    each shore's folders, and every user name (boats' first)."""

    out: Path
    router: Path
    boats: dict[str, Path]
    shores: list[Path]
    users: list[str]
    port: int


_FLEET_HEADER = (
    "// Written by `seamap security init --router` (seamap/security.py): TLS with mutual\n"
    "// certificates, user/password; the router's access rules: seamap/security.py.\n"
)


def init_fleet_security(
    out: Path,
    vehicles: list[str],
    hosts: list[str],
    shores: int = 1,
    install_dir: Path | None = None,
    port: int = 7447,
) -> FleetSecuritySet:
    """Write a fleet's set into ``out``: ``router/`` (CA certificate, the router's
    certificate naming every host, the users file, ``router.json5`` with one policy per
    boat and one for the shores, ``zenoh.toml``), ``boat-{vehicle}/`` and ``shore-N/``
    (each a client of the router: CA certificate, own certificate and key, json5 with its
    user and password, ``zenoh.toml``). SeamapError in one line for a bad argument or an
    unwritable folder."""
    if not vehicles:
        raise SeamapError("--vehicle: give at least one")
    if len(set(vehicles)) != len(vehicles):
        raise SeamapError(f"--vehicle: given twice ({', '.join(vehicles)})")
    for vehicle in vehicles:
        _check_vehicle(vehicle)
        if ":" in vehicle:  # the users file is "user:password"
            raise SeamapError(f"--vehicle {vehicle!r}: no ':' in a vehicle id")
    hosts = _check_common(shores, port, hosts)
    return _into_new_folder(
        Path(out),
        lambda folder: _write_fleet_set(folder, vehicles, hosts, shores, install_dir, port),
    )


def _write_fleet_set(
    out: Path,
    vehicles: list[str],
    hosts: list[str],
    shores: int,
    install_dir: Path | None,
    port: int,
) -> FleetSecuritySet:
    ca = _new_ca(out, "+".join(vehicles))
    router = out / "router"
    _identity(router, "router", "seamap-router", ca, hosts)
    shore_users = [f"shore-{n}" for n in range(1, shores + 1)]
    users = [boat_user(v) for v in vehicles] + shore_users
    passwords = _users_file(router, users)
    config = router_zenoh(_where(router, install_dir), vehicles, shore_users, port)
    _write(router / "router.json5", _FLEET_HEADER + json.dumps(config, indent=2) + "\n")
    _write(
        router / "zenoh.toml",
        "# The [zenoh] table of the router's site file (`seamap router --config`):\n"
        + _toml_lines(_where(router, install_dir) / "router.json5", [f"tls/0.0.0.0:{port}"], []),
    )
    connect = f"tls/{_bracket(hosts[0])}:{port}"
    folders = {}
    for user in users:
        folder = out / user
        _identity(folder, user, user, ca)
        where = _where(folder, install_dir)
        config = shore_zenoh(where, user, passwords[user], hosts[0], port, mode="client")
        _write(folder / f"{user}.json5", _FLEET_HEADER + json.dumps(config, indent=2) + "\n", 0o600)
        _write(
            folder / "zenoh.toml",
            f"# The [zenoh] table of {user}'s site file:\n"
            + '[zenoh]\nmode = "client"\n'
            + _toml_lines(where / f"{user}.json5", [], [connect]).removeprefix("[zenoh]\n"),
        )
        folders[user] = folder
    return FleetSecuritySet(
        out,
        router,
        {v: folders[boat_user(v)] for v in vehicles},
        [folders[user] for user in shore_users],
        users,
        port,
    )


_Set = TypeVar("_Set")


def _into_new_folder(out: Path, write: Callable[[Path], _Set]) -> _Set:
    """``write(out)`` into a folder that holds no set yet (created if need be); one-line
    SeamapError if it holds one or cannot be written."""
    if (out / "ca.key").exists():
        raise SeamapError(f"{out}: already holds a security set (ca.key); choose another --out")
    try:
        out.mkdir(parents=True, exist_ok=True)
        return write(out)
    except OSError as exc:
        raise SeamapError(f"{out}: cannot write the security set ({exc.strerror or exc})") from None
