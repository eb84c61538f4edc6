"""deploy/: the compose file, image recipe and config checked without a container engine.

Catches what a schema cannot: a depends_on naming no service, a command no `lrfslam`
understands, a config key a service would refuse at start-up, a healthcheck whose flags
`lrfslam status` does not have, two services publishing one host port, a monitor port
(no authentication) published beyond the host's loopback by default.
"""

from __future__ import annotations

import re
import shutil
import socket
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
import yaml

from lrfslam import cli, services
from lrfslam.runtime import config as config_mod
from lrfslam.runtime.bus import BusConfig
from lrfslam.runtime.runner import bus_config, flag_sets, group_stages, service_parser
from lrfslam.tools import monitor, ros2, status

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
COMPOSE = DEPLOY / "compose.yaml"
CONFIG = DEPLOY / "config.toml"
ROUTER = "zenohd"
CERTS = "certs"
MONITOR = "monitor"
ROS2 = "ros2"

_VAR = re.compile(r"\$\{(\w+)(?::?-([^}]*))?\}")


def interpolate(value: str, env: dict[str, str] | None = None) -> str:
    """Compose's ${NAME}, ${NAME:-default} with an empty environment (the defaults users get)."""
    return _VAR.sub(lambda m: (env or {}).get(m.group(1)) or (m.group(2) or ""), value)


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


@pytest.fixture(scope="module")
def svcs(compose) -> dict:
    return compose["services"]


def workdir() -> str:
    lines = [ln.split(None, 1)[1].strip() for ln in (DEPLOY / "Dockerfile").read_text().splitlines()
             if ln.startswith("WORKDIR ")]
    assert lines, "the Dockerfile sets no WORKDIR"
    return lines[-1]


def mounts(svc: dict) -> dict[str, Path]:
    """Container path -> host path of a service's bind mounts (relative to the compose file)."""
    out = {}
    for vol in svc.get("volumes", []):
        host, container, *_ = interpolate(vol).split(":")
        out[container] = (COMPOSE.parent / host).resolve()
    return out


def test_services_are_the_certs_the_router_the_six_stages_the_monitor_and_the_ros2_bridge(svcs):
    assert set(svcs) == {CERTS, ROUTER, MONITOR, ROS2, *services.NAMES}


def test_the_ros2_bridge_runs_only_when_asked_waits_for_the_router_alone_and_parses(svcs):
    """Under a profile, so `docker compose up` leaves it out; its robot is the pipeline's."""
    bridge = svcs[ROS2]
    assert bridge["profiles"] == ["ros2"]
    assert not [name for name, svc in svcs.items() if name != ROS2 and "profiles" in svc]
    assert bridge["depends_on"] == {ROUTER: {"condition": "service_healthy"}}
    assert not [name for name, svc in svcs.items() if ROS2 in svc.get("depends_on", {})]
    args = ros2.parser().parse_args(bridge["command"][1:])
    assert args.robot == config_mod.read_file(CONFIG)["bus"]["robot"]
    assert args.connect == ["tls/zenohd:7447"] and args.domain_id == 0 and not args.subscribe


def test_depends_on_targets_exist_and_form_no_cycle(svcs):
    graph = {}
    for name, svc in svcs.items():
        deps = svc.get("depends_on", {})
        deps = {d: {} for d in deps} if isinstance(deps, list) else deps
        for target, how in deps.items():
            assert target in svcs, f"{name} depends on unknown service {target!r}"
            assert target != name
            assert how.get("condition", "service_started") in (
                "service_started", "service_healthy", "service_completed_successfully")
        graph[name] = set(deps)
    order = []
    while graph:
        ready = sorted(n for n, deps in graph.items() if deps <= set(order))
        assert ready, f"depends_on cycle among {sorted(graph)}"
        order += ready
        for n in ready:
            del graph[n]
    assert order[:2] == [CERTS, ROUTER]


def test_every_stage_waits_for_a_healthy_router_and_the_sensor_starts_last(svcs):
    for name in services.NAMES:
        assert svcs[name]["depends_on"][ROUTER]["condition"] == "service_healthy", name
    sensor_deps = set(svcs["sensor"]["depends_on"])
    assert sensor_deps == {ROUTER, *services.NAMES} - {"sensor"}


def test_the_monitor_waits_for_the_router_alone_and_nothing_waits_for_it(svcs):
    """A viewer must neither hold the pipeline back nor be stopped after it."""
    assert svcs[MONITOR]["depends_on"] == {ROUTER: {"condition": "service_healthy"}}
    assert not [name for name, svc in svcs.items() if MONITOR in svc.get("depends_on", {})]


def test_commands_are_lrfslam_commands(svcs):
    known = set(services.NAMES) | set(cli.COMMANDS)
    for name, svc in svcs.items():
        command = svc["command"]
        assert isinstance(command, list), f"{name}: use the exec (list) form, no shell in between"
        assert command[0] in known, f"{name}: {command[0]!r} is no lrfslam command"
    assert svcs[ROUTER]["command"][0] == "router"
    for name in services.NAMES:
        assert svcs[name]["command"][0] == name


def test_service_commands_parse_and_their_config_loads(svcs):
    """Each command line plus the mounted config.toml gives the config the service would run."""
    for name in services.NAMES:
        spec = services.spec(name)
        args = service_parser(spec).parse_args(svcs[name]["command"][1:])
        host_config = mounts(svcs[name]).get(args.config)
        assert host_config is not None, f"{name}: --config {args.config} is not mounted"
        assert host_config.is_file(), host_config
        file = config_mod.read_file(host_config)
        bus = bus_config(args, file, {})
        assert bus.mode == "client"
        assert bus.connect == ("tls/zenohd:7447",)
        cfg = config_mod.service_config(spec, sets=flag_sets(spec, args), file=file, env={})
        assert isinstance(cfg, spec.config_type)


def test_monitor_command_parses_and_serves_the_published_ports(svcs):
    """Its robot is the pipeline's (config.toml's [bus], which it does not read), it reaches the router
    by name, listens on the container's interfaces (without a token: the host's port bindings keep it
    on loopback, below), and serves Foxglove and the dashboard on the container ports the host ports
    are mapped to."""
    args = monitor.parser().parse_args(svcs[MONITOR]["command"][1:])
    assert svcs[MONITOR]["command"][0] == "monitor"
    assert args.robot == config_mod.read_file(CONFIG)["bus"]["robot"]
    assert args.connect == ["tls/zenohd:7447"]
    assert args.host == "0.0.0.0" and args.dashboard and args.insecure and args.token_file is None
    container_ports = {interpolate(p).rsplit(":", 1)[-1] for p in svcs[MONITOR]["ports"]}
    assert container_ports == {str(args.port), str(args.http_port)}


def test_router_listens_on_its_published_port(svcs):
    router = svcs[ROUTER]
    command = router["command"]
    listen = [command[i + 1] for i, a in enumerate(command) if a in ("--listen", "-l")]
    assert listen == ["tls/0.0.0.0:7447"], "the router must listen on all interfaces of its container, over TLS"
    published = [interpolate(p).rsplit(":", 1)[-1] for p in router["ports"]]
    assert "7447" in published


def bindings(svc: dict, env: dict[str, str] | None = None) -> list[tuple[str, str]]:
    """(host address, host port) of each published port; "" for every interface."""
    out = []
    for port in svc.get("ports", []):
        parts = interpolate(str(port), env).split(":")
        out.append((parts[0] if len(parts) == 3 else "", parts[-2]))
    return out


def test_host_ports_are_unique_and_only_the_router_and_the_monitor_publish(svcs):
    seen = {}
    for name, svc in svcs.items():
        for _, host in bindings(svc):
            assert host not in seen, f"host port {host} published by {seen.get(host)} and {name}"
            seen[host] = name
    assert set(seen.values()) == {ROUTER, MONITOR}


def test_monitor_ports_are_on_loopback_unless_asked(svcs):
    """The Foxglove WebSocket and the dashboard have no authentication: by default only the robot's
    own host reaches them; the variables move them (and the test deployment off 8765/8080)."""
    assert bindings(svcs[MONITOR]) == [("127.0.0.1", "8765"), ("127.0.0.1", "8080")]
    env = {"LRFSLAM_MONITOR_ADDRESS": "0.0.0.0", "LRFSLAM_FOXGLOVE_PORT": "18765",
           "LRFSLAM_DASHBOARD_PORT": "18080"}
    assert bindings(svcs[MONITOR], env) == [("0.0.0.0", "18765"), ("0.0.0.0", "18080")]
    # The router is Zenoh's port, for remote monitors and services: every interface.
    assert bindings(svcs[ROUTER]) == [("", "7447")]


def test_one_image_with_init_and_restart_on_failure(svcs):
    images = {interpolate(svc["image"]) for svc in svcs.values()}
    assert len(images) == 1, images
    for name, svc in svcs.items():
        assert svc.get("init") is True, f"{name}: Python as PID 1 would ignore SIGTERM's default action"
        # The certs service runs once per start and ends; the others restart after a crash.
        assert svc.get("restart") == ("no" if name == CERTS else "on-failure"), name
        assert svc["build"]["dockerfile"] == "deploy/Dockerfile"
        assert (COMPOSE.parent / svc["build"]["context"] / svc["build"]["dockerfile"]).is_file()


def test_healthchecks_read_their_own_service_and_the_router_its_port(svcs, tmp_path):
    """A service's healthcheck reads the health file its own command writes (no router asked,
    no name lookup); the router's dials its loopback port. The flags parse and fail as a
    failing healthcheck would."""
    closed = socket.socket()
    closed.bind(("127.0.0.1", 0))
    port = closed.getsockname()[1]
    closed.close()
    for name, svc in svcs.items():
        if name == CERTS:   # it ends before anything waits for it: no health to check
            assert "healthcheck" not in svc
            continue
        test = svc["healthcheck"]["test"]
        assert test[:3] == ["CMD", "lrfslam", "status"], name
        argv = test[3:]
        if name == ROUTER:
            assert argv == ["--check", "--zenoh-config", "/etc/lrfslam/zenoh/service-tls.json5",
                            "-e", "tls/127.0.0.1:7447"]
            # Against a closed port: argparse accepts the flags and the router is unreachable (2).
            assert status.main(["--check", "-e", f"tls/127.0.0.1:{port}"]) == 2
            continue
        assert argv[0] == "--check-file", name
        command = svc["command"]
        assert command[0] == name
        assert command[command.index("--health-file") + 1] == argv[1], f"{name} checks a file it does not write"
        # No service has written the file yet: unhealthy (1), with the reason.
        assert status.main(["--check-file", str(tmp_path / "health.json")]) == 1


def test_recorder_writes_into_the_bind_mounted_recordings(svcs):
    recorder = svcs["recorder"]
    file = config_mod.read_file(CONFIG)
    directory = Path(workdir()) / file["recorder"]["directory"]
    targets = mounts(recorder)
    assert str(directory) in targets, f"{directory} is not a bind mount: {sorted(targets)}"
    assert targets[str(directory)] == (ROOT / "recordings").resolve()
    # Long enough for the recorder to write the MCAP summary after SIGTERM (compose's default is 10 s).
    grace = recorder["stop_grace_period"]
    assert grace.endswith("s") and int(grace[:-1]) >= 20


def test_sensor_shows_how_to_map_a_serial_device():
    text = COMPOSE.read_text()
    assert '# devices: ["/dev/ttyUSB0:/dev/ttyUSB0"]' in text
    assert '"--device", "/dev/ttyUSB0"' in text


def test_config_toml_loads_for_every_service():
    """Through the runner's own layering (mode presets included), as `lrfslam <service> --config`."""
    file = config_mod.read_file(CONFIG)
    assert set(file) == {"bus", *services.NAMES}
    for name in services.NAMES:
        spec = services.spec(name)
        args = service_parser(spec).parse_args(["--config", str(CONFIG)])
        bus = bus_config(args, file, {})
        assert bus.robot == file["bus"]["robot"]
        cfg = config_mod.service_config(spec, sets=flag_sets(spec, args), file=file, env={})
        for key, value in file[name].items():
            assert getattr(cfg, key) == value, f"{name}.{key}"


def test_commented_knobs_in_config_toml_are_real_settings():
    """`# name = value` lines are documentation users uncomment: each must still load."""
    table = None
    knobs: dict[str, list[str]] = {}
    for line in CONFIG.read_text().splitlines():
        if m := re.match(r"^\[(\w+)\]", line):
            table = m.group(1)
        elif m := re.match(r"^#\s*([a-z_][a-z0-9_.]*)\s*=\s*(.+?)\s*(#.*)?$", line):
            knobs.setdefault(table, []).append(f"{m.group(1)} = {m.group(2)}")
    assert sum(len(v) for v in knobs.values()) >= 10
    for table, lines in knobs.items():
        if table == "bus":
            config_mod.load(BusConfig, table=tomllib.loads("\n".join(lines)))
            continue
        spec = services.spec(table)
        config_mod.service_config(spec, file={table: tomllib.loads("\n".join(lines))})


def test_dockerfile_base_and_entrypoint():
    text = (DEPLOY / "Dockerfile").read_text()
    assert re.search(r"^FROM python:3\.11-slim-bookworm$", text, re.MULTILINE)
    assert re.search(r'^ENTRYPOINT \["lrfslam"\]$', text, re.MULTILINE)


def test_dockerignore_keeps_the_context_small():
    ignored = {ln.strip() for ln in (ROOT / ".dockerignore").read_text().splitlines()}
    assert {".git", ".venv", "recordings"} <= ignored
    assert "README.md" not in ignored and "pyproject.toml" not in ignored  # pip install . needs both


@pytest.mark.parametrize("script", ["setup-podman.sh", "podman-build.sh", "zenoh/make-certs.sh"])
def test_shell_scripts_parse(script):
    subprocess.run(["bash", "-n", str(DEPLOY / script)], check=True)


@pytest.mark.parametrize("name", ["compose.yaml", "compose.group.yaml"])
def test_compose_spec_schema(name):
    exe = shutil.which("check-jsonschema") or shutil.which("check-jsonschema", path=str(Path(sys.executable).parent))
    if exe is None:
        pytest.skip("check-jsonschema not installed (pip install check-jsonschema)")
    run = subprocess.run([exe, "--builtin-schema", "vendor.compose-spec", str(DEPLOY / name)],
                         capture_output=True, text=True, timeout=120, check=False)
    assert run.returncode == 0, run.stdout + run.stderr


def test_lms200_override_is_the_base_sensor_plus_the_device():
    """deploy/compose.lms200.yaml: compose replaces a list command whole, so it must stay the base's."""
    override = yaml.safe_load((DEPLOY / "compose.lms200.yaml").read_text())["services"]
    base = yaml.safe_load(COMPOSE.read_text())["services"]
    command = override["sensor"]["command"]
    assert command[:len(base["sensor"]["command"])] == base["sensor"]["command"]
    spec = services.spec("sensor")
    args = service_parser(spec).parse_args(command[1:])
    cfg = config_mod.service_config(spec, sets=flag_sets(spec, args), file=config_mod.read_file(CONFIG), env={})
    assert cfg.source == "lms200"
    (mapping,) = override["sensor"]["devices"]
    assert interpolate(mapping) == f"/dev/ttyUSB0:{cfg.device}"
    slam = config_mod.service_config(services.spec("slam"), sets=[], file=config_mod.read_file(CONFIG),
                                     env=override["slam"]["environment"])
    assert slam.wait_for_odometry is False
    exe = shutil.which("check-jsonschema") or shutil.which("check-jsonschema", path=str(Path(sys.executable).parent))
    if exe is not None:
        run = subprocess.run([exe, "--builtin-schema", "vendor.compose-spec", str(DEPLOY / "compose.lms200.yaml")],
                             capture_output=True, text=True, timeout=120, check=False)
        assert run.returncode == 0, run.stdout + run.stderr


def test_group_override_runs_the_three_stages_as_the_base_runs_slam(svcs):
    """deploy/compose.group.yaml: `stages` is the base's slam container running `lrfslam group`
    with the slam's own arguments; the three stage containers are left out, and the sensor waits
    for `stages` and no longer for them."""
    override = yaml.safe_load((DEPLOY / "compose.group.yaml").read_text())["services"]
    stages = override["stages"]
    assert stages["extends"] == {"file": "compose.yaml", "service": "slam"}
    group, names, *rest = stages["command"]
    assert (group, names) == ("group", "denoise,features,slam") and rest == svcs["slam"]["command"][1:]
    assert group_stages(names) == ["denoise", "features", "slam"]   # (the rest parse as the slam's do)
    for name in names.split(","):
        assert override[name] == {"profiles": ["process-per-stage"]}
        assert svcs["sensor"]["depends_on"][name]["required"] is False
    assert set(override["sensor"]["depends_on"]) == {"stages"}
    assert set(stages["depends_on"]) == set(svcs["slam"]["depends_on"])
