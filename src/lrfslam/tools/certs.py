"""``lrfslam certs OUT_DIR --host ROBOT_HOST [--host ...]``: a private CA and the certificates of deploy/zenoh/*.json5.

Writes into OUT_DIR (deploy/README.md, "Access control"):

    ca.pem, ca-key.pem            the CA: made when absent, reused when there, so that the
                                  certificates it issued earlier stay valid. Keep ca-key.pem off the robot.
    router.pem, router-key.pem    CN lrfslam-router, for the names and addresses desks dial
                                  (zenohd, localhost, 127.0.0.1 and every --host): a client that
                                  verifies names (verify_name_on_connect) refuses any other.
    service.pem, service-key.pem  CN lrfslam-service: the pipeline services' rights, on every robot
    monitor.pem, monitor-key.pem  CN lrfslam-monitor: a monitor's (read only)
    ros2-desk.pem, ...            CN lrfslam-ros2-desk: a ROS 2 desk's (reads the ROS 2 topics)
    ros2-robot.pem, ...           CN lrfslam-ros2-robot: a ROS 2 robot's (publishes its /scan, /odom)
    service-ROBOT.pem, ...        with ``--robot ROBOT``: CN lrfslam-service-ROBOT, the services'
                                  rights on that robot's keys only, for a router several robots share

The common names are what deploy/zenoh/router-tls-acl.json5 grants rights to (:data:`ROLES`; a
test reads both); a robot's certificate needs the lines :func:`robot_acl` prints added to it.
A certificate or key already in OUT_DIR is never overwritten silently: without ``--renew`` or
``--if-absent`` one there stops the command with one line and exit 1 before anything is
written. ``--renew ROLE`` issues that role anew (signed by the same CA, so nothing else needs to
change), and any role missing, leaving the others as they are; ``--if-absent`` (compose's first
start) issues only what is missing, so a second start changes nothing. Keys are written 0600,
certificates 0644.

Written with the ``cryptography`` package rather than by calling ``openssl``: the extensions
rustls (Zenoh's TLS) insists on are set in one place and tested in-process, nothing depends on an
``openssl`` binary of some version being installed (the container image, a Windows or macOS desk),
and no temporary request or extension files are left about the key folder.
"""

from __future__ import annotations

import argparse
import datetime as dt
import ipaddress
import json
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from lrfslam.errors import ConfigError
from lrfslam.msgs import topics


@dataclass(frozen=True)
class Role:
    """One certificate OUT_DIR holds: its file stem, common name and whether it serves (the router)."""

    name: str
    common_name: str
    server: bool = False


ROLES = (Role("router", "lrfslam-router", server=True), Role("service", "lrfslam-service"),
         Role("monitor", "lrfslam-monitor"), Role("ros2-desk", "lrfslam-ros2-desk"),
         Role("ros2-robot", "lrfslam-ros2-robot"))


#: What the router's certificate always names: the compose network's name for it and loopback,
#: which the services and the router's own healthcheck dial.
ALWAYS_NAMES = ("zenohd", "localhost", "127.0.0.1")
CA_DAYS = 3650
#: Apple's limit for a TLS server certificate, kept for every role (as deploy/zenoh/make-certs.sh's openssl did).
CERT_DAYS = 825
#: Valid from a little before now, so that a desk whose clock is a few minutes behind accepts them.
BACKDATE = dt.timedelta(minutes=5)
CA_COMMON_NAME = "lrfslam CA"
KEY_MODE, CERT_MODE = 0o600, 0o644
_HOST_NAME = re.compile(r"^(?=.{1,253}$)[A-Za-z0-9_]([A-Za-z0-9_-]{0,62})(\.[A-Za-z0-9_]([A-Za-z0-9_-]{0,62}))*\.?$")


def robot_role(robot: str) -> Role:
    """The services' certificate limited to ``robot``'s keys (``--robot``)."""
    topics.check_robot(robot)
    return Role(f"service-{robot}", f"lrfslam-service-{robot}")


def robot_acl(robot: str) -> dict:
    """The rule, subject and policy that give :func:`robot_role`'s certificate the services' rights
    on ``lrf/<robot>/**`` alone: added to a router's ``access_control`` (its ``rules``, ``subjects``
    and ``policies`` lists), they keep one robot's key from publishing as another."""
    role = robot_role(robot)
    return {
        "rules": [{"id": role.name, "permission": "allow", "flows": ["ingress", "egress"],
                   "messages": ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                                "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"],
                   "key_exprs": [topics.everything(robot)]}],
        "subjects": [{"id": role.name, "cert_common_names": [role.common_name]}],
        "policies": [{"id": role.name, "rules": [role.name], "subjects": [role.name]}],
    }


def files(out: Path, stem: str) -> tuple[Path, Path]:
    """(certificate, key) of ``stem`` in ``out``."""
    return out / f"{stem}.pem", out / f"{stem}-key.pem"


def subject_names(hosts: list[str]) -> list[x509.GeneralName]:
    """The router's subject alternative names: ALWAYS_NAMES and ``hosts``, each an IP address or a DNS name.

    Raises
    ------
    ConfigError
        A host that is neither an address nor a valid host name.
    """
    names: list[x509.GeneralName] = []
    for host in dict.fromkeys([*ALWAYS_NAMES, *hosts]):
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host.strip("[]"))))
        except ValueError:
            if not _HOST_NAME.match(host):
                raise ConfigError(f"--host {host!r} is neither an IP address nor a host name") from None
            names.append(x509.DNSName(host.rstrip(".").lower()))
    return names


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _builder(subject: str, issuer: x509.Name, key: ec.EllipticCurvePrivateKey, now: dt.datetime,
             days: int) -> x509.CertificateBuilder:
    return (x509.CertificateBuilder().subject_name(_name(subject)).issuer_name(issuer)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - BACKDATE).not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False))


def make_ca(now: dt.datetime) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    """A new CA: P-256 key, may sign certificates (and no CA below it)."""
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (_builder(CA_COMMON_NAME, _name(CA_COMMON_NAME), key, now, CA_DAYS)
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                         crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
            .sign(key, hashes.SHA256()))
    return cert, key


def issue(role: Role, ca: x509.Certificate, ca_key: ec.EllipticCurvePrivateKey, hosts: list[str],
          now: dt.datetime) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    """``role``'s certificate signed by ``ca``: a client certificate, and for the router also a
    server certificate naming ALWAYS_NAMES and ``hosts`` (the router is a client of other routers)."""
    key = ec.generate_private_key(ec.SECP256R1())
    usages = [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH] if role.server \
        else [ExtendedKeyUsageOID.CLIENT_AUTH]
    builder = (_builder(role.common_name, ca.subject, key, now, CERT_DAYS)
               .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
               .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
               .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                                            data_encipherment=False, key_agreement=False, key_cert_sign=False,
                                            crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
               .add_extension(x509.ExtendedKeyUsage(usages), critical=False))
    if role.server:
        builder = builder.add_extension(x509.SubjectAlternativeName(subject_names(hosts)), critical=False)
    return builder.sign(ca_key, hashes.SHA256()), key


def load_ca(out: Path) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey] | None:
    """The CA already in ``out``, or None if there is none.

    Raises
    ------
    ConfigError
        Only one of its two files is there, they do not belong together, or one cannot be read as PEM.
    """
    cert_path, key_path = files(out, "ca")
    if not cert_path.exists() and not key_path.exists():
        return None
    if not (cert_path.exists() and key_path.exists()):
        have, lack = (cert_path, key_path) if cert_path.exists() else (key_path, cert_path)
        raise ConfigError(f"{have} is there but {lack.name} is not: cannot sign with half a CA "
                          "(put the missing file back, or use another OUT_DIR for a new CA)")
    try:
        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"cannot read the CA in {out}: {exc}") from None
    if not isinstance(key, ec.EllipticCurvePrivateKey) or key.public_key() != cert.public_key():
        raise ConfigError(f"{key_path} is not the key of {cert_path}")
    return cert, key


def write(path: Path, data: bytes, mode: int) -> None:
    """``data`` into ``path`` with exactly ``mode`` (whatever the umask), replacing it at once: a
    reader sees the old file or the new one, and a key is never readable by others, not even while written."""
    tmp = path.with_name(f".{path.name}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, path)


def _pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lrfslam certs", description=__doc__.splitlines()[0])
    p.add_argument("out", metavar="OUT_DIR", help="folder of the CA and the certificates (made if missing)")
    p.add_argument("--host", action="append", default=[], metavar="NAMES_OR_IPS",
                   help="names or addresses desks dial to reach the router, comma-separated (repeatable); "
                        "needed when the router's certificate is issued, except with --if-absent")
    p.add_argument("--robot", action="append", default=[], metavar="ROBOT",
                   help="also a services' certificate limited to ROBOT's keys (repeatable); prints the lines "
                        "the router's access-control list needs for it")
    p.add_argument("--renew", action="append", default=[], metavar="ROLE",
                   help=f"issue ROLE ({', '.join(r.name for r in ROLES)}, service-ROBOT) anew, replacing its "
                        "certificate and key (repeatable); without it an existing one stops the command")
    p.add_argument("--if-absent", action="store_true",
                   help="issue only what OUT_DIR lacks and keep the rest (a container's first start)")
    p.add_argument("--shown-as", metavar="TEXT",
                   help="how the closing message names OUT_DIR (e.g. the host folder a container mounts there)")
    return p


def main(argv: list[str] | None = None) -> int:
    p = parser()
    args = p.parse_args(argv)
    out = Path(args.out)
    hosts = [h.strip() for arg in args.host for h in arg.split(",") if h.strip()]
    roles_all = [*ROLES, *(robot_role(r) for r in dict.fromkeys(args.robot))]
    if unknown := [r for r in args.renew if r not in {role.name for role in roles_all}]:
        p.error(f"--renew {unknown[0]}: not a role here ({', '.join(role.name for role in roles_all)})")
    present = {role.name: [path for path in files(out, role.name) if path.exists()] for role in roles_all}
    if not args.renew and not args.if_absent and (existing := [path for paths in present.values() for path in paths]):
        role = existing[0].name.removesuffix(".pem").removesuffix("-key")
        print(f"lrfslam certs: {existing[0]} exists; not overwriting it (--renew {role} issues it anew, "
              "signed by the same CA; --if-absent issues only what is missing)", file=sys.stderr)
        return 1
    # With --renew: those roles, and any role not wholly there (half of one is of no use); the
    # others are left as they are.
    roles = [role for role in roles_all if role.name in args.renew or len(present[role.name]) < 2]
    if not hosts and not args.if_absent and any(role.server for role in roles):
        p.error("--host is needed to issue the router's certificate (the name or address desks dial)")
    subject_names(hosts)   # a bad one stops the command before anything is written
    if not roles:   # nothing to sign: the CA's key may well be off this machine, as it should be
        print(closing_line(args.shown_as or str(out.resolve()), "kept"))
        return 0
    ca = load_ca(out)
    if ca is None and (kept := [role.name for role in roles_all if role not in roles]):
        raise ConfigError(f"{out} holds no CA but holds {', '.join(kept)}: a new CA would not have signed "
                          "them (put ca.pem and ca-key.pem back, --renew every role, or use another OUT_DIR)")
    now = dt.datetime.now(dt.UTC)
    out.mkdir(parents=True, exist_ok=True)
    signed_by = "the existing CA"
    if ca is None:
        ca = make_ca(now)
        signed_by = "the new CA"
        ca_cert, ca_key = files(out, "ca")
        write(ca_key, _key_pem(ca[1]), KEY_MODE)
        print(f"wrote {ca_key.resolve()} (the CA's key, mode 0{KEY_MODE:o}: keep it off the robot)")
        write(ca_cert, _pem(ca[0]), CERT_MODE)
        print(f"wrote {ca_cert.resolve()} (the CA: every host trusts it)")
    for role in roles:
        cert, key = issue(role, ca[0], ca[1], hosts, now)
        cert_path, key_path = files(out, role.name)
        write(key_path, _key_pem(key), KEY_MODE)
        print(f"wrote {key_path.resolve()} (mode 0{KEY_MODE:o})")
        write(cert_path, _pem(cert), CERT_MODE)
        names = f", for {', '.join(dict.fromkeys([*ALWAYS_NAMES, *hosts]))}" if role.server else ""
        print(f"wrote {cert_path.resolve()} (CN {role.common_name}{names}; signed by {signed_by}, valid until "
              f"{cert.not_valid_after_utc:%Y-%m-%d})")
    for robot in dict.fromkeys(args.robot):
        print(f"for {robot_role(robot).common_name}, add to the router's access_control lists (then restart it): "
              f"{json.dumps(robot_acl(robot))}")
    print(closing_line(args.shown_as or str(out.resolve()), "made now"))
    return 0


def closing_line(where: str, done: str) -> str:
    """The one line that says where the certificates are and what a desk needs of them."""
    return (f"certificates {done} in {where}: a desk needs ca.pem, monitor.pem and monitor-key.pem from there with "
            "deploy/zenoh/monitor-tls.json5, in a tls/ folder where it runs lrfslam (a ROS 2 desk: ros2-desk.pem and "
            "its key; deploy/README.md, 'Access control')")
