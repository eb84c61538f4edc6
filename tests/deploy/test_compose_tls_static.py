"""deploy/compose.tls.yaml, the TLS + access-control override, checked without a container engine.

What merging it over compose.yaml must give: every stage a client of the router's TLS port with
the service certificate, the monitor one with the monitor certificate (what the access-control
list lets read but not publish), the router listening with the access-control config on the port
the base file publishes, every file a command names mounted from the repository, and no plain
tcp/ listener left. The override running for real: deploy/README.md ("Access control").
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml
import zenoh

from lrfslam import services
from lrfslam.runtime.runner import bus_config, service_parser
from lrfslam.tools import monitor, status
from lrfslam.tools.certs import ROLES, Role

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
ROUTER = "zenohd"
MONITOR = "monitor"
_VAR = re.compile(r"\$\{(\w+)(?::?-([^}]*))?\}")


def targets(svc: dict) -> set[str]:
    """Container paths of a service's mounts, with compose's ${NAME:-default} at its default."""
    return {_VAR.sub(lambda m: m.group(2) or "", v).split(":")[1] for v in svc.get("volumes", [])}


class _Loader(yaml.SafeLoader):
    """Compose's ``!override`` tag: the value replaces the base file's instead of merging."""


_Loader.add_constructor("!override", lambda loader, node: loader.construct_sequence(node)
                        if isinstance(node, yaml.SequenceNode) else loader.construct_mapping(node))


def load(name: str) -> dict:
    return yaml.load((DEPLOY / name).read_text(), Loader=_Loader)["services"]


@pytest.fixture(scope="module")
def tls() -> dict:
    return load("compose.tls.yaml")


def mounted(svc: dict, container_path: str) -> Path:
    """The repository file a container path of ``svc`` comes from (only ./ mounts of deploy/)."""
    for vol in svc["volumes"]:
        host, target, *_ = vol.split(":")
        if container_path.startswith(target + "/") and host.startswith("./"):
            return DEPLOY / host / container_path.removeprefix(target + "/")
    raise AssertionError(f"{container_path} is not mounted from the repository: {svc['volumes']}")


def option(argv: list[str], flag: str) -> list[str]:
    return [argv[i + 1] for i, a in enumerate(argv) if a == flag]


def test_overrides_only_existing_services_and_every_one(tls):
    # The ROS 2 bridge (profile ros2) is not part of the TLS deployment: its ROS keys are outside
    # the access-control list (docs/ros2.md, "Access control").
    assert set(tls) == set(load("compose.yaml")) - {"ros2"} == {ROUTER, MONITOR, *services.NAMES}


def test_stages_are_tls_clients_with_the_service_certificate(tls):
    base = load("compose.yaml")
    for name in services.NAMES:
        argv = tls[name]["command"]
        assert argv[0] == name
        args = service_parser(services.spec(name)).parse_args(argv[1:])
        assert bus_config(args, {}, {}).connect == ("tls/zenohd:7447",)
        conf = mounted(tls[name], args.zenoh_config)
        assert conf.name == "service-tls.json5" and conf.is_file()
        zenoh.Config.from_file(str(conf))
        # Everything else of the base command is kept (config file, health file the check reads).
        plain = [a for a in argv if a not in ("--zenoh-config", args.zenoh_config)]
        assert plain == [a if a != "tcp/zenohd:7447" else "tls/zenohd:7447" for a in base[name]["command"]], name
        # The base file's mounts are all still there (a volumes list is merged by target path).
        assert targets(base[name]) <= targets(tls[name]), name
        assert "/etc/lrfslam/tls" in targets(tls[name])


def test_monitor_is_a_tls_client_with_the_monitor_certificate(tls):
    """monitor-tls.json5 is the desk's file, paths relative to the working directory: in the container
    they must land on the certificate folder the override mounts (LRFSLAM_TLS), and be the monitor's."""
    base = load("compose.yaml")[MONITOR]
    svc = tls[MONITOR]
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
    tls_dir = next(_VAR.sub(lambda m: m.group(2) or "", v).split(":")[1]
                   for v in svc["volumes"] if v.startswith("${LRFSLAM_TLS"))
    resolved = {key: str(Path(svc["working_dir"]) / path) for key, path in paths.items()}
    assert resolved == {"root_ca_certificate": f"{tls_dir}/ca.pem",
                        "connect_certificate": f"{tls_dir}/monitor.pem",
                        "connect_private_key": f"{tls_dir}/monitor-key.pem"}
    # The certificate is the one lrfslam certs (make-certs.sh) issues with the monitor's common name,
    # which the router's list grants reading only.
    assert Role("monitor", "lrfslam-monitor") in ROLES
    acl = (DEPLOY / "zenoh" / "router-tls-acl.json5").read_text()
    assert '{ id: "monitor", cert_common_names: ["lrfslam-monitor"] }' in acl
    # Everything else as in the base file: robot, servers, ports, health file.
    plain = [a for a in argv if a not in ("--zenoh-config", args.zenoh_config)]
    assert plain == [a if a != "tcp/zenohd:7447" else "tls/zenohd:7447" for a in base["command"]]
    assert targets(base) <= targets(svc)


def test_router_applies_the_acl_on_the_published_port_only_over_tls(tls):
    base = load("compose.yaml")[ROUTER]
    argv = tls[ROUTER]["command"]
    assert argv[0] == "router"
    assert option(argv, "--listen") == ["tls/0.0.0.0:7447"]
    assert [p.rsplit(":", 1)[-1] for p in base["ports"]] == ["7447"]
    conf = mounted(tls[ROUTER], option(argv, "--zenoh-config")[0])
    assert conf.name == "router-tls-acl.json5"
    zenoh.Config.from_file(str(conf))
    test = tls[ROUTER]["healthcheck"]["test"]
    assert test[:3] == ["CMD", "lrfslam", "status"]
    assert option(test, "-e") == ["tls/127.0.0.1:7447"]
    assert mounted(tls[ROUTER], option(test, "--zenoh-config")[0]).is_file()


def test_the_router_healthcheck_parses_and_fails_on_a_closed_port(tls, tmp_path):
    """The flags exist; a router that does not answer is unhealthy (2), as the engine would see."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    argv = tls[ROUTER]["healthcheck"]["test"][3:]
    argv = [a.replace(":7447", f":{port}") for a in argv]
    conf = tmp_path / "client.json5"
    conf.write_text("{}")
    argv[argv.index("--zenoh-config") + 1] = str(conf)
    assert status.main(argv) == 2
