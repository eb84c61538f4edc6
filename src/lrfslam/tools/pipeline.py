"""``lrfslam pipeline --replay IN --out OUT.mcap``: several services' steps in one process, offline.

IN is an MCAP file, a recording folder (its segments in order) or several files, read as one stream.

Equivalent to replaying the services one after the other, each on a recording
holding its inputs, without the intermediate files and merges: the stages are
one :class:`~lrfslam.runtime.chain.Chain` of the services' own steps, and each
output is fed forward to the later stages as soon as it is produced. The input
is read once in log-time order; nothing reads the clock, so the same input
gives the same output bytes.

OUT.mcap holds the input's messages (raw, as recorded) and every stage's
outputs, except that input messages on a topic one of the stages produces are
dropped (that stage's outputs replace them, and they are not fed to later stages).
So ``lrfslam pipeline --replay intel.mcap --out run.mcap`` gives one file with
``scan``, ``odom``, ``scan/filtered``, ``features`` and ``slam/state``.

Configuration layers as for the services (defaults or preset < ``--config``
``[<service>]`` table < ``LRFSLAM_<SERVICE>_*`` < ``--set``), with ``--set``
naming the stage: ``--set features.mode=paper --set slam.ekf.gate_chi2=9``.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections import Counter
from collections.abc import Iterable, Mapping
from pathlib import Path

from lrfslam import services
from lrfslam.errors import ConfigError, LrfSlamError
from lrfslam.runtime import chain
from lrfslam.runtime import config as config_mod
from lrfslam.runtime.bus import BusConfig
from lrfslam.runtime.recording import RecordingSource, describe_source
from lrfslam.runtime.runner import setup_logging

log = logging.getLogger("lrfslam.pipeline")

DEFAULT_STAGES = ("denoise", "features", "slam", "mapper")


def stage_names(text: str) -> tuple[str, ...]:
    """Comma-separated service names, checked and put in pipeline order.

    Raises
    ------
    ConfigError
        A name is unknown, repeated, or a service without a replayable step
        (the sensor is a source; the recorder's job is done by OUT.mcap itself).
    """
    names = [n.strip() for n in text.split(",") if n.strip()]
    usable = [n for n in services.NAMES if n not in ("sensor", "recorder")]
    for name in names:
        if name not in usable:
            raise ConfigError(f"pipeline stage {name!r} must be one of {', '.join(usable)}")
    if not names or len(set(names)) != len(names):
        raise ConfigError(f"pipeline stages {text!r}: give each stage once")
    return tuple(n for n in services.NAMES if n in names)


def run_pipeline(stages: Iterable[chain.Stage], robot: str, in_path: RecordingSource, out_path: str | Path | None,
                 progress: bool = False) -> dict[str, Counter]:
    """Run ``stages`` (in pipeline order) over the recording ``in_path`` (file, folder or files); write ``out_path``.

    Returns
    -------
    dict of str to Counter
        Per stage name: ``in.<topic>``, ``out.<topic>``, ``error.input`` and the
        step's own ``step.*`` counters; under ``"input"``: messages read, copied,
        dropped (replaced by a stage's outputs) and undecodable.
    """
    stages = tuple(stages)
    metadata = {"lrfslam": {"robot": robot, "service": "pipeline", "replay_of": describe_source(in_path),
                            "stages": ",".join(s.spec.name for s in stages),
                            **{f"config.{s.spec.name}": config_mod.to_json(s.config) for s in stages}}}
    return chain.replay_recording(stages, robot, in_path, out_path, copy_inputs=True, metadata=metadata,
                            progress=progress)


def build_stages(names: Iterable[str], sets: Iterable[str], file: Mapping, env: Mapping[str, str]) -> list[chain.Stage]:
    """The stages ``names``, configured by :func:`~lrfslam.runtime.chain.stage` with their ``sets``."""
    names = tuple(names)
    per_stage = config_mod.by_service(sets, names)
    return [services.stage(name, sets=per_stage[name], config_file=file, env=env) for name in names]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lrfslam pipeline", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--replay", required=True, nargs="+", metavar="IN",
                        help="recording to run on: an MCAP file, a recording folder, or several files (one stream)")
    parser.add_argument("--out", metavar="OUT.mcap", help="write the input and every stage's outputs here")
    parser.add_argument("--stages", default=",".join(DEFAULT_STAGES),
                        help=f"comma-separated services, run in pipeline order (default {','.join(DEFAULT_STAGES)})")
    parser.add_argument("--config", metavar="FILE", help="TOML config file ([bus] robot and [<service>] tables)")
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="STAGE.NAME=VALUE",
                        help="override one setting of a stage, e.g. features.mode=paper (repeatable)")
    parser.add_argument("--robot", help="robot namespace given to the steps and stored in the metadata")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--log-level", default=None, help="DEBUG, INFO, WARNING, ERROR")
    args = parser.parse_args(argv)
    setup_logging("pipeline", args.log_level)
    try:
        file = config_mod.read_file(args.config, services.CONFIG_TABLES)
        robot = config_mod.load(BusConfig, table=file.get("bus", {}), env=os.environ,
                                env_prefix=f"{config_mod.ENV_PREFIX}_BUS",
                                sets=[f"robot={args.robot}"] if args.robot else []).robot
        stages = build_stages(stage_names(args.stages), args.sets, file, os.environ)
        for stage in stages:
            log.info("%s config %s", stage.spec.name, config_mod.to_json(stage.config))
        counts = run_pipeline(stages, robot, [Path(p) for p in args.replay], Path(args.out) if args.out else None,
                              progress=not args.quiet and sys.stderr.isatty())
    except (LrfSlamError, OSError) as exc:
        log.error("%s", exc)
        return 2
    for name, c in counts.items():
        log.info("%s: %s", name, ", ".join(f"{k}={v}" for k, v in sorted(c.items())) or "nothing")
    return 0
