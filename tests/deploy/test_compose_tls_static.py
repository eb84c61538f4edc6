"""deploy/compose.yaml's mutual TLS and access control, and compose.insecure.yaml, checked without a container engine.

What the default file must give: a certs service that makes every certificate the configs name
before the router starts, every stage and the ROS 2 bridge a client of the router's TLS port with
the service certificate, the monitor one with the monitor certificate (what the access-control
list lets read but not publish), the router listening with the access-control config on the
published port and nothing plain, and every file a command names mounted from the repository.
compose.insecure.yaml turns all of it back into plain TCP, and only with --insecure. Both running
for real: tests/deploy/test_compose_podman.py.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import pytest
import yaml
import zenoh

from lrfslam import services
from lrfslam.errors import ConfigError
from lrfslam.runtime.runner import bus_config, service_parser
from lrfslam.tools import certs, monitor, ros2, status
from lrfslam.tools.exposure import check_listen

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
ROUTER = "zenohd"
MONITOR = "monitor"
CERTS = "certs"
_VAR = re.compile(r"\$\{(\w+)(?::?-([^}]*))?\}")


def default(value: str) -> str:
    """``value`` with compose's ${NAME:-default} at its default."""
    return _VAR.sub(lambda m: m.group(2) or "", value)


def targets(svc: dict) -> set[str]:
    """Container paths of a service's mounts, variables at their defaults."""
    return {default(v).split(":")[1] for v in svc.get("volumes", [])}


class _Loader(yaml.SafeLoader):
    """Compose's ``!override`` tag: the value replaces the base file's instead of merging."""


_Loader.add_constructor("!override", lambda loader, node: loader.construct_sequence(node)
                        if isinstance(node, yaml.SequenceNode) else loader.construct_mapping(node))


def load(name: str) -> dict:
    return yaml.load((DEPLOY / name).read_text(), Loader=_Loader)["services"]


@pytest.fixture(scope="module")
def base() -> dict:
    return load("compose.yaml")


def mounted(svc: dict, container_path: str) -> Path:
    """The repository file a container path of ``svc`` comes from (only ./ mounts of deploy/)."""
    for vol in svc["volumes"]:
        host, target, *_ = vol.split(":")
        if container_path.startswith(target + "/") and host.startswith("./"):
            return DEPLOY / host / container_path.removeprefix(target + "/")
    raise AssertionError(f"{container_path} is not mounted from the repository: {svc['volumes']}")


def option(argv: list[str], flag: str) -> list[str]:
    return [argv[i + 1] for i, a in enumerate(argv) if a == flag]


def tls_files(conf: Path, folder: Path) -> set[Path]:
    """The certificate files a Zenoh JSON5 config names, read from ``folder`` instead of its own place."""
    names = re.findall(r'(?:root_ca_certificate|(?:connect|listen)_(?:certificate|private_key)): "([^"]+)"',
                       conf.read_text())
    assert names, conf
    return {folder / Path(n).name for n in names}


def test_the_certs_service_makes_every_file_the_configs_name_once(base, tmp_path, capsys):
    """Its command, run as the container runs it (on a temporary folder): every certificate and key
    the router's, the services' and the monitor's configs name exists afterwards; a second start
    changes nothing and says where they are."""
    svc = base[CERTS]
    argv = [default(a) for a in svc["command"]]
    assert argv[0] == "certs" and "--if-absent" in argv and svc["restart"] == "no"
    folder = argv[1]
    # The same host folder the others mount read-only there; only this one may write it.
    (host,) = [default(v).split(":")[0] for v in svc["volumes"] if default(v).split(":")[1] == folder]
    for name, other in base.items():
        if name != CERTS:
            assert f"{host}:{folder}:ro" in [default(v) for v in other["volumes"]], name
    assert certs.main([str(tmp_path), *argv[2:]]) == 0
    first = capsys.readouterr().out
    assert first.splitlines()[-1].startswith(f"certificates made now in {default(host)} (relative to deploy/)")
    for name in ("router-tls-acl.json5", "service-tls.json5", "monitor-tls.json5"):
        missing = [f for f in tls_files(DEPLOY / "zenoh" / name, tmp_path) if not f.is_file()]
        assert not missing, (name, missing)
    before = {f.name: f.read_bytes() for f in tmp_path.iterdir()}
    assert certs.main([str(tmp_path), *argv[2:]]) == 0
    assert capsys.readouterr().out.splitlines() == [first.splitlines()[-1].replace("made now", "kept")]
    assert {f.name: f.read_bytes() for f in tmp_path.iterdir()} == before


def test_the_lists_subjects_are_the_roles_certs_issues():
    acl = (DEPLOY / "zenoh" / "router-tls-acl.json5").read_text()
    named = set(re.findall(r'cert_common_names: \["([^"]+)"\]', acl))
    assert named == {r.common_name for r in certs.ROLES if not r.server}


def test_stages_are_tls_clients_with_the_service_certificate(base):
    for name in services.NAMES:
        argv = base[name]["command"]
        assert argv[0] == name
        args = service_parser(services.spec(name)).parse_args(argv[1:])
        assert bus_config(args, {}, {}).connect == ("tls/zenohd:7447",)
        conf = mounted(base[name], args.zenoh_config)
        assert conf.name == "service-tls.json5" and conf.is_file()
        zenoh.Config.from_file(str(conf))
        assert "/etc/lrfslam/tls" in targets(base[name])


def test_the_ros2_bridge_is_a_tls_client_with_the_service_certificate(base):
    args = ros2.parser().parse_args(base["ros2"]["command"][1:])
    assert args.connect == ["tls/zenohd:7447"]
    assert mounted(base["ros2"], args.zenoh_config).name == "service-tls.json5"


def test_monitor_is_a_tls_client_with_the_monitor_certificate(base):
    """monitor-tls.json5 is the desk's file, paths relative to the working directory: in the container
    they must land on the certificate folder mounted there (LRFSLAM_TLS), and be the monitor's."""
    svc = base[MONITOR]
    argv = svc["command"]
    assert argv[0] == "monitor"
    args = monitor.parser().parse_args(argv[1:])
    assert args.connect == ["tls/zenohd:7447"]
    conf = mounted(svc, args.zenoh_config)
    assert conf.name == "monitor-tls.json5"
    zenoh.Config.from_file(str(conf))
    text = conf.read_text()
    paths = {key: re.search(rf'{key}: "([^"]+)"', text).group(1)
             for key in ("root_ca_certificate", "connect_certificate", "connect_private_key")}
    tls_dir = next(default(v).split(":")[1] for v in svc["volumes"] if v.startswith("${LRFSLAM_TLS"))
    resolved = {key: str(Path(svc["working_dir"]) / path) for key, path in paths.items()}
    assert resolved == {"root_ca_certificate": f"{tls_dir}/ca.pem",
                        "connect_certificate": f"{tls_dir}/monitor.pem",
                        "connect_private_key": f"{tls_dir}/monitor-key.pem"}


def test_router_applies_the_acl_on_the_published_port_only_over_tls_once_the_certificates_exist(base):
    router = base[ROUTER]
    argv = router["command"]
    assert argv[0] == "router"
    assert option(argv, "--listen") == ["tls/0.0.0.0:7447"]
    check_listen(option(argv, "--listen"), False, logging.getLogger("test"))   # needs no --insecure
    assert [p.rsplit(":", 1)[-1] for p in router["ports"]] == ["7447"]
    assert router["depends_on"][CERTS] == {"condition": "service_completed_successfully"}
    conf = mounted(router, option(argv, "--zenoh-config")[0])
    assert conf.name == "router-tls-acl.json5"
    zenoh.Config.from_file(str(conf))
    test = router["healthcheck"]["test"]
    assert test[:3] == ["CMD", "lrfslam", "status"]
    assert option(test, "-e") == ["tls/127.0.0.1:7447"]
    assert mounted(router, option(test, "--zenoh-config")[0]).is_file()


def test_the_router_healthcheck_parses_and_fails_on_a_closed_port(base, tmp_path):
    """The flags exist; a router that does not answer is unhealthy (2), as the engine would see."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    argv = base[ROUTER]["healthcheck"]["test"][3:]
    argv = [a.replace(":7447", f":{port}") for a in argv]
    conf = tmp_path / "client.json5"
    conf.write_text("{}")
    argv[argv.index("--zenoh-config") + 1] = str(conf)
    assert status.main(argv) == 2


def test_the_insecure_override_is_plain_everywhere_and_says_so(base):
    plain = load("compose.insecure.yaml")
    assert set(plain) == set(base) - {CERTS}
    router = plain[ROUTER]["command"]
    assert option(router, "--listen") == ["tcp/0.0.0.0:7447"] and "--zenoh-config" not in router
    check_listen(option(router, "--listen"), "--insecure" in router, logging.getLogger("test"))
    with pytest.raises(ConfigError, match="plain"):
        check_listen(option(router, "--listen"), False, logging.getLogger("test"))
    assert option(plain[ROUTER]["healthcheck"]["test"], "-e") == ["tcp/127.0.0.1:7447"]
    for name in (*services.NAMES, MONITOR, "ros2"):
        argv = plain[name]["command"]
        assert option(argv, "--connect") == ["tcp/zenohd:7447"] and "--zenoh-config" not in argv, name
        # Everything else as in the default file: the TLS options alone go.
        tls = base[name]["command"]
        kept = [a for i, a in enumerate(tls) if a != "--zenoh-config" and (i == 0 or tls[i - 1] != "--zenoh-config")]
        assert sorted(a.replace("tls/", "tcp/") for a in kept) == sorted(argv), name
