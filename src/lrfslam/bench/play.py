"""``lrfslam play --rate max`` through live stages against ``lrfslam pipeline --replay`` of the same input.

    python -m lrfslam.bench.play RECORDING [--stages denoise,features,slam] [--group STAGES] [--window 8] [--no-compare]

In a temporary folder: a router, the recorder and each stage as separate processes (Zenoh clients
over TCP on loopback; ``--group``: those of the stages in one ``lrfslam group`` process), then ``lrfslam play RECORDING --rate max``; its one-line summary is printed
(seconds on play's monotonic clock, scans/s, drops and gaps of the live services). The stages are
stopped (SIGTERM, in pipeline order, then the recorder), and ``lrfslam pipeline --replay`` runs the
same stages over the same input in one process, timed on this script's monotonic clock; then every
output topic of the recording is compared with the pipeline's, message by message (stamp,
sequence, payload bytes). docs/delivery.md holds the figures. Timing lives here, not in the tests.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import zenoh

from lrfslam import services
from lrfslam.bench.live import free_port
from lrfslam.runtime.recording import read_recording
from lrfslam.tools.status import client_config, query_status

ROBOT = "bench"


def cli(*args: str, cwd: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "lrfslam.cli", *args], cwd=cwd)


def wait_alive(endpoint: str, names: list[str], timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            session = zenoh.open(client_config([endpoint]))
            break
        except zenoh.ZError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)
    with session:
        while {s for _, s in query_status(session, ROBOT, 1.0)[0]} < set(names):
            if time.monotonic() > deadline:
                raise SystemExit(f"not alive after {timeout_s:.0f} s: {names}")
            time.sleep(0.3)


def first_difference(a: list, b: list) -> int | None:
    """Index of the first message that differs (or is missing in one), None if none does."""
    for i, (x, y) in enumerate(zip(a, b)):
        if x != y:
            return i
    return None if len(a) == len(b) else min(len(a), len(b))


def compare(live: Path, offline: Path, names: list[str]) -> list[str]:
    """One line per topic: messages in each, and whether every one is identical."""
    lines = []
    for topic in names:
        a = [(m.stamp_ns, m.sequence, m.data) for m in read_recording(live, [topic])]
        b = [(m.stamp_ns, m.sequence, m.data) for m in read_recording(offline, [topic])]
        diff = first_difference(a, b)
        lines.append(f"{topic:15s} live {len(a):6d}  offline {len(b):6d}  "
                     + ("identical" if diff is None else f"DIFFERENT from message {diff}"))
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("recording", type=Path)
    parser.add_argument("--stages", default="denoise,features,slam")
    parser.add_argument("--window", default="8")
    parser.add_argument("--group", metavar="STAGES", default="",
                        help="these of the stages in one process (lrfslam group), e.g. denoise,features,slam")
    parser.add_argument("--no-compare", action="store_true", help="skip the offline run and the comparison")
    args = parser.parse_args()
    stages = args.stages.split(",")
    recording = args.recording.resolve()
    with tempfile.TemporaryDirectory(prefix="bench_play_") as tmp:
        work = Path(tmp)
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        common = ["--robot", ROBOT, "--mode", "client", "--connect", endpoint, "--log-level", "WARNING"]
        procs = {"router": cli("router", "--listen", endpoint, "--log-level", "WARNING", cwd=work)}
        procs["recorder"] = cli("recorder", *common, "--set", "name=live", cwd=work)
        grouped = args.group.split(",") if args.group else []
        if grouped:
            procs["group"] = cli("group", args.group, *common, cwd=work)
        procs.update({stage: cli(stage, *common, cwd=work) for stage in stages if stage not in grouped})
        try:
            wait_alive(endpoint, ["recorder", *stages])
            subprocess.run([sys.executable, "-m", "lrfslam.cli", "play", str(recording), "--rate", "max", "--robot",
                            ROBOT, "--connect", endpoint, "--window", args.window, "--log-level", "WARNING"],
                           cwd=work, check=False)
        finally:
            for proc in [*(p for n, p in procs.items() if n not in ("recorder", "router")), procs["recorder"],
                         procs["router"]]:
                proc.terminate()
                proc.wait(60)
        if args.no_compare:
            return
        started = time.monotonic()
        subprocess.run([sys.executable, "-m", "lrfslam.cli", "pipeline", "--replay", str(recording), "--out",
                        str(work / "offline.mcap"), "-q", "--stages", args.stages, "--log-level", "WARNING"],
                       cwd=work, check=True)
        print(f"lrfslam pipeline --replay, same stages: {time.monotonic() - started:.2f} s")
        names = [tp.name for stage in stages for tp in services.spec(stage).outputs]
        print("\n".join(compare(work / "recordings" / "live", work / "offline.mcap", names)))


if __name__ == "__main__":
    main()
