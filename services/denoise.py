"""denoise: the paper's angle-histogram noise reduction.

in:  scan           LaserScan
out: scan/filtered  FilteredScan (the scan after the 4 m cut, the kept beams and their points)
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from lrfslam.algo.histogram import DenoiseParams, denoise
from lrfslam.errors import ConfigError, InputError
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.step import Message, Output, ServiceSpec, StepBase

MODES = ("paper", "default")


@dataclass(frozen=True)
class DenoiseConfig:
    mode: str = "default"   # "paper" (literal reading) or "default" (measured improvements); presets histogram.*
    histogram: DenoiseParams = field(default_factory=DenoiseParams.default)

    #: What an operator sets (docs/settings.md); ``mode`` presets the rest of ``histogram``.
    SETTINGS: ClassVar[tuple[str, ...]] = (
        "mode", "histogram.max_range_m", "histogram.keep_frac", "histogram.bin_deg", "histogram.period_deg",
    )

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ConfigError(f"denoise.mode must be one of {MODES}, got {self.mode!r}")


def preset(mode: str) -> DenoiseConfig:
    if mode not in MODES:
        raise ConfigError(f"mode must be one of {MODES}, got {mode!r}")
    return DenoiseConfig(mode=mode, histogram=getattr(DenoiseParams, mode)())


class DenoiseStep(StepBase):
    def __init__(self, cfg: DenoiseConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.seq = 0

    def on_message(self, msg: Message):
        scan: t.LaserScan = msg.value
        if scan.ranges_m.size < 2:
            raise InputError(f"scan {scan.seq} has {scan.ranges_m.size} beams")
        params = self.cfg.histogram
        result = denoise(scan.ranges_m, scan.angles_rad, params)
        # The cut is part of the output: downstream stages see beyond-4 m beams as no return.
        ranges = np.where(result.valid, scan.ranges_m, np.where(np.isnan(scan.ranges_m), np.nan, np.inf))
        status = np.where(result.valid, t.BEAM_VALID,
                          np.where(scan.status == t.BEAM_VALID, t.BEAM_NO_RETURN, scan.status))
        cut = dataclasses.replace(scan, ranges_m=ranges, status=status)
        kept = np.flatnonzero(result.kept)
        self.counts["scans"] += 1
        self.counts["points_kept"] += kept.size
        self.counts["points_removed"] += int(result.valid.sum()) - kept.size
        self.seq += 1
        yield Output(topics.SCAN_FILTERED, t.FilteredScan(stamp_ns=scan.stamp_ns, seq=self.seq, scan=cut,
                                                          kept_beams=kept, points_xy_m=result.points_xy[kept],
                                                          max_range_m=params.max_range_m, mode=self.cfg.mode))


SPEC = ServiceSpec(
    name="denoise",
    summary="Angle-histogram noise reduction of laser scans (4 m cut, direction histogram, >15 % bins).",
    config_type=DenoiseConfig,
    inputs=(topics.SCAN,),
    outputs=(topics.SCAN_FILTERED,),
    skippable=(topics.SCAN,),
    build=lambda cfg, ctx: DenoiseStep(cfg),
    preset=preset,
)
