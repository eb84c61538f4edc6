"""Delivery under load: `lrfslam up` at a given speedup, each stage's rate, drops and gaps.

    python -m lrfslam.bench.delivery [--duration 60] [--speedup 7.5] [--slow features:40]

Runs ``lrfslam up`` (router, every stage, the recorder) in a temporary folder. Two status
snapshots, ``--window`` seconds apart in the middle of the run, give each stage's rate of
messages handled (its ``in`` and ``out`` counters over its own uptime, a monotonic clock);
the second snapshot's table is printed as ``lrfslam status`` shows it, then up's summary.
``--slow SERVICE:MS`` sets LRFSLAM_BUS_DEBUG_SLOW: that stage sleeps MS after each input
(bus.debug_slow, a measurement knob). docs/delivery.md holds the figures. Timing lives here,
not in the tests.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import zenoh

from lrfslam.bench.live import free_port
from lrfslam.msgs import counters
from lrfslam.tools.status import client_config, query_status, status_table

#: Health statuses a service publishes: not data delivered.
HEALTH_OUT = f"{counters.OUT}health"

ROBOT = "bench"


def snapshot(session: zenoh.Session) -> dict:
    alive, statuses = query_status(session, ROBOT, 2.0)
    return {"alive": alive, "statuses": {s.service: s for s in statuses}}


def rates(first: dict, second: dict) -> dict[str, tuple[float, float]]:
    """Per service (in, out) messages per second between two snapshots, on its uptime clock."""
    out = {}
    for name, b in second["statuses"].items():
        a = first["statuses"].get(name)
        if a is None or a.pid != b.pid or b.uptime_s <= a.uptime_s:
            continue
        dt = b.uptime_s - a.uptime_s

        def total(st, prefix: str) -> int:
            return sum(v for k, v in st.counters.items() if k.startswith(prefix) and not k.startswith(HEALTH_OUT))
        out[name] = ((total(b, counters.IN) - total(a, counters.IN)) / dt,
                     (total(b, counters.OUT) - total(a, counters.OUT)) / dt)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=60.0)
    parser.add_argument("--speedup", type=float, default=7.5)
    parser.add_argument("--window", type=float, default=20.0, help="seconds between the two status snapshots")
    parser.add_argument("--slow", default="", metavar="SERVICE:MS", help="slow one stage (bus.debug_slow)")
    args = parser.parse_args()
    port = free_port()
    env = dict(os.environ)
    if args.slow:
        env["LRFSLAM_BUS_DEBUG_SLOW"] = args.slow
    cmd = [sys.executable, "-m", "lrfslam.cli", "up", "--duration", str(args.duration), "--speedup",
           str(args.speedup), "--port", str(port), "--robot", ROBOT]
    print("$", (f"LRFSLAM_BUS_DEBUG_SLOW={args.slow} " if args.slow else "") + " ".join(["lrfslam", *cmd[3:]]))
    with tempfile.TemporaryDirectory() as tmp:
        up = subprocess.Popen(cmd, cwd=tmp, env=env, stdout=subprocess.PIPE, text=True)
        try:
            time.sleep(max(3.0, (args.duration - args.window) / 2))
            with zenoh.open(client_config([f"tcp/127.0.0.1:{port}"])) as session:
                first = snapshot(session)
                time.sleep(args.window)
                second = snapshot(session)
            stdout, _ = up.communicate(timeout=args.duration + 120)
        finally:
            if up.poll() is None:
                up.kill()
                up.wait()
    print(f"\nstatus after {args.window:.0f} s more:")
    print(status_table(second["alive"], list(second["statuses"].values())))
    print(f"\nrates over those {args.window:.0f} s (messages/s on each stage's uptime clock):")
    for name, (r_in, r_out) in sorted(rates(first, second).items()):
        print(f"  {name:10s} in {r_in:7.1f}  out {r_out:7.1f}")
    print(stdout)
    return up.returncode


if __name__ == "__main__":
    sys.exit(main())
