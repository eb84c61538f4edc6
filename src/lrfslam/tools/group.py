"""``lrfslam group STAGE,STAGE,...``: several stages in one process, each still its own service on the bus.

As ROS 2's component containers: one Zenoh session and one in-process chain through the stages'
steps (:func:`lrfslam.runtime.runner.run_services`); ``lrfslam up --group`` starts one
(docs/delivery.md, "Stages sharing a process").
"""

from __future__ import annotations

import argparse
import logging
import os

from lrfslam import services
from lrfslam.errors import ConfigError, LrfSlamError
from lrfslam.runtime import config as config_mod
from lrfslam.runtime.runner import (
    GROUPABLE,
    add_common_arguments,
    bus_config,
    group_stages,
    run_services,
    setup_logging,
)

log = logging.getLogger("lrfslam")


def main(argv: list[str] | None = None) -> int:
    """``lrfslam group STAGE,STAGE,...``: several services in one process (:func:`run_services`)."""
    parser = argparse.ArgumentParser(
        prog="lrfslam group", description="run several stages in one process, as ROS 2's component containers do: "
        "each keeps its liveliness token, status, health and outputs on the bus; between them, messages pass in "
        "memory (docs/delivery.md, Stages sharing a process)")
    parser.add_argument("stages", help=f"comma-separated, any of {', '.join(GROUPABLE)}, e.g. "
                                       "denoise,features,slam,mapper")
    add_common_arguments(parser)   # --set SERVICE.NAME=VALUE here, as in lrfslam up
    parser.add_argument("--health-file", metavar="FILE",
                        help="write the first stage's health to FILE, for a container healthcheck")
    parser.add_argument("--checkpoint-dir", metavar="DIR", help="where the slam and the mapper save their state")
    args = parser.parse_args(argv)
    try:
        names = group_stages(args.stages)
    except ConfigError as exc:
        setup_logging("group", args.log_level)
        log.error("%s", exc)
        return 2
    setup_logging("+".join(names), args.log_level)
    try:
        file = config_mod.read_file(args.config, services.CONFIG_TABLES)
        bus = bus_config(args, file, os.environ)
        sets = config_mod.by_service(args.sets, names)
        hosted = [(services.spec(n), config_mod.service_config(services.spec(n), sets=sets[n], file=file,
                                                               env=os.environ)) for n in names]
        for spec, cfg in hosted:
            log.info("%s config %s", spec.name, config_mod.to_json(cfg))
        return run_services(hosted, bus)
    except (LrfSlamError, OSError) as exc:
        log.error("%s", exc)
        return 2
