"""Who can reach what a command serves: loopback only, or beyond.

``lrfslam up --listen`` and ``lrfslam router --listen`` refuse a plain Zenoh endpoint (no
encryption, no authentication: anyone who reaches it reads and publishes on the bus) beyond
loopback unless told ``--insecure`` (:func:`check_listen`), and ``lrfslam monitor`` refuses to
serve its web pages beyond loopback without a token (src/lrfslam/tools/monitor.py): all ask here,
so that they agree on what loopback is. A host name other than ``localhost`` counts as beyond loopback: what it resolves to is not
known for sure when the command starts, and may change while it runs.
"""

from __future__ import annotations

import ipaddress
import logging
import re
from collections.abc import Mapping
from pathlib import Path

from lrfslam.errors import ConfigError

#: Zenoh link protocols with neither encryption nor authentication (tls/ and quic/ have both).
PLAIN_PROTOCOLS = frozenset({"tcp", "udp", "ws"})
#: The environment variable that holds the monitor's token when no --token-file is given.
TOKEN_ENV = "LRFSLAM_MONITOR_TOKEN"
#: A token is at least this long: 16 random characters of the alphabet below are ~96 bits.
MIN_TOKEN_CHARS = 16
#: Characters that pass unescaped in a URL query and a cookie.
_TOKEN = re.compile(r"^[A-Za-z0-9._~-]+$")


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an address, possibly in brackets, or a name) is this machine's loopback only:
    127.0.0.0/8, ::1 (also as ::ffff:127.x.y.z) or ``localhost``. 0.0.0.0 and :: are every interface."""
    host = host.strip().removeprefix("[").removesuffix("]")
    if host.lower().rstrip(".") == "localhost":
        return True
    try:
        addr = ipaddress.ip_address(host.split("%", 1)[0])   # fe80::1%eth0: the scope is not the address
    except ValueError:
        return False
    if isinstance(addr, ipaddress.IPv6Address) and addr.ipv4_mapped is not None:
        addr = addr.ipv4_mapped
    return addr.is_loopback


def endpoint_host(endpoint: str) -> tuple[str, str]:
    """(protocol, host) of a Zenoh endpoint ``protocol/address[?metadata][#config]``, the address
    being ``host:port`` or ``[v6 address]:port``.

    Raises
    ------
    ConfigError
        No ``protocol/`` in front.
    """
    protocol, slash, address = endpoint.partition("/")
    if not slash or not protocol:
        raise ConfigError(f"{endpoint!r} is not a Zenoh endpoint (protocol/address, e.g. tcp/127.0.0.1:7447)")
    address = re.split(r"[?#]", address, maxsplit=1)[0]
    if address.startswith("["):
        host = address[1:address.find("]")] if "]" in address else address[1:]
    elif address.count(":") == 1:
        host = address.split(":", 1)[0]
    else:
        host = address
    return protocol.lower(), host


def plain_beyond_loopback(endpoint: str) -> bool:
    """Whether ``endpoint`` is a plain (tcp/, udp/, ws/) endpoint that others than this machine may reach."""
    protocol, host = endpoint_host(endpoint)
    return protocol in PLAIN_PROTOCOLS and not is_loopback(host)


def check_listen(endpoints: list[str], insecure: bool, log: logging.Logger | None) -> None:
    """Refuse plain ``endpoints`` beyond loopback unless ``insecure``; with it, warn on ``log`` once
    for each (None: the process that listens warns, ``lrfslam up``'s router).

    Raises
    ------
    ConfigError
        A plain endpoint beyond loopback without ``insecure``.
    """
    for ep in filter(plain_beyond_loopback, endpoints):
        if not insecure:
            raise ConfigError(f"--listen {ep} is plain (no TLS) beyond loopback: whoever reaches it can read and "
                              "publish on the bus; listen on tls/ with a --zenoh-config of the router's certificate "
                              "(deploy/README.md, 'Access control'), or pass --insecure on a closed network")
        if log is not None:
            log.warning("--listen %s: plain, beyond loopback, no authentication (--insecure): whoever reaches it can "
                        "read and publish on the bus", ep)


def read_token(path: str | None, env: Mapping[str, str]) -> str | None:
    """The monitor's token: the content of ``path`` (surrounding whitespace stripped), else the
    environment's ``LRFSLAM_MONITOR_TOKEN`` (empty counts as unset); None if neither gives one.

    Raises
    ------
    ConfigError
        The file cannot be read, or the token is too short or has characters a URL or cookie would
        have to escape.
    """
    if path:
        try:
            token, where = Path(path).read_text(encoding="utf-8").strip(), f"--token-file {path}"
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(f"cannot read --token-file {path}: {getattr(exc, 'strerror', None) or exc}") from None
    elif env.get(TOKEN_ENV):
        token, where = env[TOKEN_ENV].strip(), TOKEN_ENV
    else:
        return None
    if len(token) < MIN_TOKEN_CHARS or not _TOKEN.match(token):
        raise ConfigError(f"the token in {where} must be at least {MIN_TOKEN_CHARS} characters of A-Z a-z 0-9 . _ ~ - "
                          "(make one with: python3 -c 'import secrets; print(secrets.token_urlsafe(32))')")
    return token
