"""Who can reach what a command serves: loopback only, or beyond.

``lrfslam up --listen`` refuses a plain Zenoh endpoint (no encryption, no authentication: anyone
who reaches it reads and publishes on the bus) beyond loopback unless told ``--insecure``
(src/lrfslam/tools/up.py). A host name other than ``localhost`` counts as beyond loopback: what it
resolves to is not known for sure when the command starts, and may change while it runs.
"""

from __future__ import annotations

import ipaddress
import re

from lrfslam.errors import ConfigError

#: Zenoh link protocols with neither encryption nor authentication (tls/ and quic/ have both).
PLAIN_PROTOCOLS = frozenset({"tcp", "udp", "ws"})


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
