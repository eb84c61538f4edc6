"""``lrfslam``: the one command line of the project.

    lrfslam up [--duration S]          the whole pipeline on the simulated hallway, with a summary
    lrfslam <service> [...]            one service live, or on a recording with --replay IN --out OUT
    lrfslam status                     live services and their statistics
    lrfslam router                     a Zenoh router
    lrfslam certs OUT_DIR --host ROBOT_HOST   a private CA and the router's, services' and monitors' certificates
    lrfslam info RECORDING             topics, schemas, counts and duration of a recording (file or folder)
    lrfslam recover IN.mcap -o OUT.mcap   an indexed copy of a file whose writer was killed
    lrfslam pipeline --replay IN.mcap --out OUT.mcap [--stages denoise,features,slam]
    lrfslam eval features|slam|relations ...
    lrfslam import carmen LOG -o FILE.mcap
    lrfslam export RECORDING [-o DIR | --foxglove OUT.mcap]   map.json/map.png, or a copy for Foxglove
    lrfslam map save RECORDING -o MAP/ | map info MAP/         a map a user keeps (docs/maps.md)
    lrfslam monitor --connect tcp/HOST:7447 [--port 8765]     live Foxglove WebSocket server
    lrfslam play RECORDING [--rate X | --rate max] [--topics T ...] [--loop]   a recording onto the live bus
    lrfslam ros2 --connect tcp/HOST:7447 [--domain-id 0] [--subscribe]   ROS 2 over rmw_zenoh, both ways
    lrfslam bench [--only SECTIONS] [--quick] [--json] | --check ekf   one table of costs, latency, rates, logs
    lrfslam emulate-lms200             an LMS200 on a pseudo-terminal

Exit codes: 0 done; 1 the command ran and reports a problem (``status``: a service
unhealthy); 2 error (usage, configuration, a missing or unreadable input, a stage
of ``up`` that failed to start), printed as one line ``lrfslam <command>: error: ...``
and with no output written; 128 + N stopped by signal N (130 Ctrl-C, 143 SIGTERM),
with the offline commands' outputs removed (:mod:`lrfslam.runtime.outputs`).
"""

from __future__ import annotations

import importlib
import signal
import sys

from lrfslam import services
from lrfslam.errors import LrfSlamError
from lrfslam.runtime.outputs import Interrupted, raise_on_signals

# command -> (module, function, one-line help)
COMMANDS: dict[str, tuple[str, str, str]] = {
    "up": ("lrfslam.tools.up", "main", "run the whole pipeline (router + six services) and summarise"),
    "status": ("lrfslam.tools.status", "main", "list live services and their statistics"),
    "router": ("lrfslam.tools.router", "main", "run a Zenoh router"),
    "certs": ("lrfslam.tools.certs", "main",
              "a private CA and the TLS certificates of the router, the services and monitors (deploy/zenoh)"),
    "info": ("lrfslam.tools.info", "main", "describe an MCAP recording (a file or a recording folder)"),
    "recover": ("lrfslam.tools.recover", "main", "rewrite a file whose writer was killed as an indexed MCAP"),
    "pipeline": ("lrfslam.tools.pipeline", "main", "run several stages over a recording in one process (offline)"),
    "eval": ("lrfslam.tools.evaluate", "main", "accuracy evaluations (features, slam, relations)"),
    "import": ("lrfslam.tools.importers", "main", "convert a log (CARMEN) into a recording"),
    "emulate-lms200": ("lrfslam.drivers.lms200.emulator", "main", "emulate an LMS200 on a pseudo-terminal"),
    "export": ("lrfslam.tools.export", "main",
               "the map of a recording: occupancy grid (map_server PGM + YAML), JSON, PNG; or a Foxglove copy"),
    "map": ("lrfslam.tools.maps", "main",
            "a map a user keeps: map save RECORDING -o MAP/ (one folder, docs/maps.md), map info MAP/"),
    "monitor": ("lrfslam.tools.monitor", "main", "serve a robot's live streams to Foxglove (WebSocket)"),
    "play": ("lrfslam.tools.play", "main",
             "play a recording onto the live bus (--rate X, or --rate max: as fast as the stages answer)"),
    "ros2": ("lrfslam.tools.ros2", "main",
             "the robot's topics to ROS 2 over rmw_zenoh (--subscribe: a ROS 2 robot's scans into the pipeline)"),
    "group": ("lrfslam.tools.group", "main",
              "several stages in one process (e.g. denoise,features,slam,mapper), each still its own service on the bus"),
    "bench": ("lrfslam.bench.command", "main",
              "one table: stage costs, EKF against a dense update, codecs, live latency, max rate, logs, memory"),
}

#: Commands that run to an end and write files (and any service with ``--replay``): SIGTERM
#: stops them like Ctrl-C, removing what they had not finished (the live services and
#: ``up`` handle the signals themselves and stop cleanly).
OFFLINE = frozenset({"info", "pipeline", "eval", "import", "export", "map"})


def usage() -> str:
    lines = ["usage: lrfslam <command> [options]   (lrfslam <command> --help for its options)", "",
             "services (each a separate process; --replay IN.mcap --out OUT.mcap runs it on a recording):"]
    for name in services.NAMES:
        lines.append(f"  {name:15s} {services.spec(name).summary}")
    lines += ["", "commands:"]
    lines += [f"  {name:15s} {text}" for name, (_, _, text) in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(usage())
        return 0 if argv else 2
    command, rest = argv[0], argv[1:]
    if command not in COMMANDS and command not in services.NAMES:
        print(f"lrfslam: unknown command {command!r}\n\n{usage()}", file=sys.stderr)
        return 2
    if command in OFFLINE or (command in services.NAMES and any(a.split("=")[0] == "--replay" for a in rest)):
        raise_on_signals()
    try:
        if command in services.NAMES:
            from lrfslam.runtime.runner import main as run_service
            return run_service(services.spec(command), rest, services.CONFIG_TABLES)
        module, func, _ = COMMANDS[command]
        return int(getattr(importlib.import_module(module), func)(rest) or 0)
    except Interrupted as exc:
        print(f"lrfslam {command}: stopped by {signal.Signals(exc.signum).name}", file=sys.stderr)
        return 128 + exc.signum
    except SystemError as exc:
        # A signal handled while compiled code (the scan matcher's numba kernels) was being
        # entered surfaces as a SystemError caused by the handler's Interrupted.
        cause = exc.__cause__
        while cause is not None and not isinstance(cause, Interrupted):
            cause = cause.__cause__
        if cause is None:
            raise
        print(f"lrfslam {command}: stopped by {signal.Signals(cause.signum).name}", file=sys.stderr)
        return 128 + cause.signum
    except KeyboardInterrupt:
        print(f"lrfslam {command}: interrupted", file=sys.stderr)
        return 128 + signal.SIGINT
    except (LrfSlamError, OSError) as exc:
        print(f"lrfslam {command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
