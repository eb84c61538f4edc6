"""``lrfslam certs``: the files it writes, checked by real TLS handshakes on loopback.

Python's ``ssl`` (OpenSSL) plays the router with router.pem and demands a client certificate, as
deploy/zenoh/router-tls.json5 has Zenoh do; clients dial it by the names the router's certificate
must carry. Zenoh's own TLS (rustls) runs on these files in tests/deploy/test_zenoh_tls.py and
tests/deploy/test_zenoh_acl.py, through deploy/zenoh/make-certs.sh.
"""

from __future__ import annotations

import ipaddress
import json
import os
import socket
import ssl
import stat
import threading
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from lrfslam.cli import main as lrfslam
from lrfslam.tools.certs import ROLES, robot_acl

FILES = {"ca.pem", "ca-key.pem", *(f"{r.name}{suffix}" for r in ROLES for suffix in (".pem", "-key.pem"))}


def cert(folder: Path, stem: str) -> x509.Certificate:
    return x509.load_pem_x509_certificate((folder / f"{stem}.pem").read_bytes())


def handshake(folder: Path, server_name: str, client: str | None, client_folder: Path | None = None) -> str:
    """A TLS connection on loopback to a server holding router.pem that demands a client certificate
    signed by ``folder``'s CA; the client trusts that CA, checks ``server_name`` and presents
    ``client``'s certificate from ``client_folder`` (default ``folder``; None: no certificate).
    Returns the common name the server saw."""
    server_ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    server_ctx.load_cert_chain(folder / "router.pem", folder / "router-key.pem")
    server_ctx.load_verify_locations(folder / "ca.pem")
    server_ctx.verify_mode = ssl.CERT_REQUIRED
    client_ctx = ssl.create_default_context(cafile=str(folder / "ca.pem"))
    if client is not None:
        where = client_folder or folder
        client_ctx.load_cert_chain(where / f"{client}.pem", where / f"{client}-key.pem")
    seen: dict[str, object] = {}
    with socket.create_server(("127.0.0.1", 0)) as listener:
        def serve() -> None:
            conn, _ = listener.accept()
            try:
                with server_ctx.wrap_socket(conn, server_side=True) as tls:
                    subject = dict(pair[0] for pair in tls.getpeercert()["subject"])
                    seen["cn"] = subject["commonName"]
                    tls.sendall(b"ok")
            except (ssl.SSLError, OSError) as exc:
                seen["error"] = exc
        thread = threading.Thread(target=serve)
        thread.start()
        try:
            with socket.create_connection(listener.getsockname()) as raw, \
                    client_ctx.wrap_socket(raw, server_hostname=server_name) as tls:
                # TLS 1.3: the server judges the client's certificate after the client's handshake
                # is done; a refusal arrives on the first read.
                assert tls.recv(2) == b"ok"
        finally:
            thread.join(10)
    if "error" in seen:
        raise seen["error"]
    return seen["cn"]


@pytest.fixture(scope="module")
def issued(tmp_path_factory):
    out = tmp_path_factory.mktemp("certs") / "tls"
    assert lrfslam(["certs", str(out), "--host", "robot.test", "--host", "10.1.2.3", "--host", "::1"]) == 0
    return out


def test_it_writes_the_files_of_make_certs_and_says_how_to_give_a_desk_them(tmp_path, capsys):
    assert lrfslam(["certs", str(tmp_path / "tls"), "--host", "robot.test"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert {p.name for p in (tmp_path / "tls").iterdir()} == FILES
    assert sorted(Path(ln.split()[1]).name for ln in lines[:-1]) == sorted(FILES)
    assert all(ln.startswith("wrote ") for ln in lines[:-1])
    assert lines[-1].startswith(f"certificates made now in {(tmp_path / 'tls').resolve()}: a desk needs ca.pem, "
                                "monitor.pem and monitor-key.pem")


@pytest.mark.parametrize("name", ["robot.test", "10.1.2.3", "::1", "localhost", "127.0.0.1", "zenohd"])
@pytest.mark.parametrize("client", ["service", "monitor", "ros2-desk", "ros2-robot"])
def test_a_client_of_the_ca_reaches_the_router_by_every_name_it_carries(issued, name, client):
    assert handshake(issued, name, client) == f"lrfslam-{client}"


def test_a_name_the_router_does_not_carry_is_refused(issued):
    with pytest.raises(ssl.SSLCertVerificationError, match="mismatch"):
        handshake(issued, "elsewhere.test", "monitor")


def test_the_router_refuses_a_client_without_a_certificate_or_from_another_ca(issued, tmp_path):
    with pytest.raises((ssl.SSLError, ConnectionError)):
        handshake(issued, "robot.test", None)
    rogue = tmp_path / "rogue"
    assert lrfslam(["certs", str(rogue), "--host", "robot.test"]) == 0
    with pytest.raises((ssl.SSLError, ConnectionError)):
        handshake(issued, "robot.test", "monitor", client_folder=rogue)


def test_common_names_usages_and_the_routers_names(issued):
    ca = cert(issued, "ca")
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    for role in ROLES:
        c = cert(issued, role.name)
        assert c.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == role.common_name
        assert c.issuer == ca.subject
        c.verify_directly_issued_by(ca)
        assert not c.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
        usages = set(c.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value)
        assert usages == ({ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH} if role.server
                          else {ExtendedKeyUsageOID.CLIENT_AUTH})
    san = cert(issued, "router").extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert set(san.get_values_for_type(x509.DNSName)) == {"zenohd", "localhost", "robot.test"}
    assert set(san.get_values_for_type(x509.IPAddress)) == {ipaddress.ip_address(a)
                                                           for a in ("127.0.0.1", "10.1.2.3", "::1")}


def test_keys_are_0600_and_certificates_0644_whatever_the_umask(tmp_path):
    for umask in (0o000, 0o077):
        old = os.umask(umask)
        try:
            assert lrfslam(["certs", str(tmp_path / f"u{umask:o}"), "--host", "robot.test"]) == 0
        finally:
            os.umask(old)
        modes = {p.name: stat.S_IMODE(p.stat().st_mode) for p in (tmp_path / f"u{umask:o}").iterdir()}
        assert modes == {name: 0o600 if name.endswith("-key.pem") else 0o644 for name in FILES}


def test_a_second_run_refuses_to_overwrite_and_renew_reuses_the_ca(tmp_path, capsys):
    out = tmp_path / "tls"
    assert lrfslam(["certs", str(out), "--host", "robot.test"]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    capsys.readouterr()
    assert lrfslam(["certs", str(out), "--host", "robot.test", "--host", "new.test"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "exists; not overwriting it (--renew" in err, err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before

    # The router anew, for one more name, by the same CA: the other certificates stay valid.
    assert lrfslam(["certs", str(out), "--renew", "router", "--host", "robot.test", "--host", "new.test"]) == 0
    after = {p.name: p.read_bytes() for p in out.iterdir()}
    assert {n for n in FILES if after[n] != before[n]} == {"router.pem", "router-key.pem"}
    assert handshake(out, "new.test", "monitor") == "lrfslam-monitor"
    # A missing role is issued by the existing CA too; a renewal needs no --host unless it is the router's.
    (out / "service.pem").unlink()
    (out / "service-key.pem").unlink()
    assert lrfslam(["certs", str(out), "--renew", "monitor"]) == 0
    assert handshake(out, "robot.test", "service") == "lrfslam-service"
    assert (out / "ca.pem").read_bytes() == before["ca.pem"]


def test_a_bad_or_missing_host_writes_nothing(tmp_path, capsys):
    out = tmp_path / "tls"
    assert lrfslam(["certs", str(out), "--host", "robot.test", "--host", "robot test"]) == 2
    assert capsys.readouterr().err == ("lrfslam certs: error: --host 'robot test' is neither an IP address "
                                       "nor a host name\n")
    with pytest.raises(SystemExit) as exc:
        lrfslam(["certs", str(out)])
    assert exc.value.code == 2 and "--host is needed" in capsys.readouterr().err
    assert not out.exists()


def test_half_a_ca_is_refused(tmp_path, capsys):
    out = tmp_path / "tls"
    assert lrfslam(["certs", str(out), "--host", "robot.test"]) == 0
    for p in out.iterdir():
        if p.name != "ca.pem":
            p.unlink()
    assert lrfslam(["certs", str(out), "--host", "robot.test"]) == 2
    assert "ca-key.pem is not" in capsys.readouterr().err
    assert [p.name for p in out.iterdir()] == ["ca.pem"]
    # No CA at all, but certificates it signed: a new CA would leave them orphaned.
    (out / "ca.pem").unlink()
    assert lrfslam(["certs", str(tmp_path / "other"), "--host", "robot.test"]) == 0
    for p in (tmp_path / "other").iterdir():
        if not p.name.startswith(("ca", "router")):
            p.rename(out / p.name)
    assert lrfslam(["certs", str(out), "--renew", "router", "--host", "robot.test"]) == 2
    assert "holds no CA but holds service, monitor, ros2-desk, ros2-robot:" in capsys.readouterr().err
    assert not (out / "router.pem").exists()


def test_if_absent_makes_what_is_missing_and_never_replaces(tmp_path, capsys):
    """Compose's first start: everything, with the router's names from a comma-separated list;
    later starts keep every file; a lost role comes back signed by the same CA."""
    out = tmp_path / "tls"
    assert lrfslam(["certs", str(out), "--if-absent", "--host", "robot.test, 10.1.2.3", "--shown-as", "../tls"]) == 0
    assert capsys.readouterr().out.splitlines()[-1].startswith("certificates made now in ../tls: a desk needs")
    assert {p.name for p in out.iterdir()} == FILES
    assert handshake(out, "10.1.2.3", "monitor") == "lrfslam-monitor"
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert lrfslam(["certs", str(out), "--if-absent", "--host", "other.test"]) == 0
    assert capsys.readouterr().out.startswith("certificates kept in ")
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    (out / "monitor.pem").unlink()
    assert lrfslam(["certs", str(out), "--if-absent"]) == 0
    after = {p.name: p.read_bytes() for p in out.iterdir()}
    assert {n for n in FILES if after[n] != before[n]} == {"monitor.pem", "monitor-key.pem"}
    assert handshake(out, "robot.test", "monitor") == "lrfslam-monitor"
    # The CA's key moved off the robot, as deploy/README.md advises: the next start still passes,
    # having nothing to sign; one that must sign says why it cannot.
    (out / "ca-key.pem").unlink()
    capsys.readouterr()
    assert lrfslam(["certs", str(out), "--if-absent"]) == 0
    assert capsys.readouterr().out.startswith("certificates kept in ")
    (out / "ros2-desk.pem").unlink()
    assert lrfslam(["certs", str(out), "--if-absent"]) == 2
    assert "ca-key.pem is not" in capsys.readouterr().err


def test_a_robots_certificate_and_the_lines_its_router_needs(tmp_path, capsys):
    out = tmp_path / "tls"
    assert lrfslam(["certs", str(out), "--host", "robot.test", "--robot", "mit-csail"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert cert(out, "service-mit-csail").subject.rfc4514_string() == "CN=lrfslam-service-mit-csail"
    assert handshake(out, "robot.test", "service-mit-csail") == "lrfslam-service-mit-csail"
    (acl_line,) = [ln for ln in lines if "access_control" in ln]
    assert json.loads(acl_line.split(": ", 1)[1]) == robot_acl("mit-csail")
    assert robot_acl("mit-csail")["rules"][0]["key_exprs"] == ["lrf/mit-csail/**"]
    assert lrfslam(["certs", str(tmp_path / "x"), "--host", "robot.test", "--robot", "a/b"]) == 2
    assert not (tmp_path / "x").exists()
    with pytest.raises(SystemExit):
        lrfslam(["certs", str(out), "--renew", "service-robot9"])
    assert "not a role here" in capsys.readouterr().err
