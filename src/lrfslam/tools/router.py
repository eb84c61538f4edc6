"""``lrfslam router``: a Zenoh router in a Python process.

Stands in for ``zenohd`` where the official image or binary is not available
(CI, ``lrfslam up``); deployments may use either, the services cannot tell.
"""

from __future__ import annotations

import argparse
import json
import logging
import threading

import zenoh

from lrfslam.errors import ConfigError
from lrfslam.runtime.bus import base_config, closing, listen_error
from lrfslam.runtime.runner import install_signal_handlers, setup_logging
from lrfslam.tools.exposure import check_listen

log = logging.getLogger("lrfslam.router")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lrfslam router", description=__doc__.splitlines()[0])
    parser.add_argument("-l", "--listen", action="append", metavar="ENDPOINT",
                        help="endpoint to listen on (default tcp/127.0.0.1:7447); for other hosts tls/0.0.0.0:7447 with a "
                             "--zenoh-config naming the router's certificate (a plain one only with --insecure)")
    parser.add_argument("-e", "--connect", action="append", default=[], metavar="ENDPOINT",
                        help="other routers to connect to")
    parser.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 config (TLS, ACL, ...) applied first")
    parser.add_argument("--id", metavar="HEX", help="this router's Zenoh id (lrfslam up names its router so it "
                        "can tell it is talking to it and not to another router on that port)")
    parser.add_argument("--insecure", action="store_true",
                        help="allow a plain tcp/, udp/ or ws/ --listen endpoint beyond loopback: whoever reaches it "
                             "reads and publishes on the bus (a closed network where that is wanted)")
    parser.add_argument("--log-level", default=None)
    args = parser.parse_args(argv)
    setup_logging("router", args.log_level)
    try:
        check_listen(args.listen or [], args.insecure, log)
    except ConfigError as exc:
        log.error("%s", exc)
        return 2
    conf = base_config("router", args.connect, args.zenoh_config)
    conf.insert_json5("listen/endpoints", json.dumps(args.listen or ["tcp/127.0.0.1:7447"]))
    if args.id:
        conf.insert_json5("id", json.dumps(args.id))
    stop = threading.Event()
    install_signal_handlers(stop)
    zenoh.init_log_from_env_or("error")
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        log.error("%s", listen_error(exc) or f"cannot start the router: {str(exc).split(' at /')[0]}")
        return 2
    with closing(session):
        log.info("router listening on %s", ", ".join(args.listen or ["tcp/127.0.0.1:7447"]))
        stop.wait()
    log.info("router stopped")
    return 0

