"""features: the feature stage (lrfslam.algo.features): corners by forward searching, jump edges by backward searching.

in:  scan/filtered  FilteredScan
out: features       Features (robot frame, 2x2 covariance, source beam, scan seq; and the
                   dominant wall direction modulo 90° with its sigma, a heading measurement
                   for the slam service that is not in the paper, docs/slam.md)
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from lrfslam.algo.features import FeatureParams, extract_features
from lrfslam.algo.wall_direction import WallDirectionParams, wall_direction
from lrfslam.errors import ConfigError
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.step import Message, Output, ServiceSpec, StepBase

MODES = ("paper", "default")
# algo.features numbers kinds from 0 (forward: corner, backward: jump edge); the schema keeps 0 for "unknown".
_KIND_TO_SCHEMA = (t.FEATURE_FORWARD, t.FEATURE_BACKWARD)


@dataclass(frozen=True)
class FeatureConfig:
    mode: str = "default"   # "paper" or "default"; presets corners.*
    corners: FeatureParams = field(default_factory=FeatureParams.default)  # both searches' knobs (key kept)
    wall_direction: bool = True  # publish the dominant wall direction mod 90° (not in the paper)
    wall_lines: WallDirectionParams = field(default_factory=WallDirectionParams)  # the line fits that measure it

    #: What an operator sets (docs/settings.md); ``mode`` presets the rest of ``corners``.
    SETTINGS: ClassVar[tuple[str, ...]] = (
        "mode", "corners.max_range_m", "corners.arm_dists_m", "corners.corner_tol_deg", "corners.jump_m",
        "corners.nms_radius_m", "corners.range_sigma_m", "wall_direction", "wall_lines.min_support_frac",
    )
    RETIRED: ClassVar[dict[str, str]] = {
        "walls.min_support_frac": "renamed features.wall_lines.min_support_frac (one name per idea: "
                                  "wall_direction turns the measurement on, wall_lines are its line fits)",
    }

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ConfigError(f"features.mode must be one of {MODES}, got {self.mode!r}")


def preset(mode: str) -> FeatureConfig:
    if mode not in MODES:
        raise ConfigError(f"mode must be one of {MODES}, got {mode!r}")
    # The paper preset is the literal reading: no wall-direction measurement.
    return FeatureConfig(mode=mode, corners=getattr(FeatureParams, mode)(), wall_direction=mode != "paper")


class FeatureStep(StepBase):
    def __init__(self, cfg: FeatureConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.seq = 0

    def on_message(self, msg: Message):
        fs: t.FilteredScan = msg.value
        found = extract_features(fs.scan.ranges_m, fs.scan.angles_rad, fs.kept_mask, self.cfg.corners)
        kinds = [_KIND_TO_SCHEMA[k] for k in found.kind.tolist()]
        self.counts["scans"] += 1
        self.counts["forward"] += kinds.count(t.FEATURE_FORWARD)
        self.counts["backward"] += kinds.count(t.FEATURE_BACKWARD)
        wall = wall_direction(fs.points_xy_m, self.cfg.wall_lines) if self.cfg.wall_direction else None
        wall_rad, wall_sigma = (wall.direction_rad, wall.sigma_rad) if wall is not None else (np.nan, np.nan)
        self.counts["wall_direction"] += int(wall is not None)
        self.seq += 1
        yield Output(topics.FEATURES, t.Features(stamp_ns=fs.stamp_ns, seq=self.seq, scan_seq=fs.scan.seq, kind=kinds,
                                                 xy_m=found.xy_m, cov_m2=found.cov_m2, beam=found.beam,
                                                 angle_deg=found.angle_deg, wall_direction_rad=wall_rad,
                                                 wall_direction_sigma_rad=wall_sigma))


SPEC = ServiceSpec(
    name="features",
    summary="Features of denoised scans: corners by forward searching, jump edges by backward searching.",
    config_type=FeatureConfig,
    inputs=(topics.SCAN_FILTERED,),
    outputs=(topics.FEATURES,),
    skippable=(topics.SCAN_FILTERED,),
    build=lambda cfg, ctx: FeatureStep(cfg),
    preset=preset,
)
