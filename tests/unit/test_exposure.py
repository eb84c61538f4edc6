"""What counts as loopback, for ``lrfslam up --listen`` and ``lrfslam monitor`` (src/lrfslam/tools/exposure.py),
and where the monitor's token comes from.

Properties over every IPv4 address and a sample of IPv6 ones, against the definition: loopback is
127.0.0.0/8 and ::1 (and the IPv4-mapped form of 127/8); every other address, 0.0.0.0 and ::
(every interface) included, is beyond it, and so is any host name but ``localhost``.
"""

from __future__ import annotations

import ipaddress

import pytest
from hypothesis import given
from hypothesis import strategies as st

from lrfslam.errors import ConfigError
from lrfslam.tools.exposure import (
    TOKEN_ENV,
    endpoint_host,
    is_loopback,
    plain_beyond_loopback,
    read_token,
)

LOOPBACK_V4 = ipaddress.ip_network("127.0.0.0/8")


@given(st.ip_addresses(v=4), st.integers(1, 65535))
def test_ipv4_is_loopback_exactly_in_127_8(addr, port):
    inside = addr in LOOPBACK_V4
    assert is_loopback(str(addr)) == inside
    assert is_loopback(f"::ffff:{addr}") == inside
    assert endpoint_host(f"tcp/{addr}:{port}") == ("tcp", str(addr))
    for proto in ("tcp", "udp", "ws"):
        assert plain_beyond_loopback(f"{proto}/{addr}:{port}") == (not inside)
    for proto in ("tls", "quic", "unixsock-stream"):
        assert not plain_beyond_loopback(f"{proto}/{addr}:{port}")


@given(st.ip_addresses(v=6), st.integers(1, 65535))
def test_ipv6_is_loopback_only_as_1_or_mapped_127(addr, port):
    expected = addr == ipaddress.IPv6Address("::1") or (addr.ipv4_mapped is not None
                                                         and addr.ipv4_mapped in LOOPBACK_V4)
    assert is_loopback(str(addr)) == expected
    assert endpoint_host(f"udp/[{addr}]:{port}") == ("udp", str(addr))
    assert plain_beyond_loopback(f"udp/[{addr}]:{port}#iface=eth0") == (not expected)


@pytest.mark.parametrize(("endpoint", "plain_beyond"), [
    ("tcp/127.0.0.1:7447", False),
    ("tcp/127.8.9.10:7447", False),
    ("tcp/localhost:7447", False),
    ("TCP/LocalHost.:7447", False),
    ("tcp/[::1]:7447", False),
    ("tcp/0.0.0.0:7447", True),         # every interface
    ("tcp/[::]:7447", True),
    ("udp/0.0.0.0:7447", True),
    ("tcp/robot.local:7447", True),     # a name: whatever it resolves to
    ("tcp/localhost.example:7447", True),
    ("tcp/192.168.1.5:7447?prio=1-7", True),
    ("tls/0.0.0.0:7448", False),
    ("quic/0.0.0.0:7448", False),
    ("unixsock-stream//tmp/zenoh.sock", False),
])
def test_endpoints(endpoint, plain_beyond):
    assert plain_beyond_loopback(endpoint) == plain_beyond


def test_not_an_endpoint():
    with pytest.raises(ConfigError, match="not a Zenoh endpoint"):
        plain_beyond_loopback("0.0.0.0:7447")


def test_the_token_comes_from_the_file_then_the_environment(tmp_path):
    (tmp_path / "token").write_text("  from-the-file-0123456789\n")
    env = {TOKEN_ENV: "from-the-environment-0123"}
    assert read_token(str(tmp_path / "token"), env) == "from-the-file-0123456789"
    assert read_token(None, env) == "from-the-environment-0123"
    assert read_token(None, {TOKEN_ENV: ""}) is None and read_token(None, {}) is None


@pytest.mark.parametrize("token", ["short-token", "has a space in it 0123", "semi;colon-0123456789", "é" * 20])
def test_a_token_a_url_or_cookie_would_mangle_or_a_short_one_is_refused(token):
    with pytest.raises(ConfigError, match="at least 16 characters of A-Z a-z 0-9"):
        read_token(None, {TOKEN_ENV: token})


def test_an_unreadable_token_file_is_one_line(tmp_path):
    with pytest.raises(ConfigError, match=r"cannot read --token-file .*nothing: No such file"):
        read_token(str(tmp_path / "nothing"), {})
