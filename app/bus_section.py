"""The layout's ``bus`` section: zenoh endpoints, TLS and user/password access, checked
with one-line errors before any session opens.

A room spread over several hosts admits only its own hosts with zenoh's own means::

    bus:
      listen: [tls/0.0.0.0:7447]
      tls:                      # zenoh transport/link/tls
        ca: tls/ca.pem          # the room's certificate authority (root_ca_certificate)
        cert: tls/hub.pem       # this host's certificate, shown when listening and connecting
        key: tls/hub.key        # its private key
        mtls: true              # both ends show a certificate signed by the room's CA
        verify_name: true       # the certificate must name the host connected to
      auth:                     # zenoh transport/auth/usrpwd
        user: hub
        password_file: secret/hub.password     # one line: this host's password
        dictionary_file: secret/room.users     # user:password lines of every admitted host

Paths are relative to the layout file's folder; they are made absolute here, so the
resolved layout the launcher writes next to the results still names the same files.
With ``tls`` every endpoint must be ``tls/`` (a ``tcp/`` one would let anyone in).
The default stays loopback-only TCP without TLS, and a room on one host admits its own
workers through a private socket and lets no one else publish in it (``private``, true by
default: :mod:`app.bus_acl`).
"""
from __future__ import annotations

import ipaddress
import os
import re
import socket
import ssl
from dataclasses import dataclass
from pathlib import Path

from app.errors import InputError

__all__ = ["TlsConfig", "AuthConfig", "AclConfig", "PROTOCOLS", "endpoint_problem", "check_endpoints", "parse_bus",
           "certificate_name"]

PROTOCOLS = ("tcp", "tls", "udp", "quic", "ws", "unixsock-stream")
SECURE = ("tls", "quic")           # link protocols that use the transport/link/tls settings
_LABEL = r"[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
_HOSTNAME = re.compile(rf"^{_LABEL}(?:\.{_LABEL})*\.?$")
_ENDPOINT_HINT = "a zenoh endpoint like tcp/127.0.0.1:7447"


@dataclass
class TlsConfig:
    """zenoh's TLS link settings (``transport/link/tls``); the same certificate and key
    serve when listening and when connecting, as every session of the room does both."""

    ca: str                   # root_ca_certificate: the room's certificate authority
    cert: str                 # listen_certificate and connect_certificate
    key: str                  # listen_private_key and connect_private_key
    mtls: bool = True         # enable_mtls: a connecting host must show a room certificate too
    verify_name: bool = True  # verify_name_on_connect: the certificate must name the host

    def to_zenoh(self) -> dict:
        return {"root_ca_certificate": self.ca,
                "listen_certificate": self.cert, "listen_private_key": self.key,
                "connect_certificate": self.cert, "connect_private_key": self.key,
                "enable_mtls": self.mtls, "verify_name_on_connect": self.verify_name}


@dataclass
class AuthConfig:
    """zenoh's user/password authentication (``transport/auth/usrpwd``). The password is
    read from a file when the session opens, so it never appears in a layout."""

    user: str
    password_file: str
    dictionary_file: str      # user:password lines; whoever is not in it is refused

    def to_zenoh(self) -> dict:
        password = _read_text(self.password_file, "bus.auth.password_file", InputError).strip()
        return {"user": self.user, "password": password, "dictionary_file": self.dictionary_file}


@dataclass
class AclConfig:
    """zenoh's access control on the hub, made from the layout (:mod:`app.bus_acl`): a
    host may publish only what the layout's workers on it publish, told apart by the
    common name of the certificate it shows (mutual TLS); ``readers``: further common
    names that may subscribe and publish nothing (a viewer's or a streaming client's)."""

    readers: list = None

    def __post_init__(self):
        self.readers = list(self.readers or [])


def endpoint_problem(endpoint, role: str = "listen") -> str | None:
    """What is syntactically wrong with a zenoh endpoint (``proto/host:port[?meta][#conf]``),
    or None. ``role`` is ``listen`` (port 0 picks a free port) or ``connect``."""
    if not isinstance(endpoint, str) or "/" not in endpoint:
        return f"{endpoint!r} is not {_ENDPOINT_HINT}"
    proto, _, rest = endpoint.partition("/")
    if proto not in PROTOCOLS:
        return f"{endpoint}: unknown protocol {proto!r} (known: {', '.join(PROTOCOLS)})"
    address = rest.split("?", 1)[0].split("#", 1)[0]
    if proto == "unixsock-stream":
        return None if address else f"{endpoint}: needs a socket path"
    host, sep, port = address.rpartition(":")
    if not sep or not host:
        return f"{endpoint}: needs HOST:PORT, as in {proto}/127.0.0.1:7447"
    if not port.isdigit() or int(port) > 65535:
        return f"{endpoint}: port {port!r} is not a number from 0 to 65535"
    if role == "connect" and int(port) == 0:
        return f"{endpoint}: port 0 (a free port) only makes sense to listen on"
    if host.startswith("["):
        try:
            ipaddress.IPv6Address(host[1:-1] if host.endswith("]") else "?")
        except ValueError:
            return f"{endpoint}: {host} is not an IPv6 address"
    elif re.fullmatch(r"[0-9.]+", host):
        try:
            ipaddress.IPv4Address(host)
        except ValueError:
            return f"{endpoint}: {host} is not an IPv4 address"
    elif not _HOSTNAME.match(host):
        return f"{endpoint}: {host!r} is not a host name or address"
    return None


def _host_port(endpoint: str) -> tuple[str, int] | None:
    proto, _, rest = endpoint.partition("/")
    if proto == "unixsock-stream":
        return None
    host, _, port = rest.split("?", 1)[0].split("#", 1)[0].rpartition(":")
    return host.strip("[]"), int(port)


def check_endpoints(listen, connect, tls, resolve: bool = False, error=InputError, prefix: str = "") -> None:
    """Syntax of every endpoint, and TLS endpoints if and only if TLS is set; with
    ``resolve``, every host name must resolve (zenoh would retry it for ever)."""
    for role, endpoints in (("listen", listen), ("connect", connect)):
        for ep in endpoints:
            problem = endpoint_problem(ep, role)
            if problem:
                raise error(f"{prefix}bus.{role}: {problem}")
            proto = ep.partition("/")[0]
            if tls is not None and proto not in SECURE:
                raise error(f"{prefix}bus.{role}: {ep} is not a tls/ endpoint; with bus.tls every endpoint "
                            "must be tls/HOST:PORT, or anyone could connect")
            if tls is None and proto in SECURE:
                raise error(f"{prefix}bus.{role}: {ep} needs a bus.tls section (ca, cert, key)")
            if resolve and (hp := _host_port(ep)) is not None:
                try:
                    socket.getaddrinfo(hp[0], hp[1], type=socket.SOCK_STREAM)
                except (OSError, UnicodeError) as exc:
                    reason = getattr(exc, "strerror", None) or exc
                    raise error(f"{prefix}bus.{role}: {ep}: host {hp[0]!r} does not resolve ({reason})") from None


def _read_text(path: str, field: str, error, where: str = "") -> str:
    prefix = f"{where}: " if where else ""
    try:
        with open(path, encoding="utf-8") as f:
            return f.read()
    except FileNotFoundError:
        raise error(f"{prefix}{field}: {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"{prefix}{field}: cannot read {path} ({getattr(exc, 'strerror', None) or exc})") from None


def _file(section: dict, key: str, folder: Path, field: str, where: str, error, pem: str | None = None) -> str:
    value = section.get(key)
    if not isinstance(value, str) or not value:
        raise error(f"{where}: {field} must be a file path")
    path = str((folder / os.path.expanduser(value)).absolute())
    text = _read_text(path, field, error, where)
    markers = {"certificate": "-----BEGIN CERTIFICATE-----", "private key": "PRIVATE KEY-----"}  # PKCS#8, EC, RSA
    if pem is not None and markers[pem] not in text:
        raise error(f"{where}: {field}: {path} is not a PEM {pem}")
    return path


def _flag(section: dict, key: str, default: bool, field: str, where: str, error) -> bool:
    value = section.get(key, default)
    if not isinstance(value, bool):
        raise error(f"{where}: {field} must be true or false, got {value!r}")
    return value


def _mapping(value, keys: set, required: set, field: str, where: str, error) -> dict:
    if not isinstance(value, dict):
        raise error(f"{where}: {field} must be a mapping with {', '.join(sorted(keys))}")
    unknown = set(value) - keys
    if unknown:
        raise error(f"{where}: {field}: unknown key {sorted(unknown)[0]!r} (known: {', '.join(sorted(keys))})")
    missing = required - {k for k, v in value.items() if v is not None}
    if missing:
        raise error(f"{where}: {field}.{sorted(missing)[0]} is required")
    return value


def parse_tls(value, folder: Path, where: str, error) -> TlsConfig:
    d = _mapping(value, {"ca", "cert", "key", "mtls", "verify_name"}, {"ca", "cert", "key"}, "bus.tls", where, error)
    return TlsConfig(ca=_file(d, "ca", folder, "bus.tls.ca", where, error, "certificate"),
                     cert=_file(d, "cert", folder, "bus.tls.cert", where, error, "certificate"),
                     key=_file(d, "key", folder, "bus.tls.key", where, error, "private key"),
                     mtls=_flag(d, "mtls", True, "bus.tls.mtls", where, error),
                     verify_name=_flag(d, "verify_name", True, "bus.tls.verify_name", where, error))


def parse_auth(value, folder: Path, where: str, error) -> AuthConfig:
    keys = {"user", "password_file", "dictionary_file"}
    d = _mapping(value, keys, keys, "bus.auth", where, error)
    user = d["user"]
    if not isinstance(user, str) or not user or ":" in user or user.strip() != user:
        raise error(f"{where}: bus.auth.user must be a name without ':' or spaces, got {user!r}")
    password_file = _file(d, "password_file", folder, "bus.auth.password_file", where, error)
    if not _read_text(password_file, "bus.auth.password_file", error, where).strip():
        raise error(f"{where}: bus.auth.password_file: {password_file} is empty")
    dictionary_file = _file(d, "dictionary_file", folder, "bus.auth.dictionary_file", where, error)
    lines = [ln.strip() for ln in _read_text(dictionary_file, "bus.auth.dictionary_file", error, where).splitlines()]
    bad = [i for i, ln in enumerate(lines, 1) if ln and (":" not in ln or ln.startswith(":") or ln.endswith(":"))]
    if bad or not any(lines):
        line = f"line {bad[0]} is not user:password" if bad else "it lists no user:password line"
        raise error(f"{where}: bus.auth.dictionary_file: {dictionary_file}: {line}")
    return AuthConfig(user=user, password_file=password_file, dictionary_file=dictionary_file)


def parse_bus(value, path: str, error=InputError) -> dict:
    """The ``bus`` section of the layout file ``path``, checked: the fields of an
    :class:`app.bus.BusConfig` (the config loader builds it; this module knows no bus)."""
    value = value or {}
    known = ("listen", "connect", "multicast", "shm", "tls", "auth", "acl", "private")
    if not isinstance(value, dict):
        raise error(f"{path}: bus must be a mapping with {', '.join(known)}")
    unknown = set(value) - set(known)
    if unknown:
        raise error(f"{path}: bus: unknown key {sorted(unknown)[0]!r} (known: {', '.join(known)})")
    folder = Path(path).parent
    tls = parse_tls(value["tls"], folder, path, error) if value.get("tls") is not None else None
    auth = parse_auth(value["auth"], folder, path, error) if value.get("auth") is not None else None
    acl = parse_acl(value.get("acl"), tls, path, error)
    endpoints = {}
    for key in ("listen", "connect"):
        v = value.get(key)
        if v is not None and (not isinstance(v, list) or not all(isinstance(e, str) for e in v)):
            raise error(f"{path}: bus.{key} must be a list of zenoh endpoints like tcp/127.0.0.1:7447")
        endpoints[key] = list(v or [])
    listen = endpoints["listen"] or [("tls" if tls else "tcp") + "/127.0.0.1:0"]
    check_endpoints(listen, endpoints["connect"], tls, error=error, prefix=f"{path}: ")
    return dict(listen=listen, connect=endpoints["connect"],
                multicast=_flag(value, "multicast", False, "bus.multicast", path, error),
                shm=_flag(value, "shm", True, "bus.shm", path, error), tls=tls, auth=auth, acl=acl,
                private=_flag(value, "private", True, "bus.private", path, error))


def parse_acl(value, tls: TlsConfig | None, where: str, error) -> AclConfig | None:
    """``acl: true`` or ``acl: {readers: [NAME, ...]}`` (false or absent: none). zenoh
    tells the hosts apart by their certificates, so it needs ``tls`` with ``mtls``."""
    if value is None or value is False:
        return None
    if value is True:
        value = {}
    d = _mapping(value, {"readers"}, set(), "bus.acl", where, error)
    readers = d.get("readers") or []
    if not isinstance(readers, list) or not all(isinstance(r, str) and r and r.strip() == r for r in readers):
        raise error(f"{where}: bus.acl.readers must be a list of certificate common names")
    if tls is None or not tls.mtls:
        raise error(f"{where}: bus.acl needs bus.tls with mtls: true (the hub tells hosts apart by the "
                    "certificates they show)")
    certificate_name(tls.cert, error, where)   # the hub's host is the one its certificate names
    return AclConfig(readers=readers)


def certificate_name(path: str, error=InputError, where: str = "") -> str:
    """The common name (CN) of the PEM certificate at ``path`` (one line if it has none)."""
    prefix = f"{where}: " if where else ""
    try:
        subject = ssl._ssl._test_decode_cert(str(path))["subject"]   # CPython's own PEM reader
    except (OSError, ssl.SSLError, AttributeError, KeyError, ValueError) as exc:
        raise error(f"{prefix}bus.tls.cert: {path}: cannot read its subject ({exc})") from None
    names = [v for rdn in subject for k, v in rdn if k == "commonName"]
    if not names:
        raise error(f"{prefix}bus.tls.cert: {path}: the certificate names no common name (CN); bus.acl tells "
                    "hosts apart by it")
    return names[0]
