"""Every setting an operator can change, with its default: a new one, a removed one or a new
default is a deliberate change made here, in docs/settings.md and in the CHANGELOG."""

from __future__ import annotations

import dataclasses
import re
import typing
from pathlib import Path

import pytest

from lrfslam import services
from lrfslam.errors import ConfigError
from lrfslam.runtime import config
from lrfslam.runtime.bus import BusConfig

DOC = Path(__file__).resolve().parents[2] / "docs" / "settings.md"
#: The sizes the settings are held to (issue 29): the two large stages at most 25, the rest fewer.
MOST = {"slam": 25, "mapper": 25}
MOST_ELSEWHERE = 15
#: Fields of a configuration at most, the settings and the fixed parameters the tests and the
#: evaluations vary (the paper's and the default method's knobs, the EKF's noise model); every
#: other parameter is a named constant of its module.
MOST_FIELDS = 25

SETTINGS = {
    "bus": {
        "robot": "robot1",
        "mode": "peer",
        "connect": ("tcp/127.0.0.1:7447",),
        "listen": ("tcp/127.0.0.1:0",),
        "zenoh_config": "",
        "queue_size": 512,
        "skip_stale": True,
        "health_period_s": 1.0,
        "debug_slow": "",
        "join": False,
        "health_file": "",
        "wall_clock_stamps": True,
        "checkpoint_dir": "",
        "checkpoint_period_s": 5.0,
    },
    "sensor": {
        "source": "auto",
        "world": "hallway_loop",
        "seed": 1,
        "rate_hz": 10.0,
        "speed_mps": 0.5,
        "speedup": 1.0,
        "range_sigma_m": 0.01,
        "mixed_pixel_prob": 0.3,
        "odom_trans_sigma_per_sqrt_m": 0.02,
        "odom_rot_sigma_per_sqrt_rad": 0.02,
        "max_scans": 0,
        "start_m": 0.0,
        "epoch_ns": 0,
        "device": "",
        "baud": 38400,
    },
    "denoise": {
        "mode": "default",
        "histogram.max_range_m": 4.0,
        "histogram.keep_frac": 0.15,
        "histogram.bin_deg": 22.5,
        "histogram.period_deg": 90.0,
    },
    "features": {
        "mode": "default",
        "corners.max_range_m": 4.0,
        "corners.arm_dists_m": (0.3, 0.6, 0.9, 1.2),
        "corners.corner_tol_deg": 10.0,
        "corners.jump_m": 1.5,
        "corners.nms_radius_m": 0.3,
        "corners.range_sigma_m": 0.015,
        "wall_direction": True,
        "wall_lines.min_support_frac": 0.6,
    },
    "slam": {
        "scan_matching": True,
        "use_backward_features": True,
        "use_wall_direction": True,
        "wait_for_odometry": True,
        "no_odometry_sigma_m": 0.2,
        "no_odometry_sigma_rad": 0.2,
        "map_period_s": 5.0,
        "ekf.odom_trans_sigma_per_sqrt_m": 0.02,
        "ekf.odom_rot_sigma_per_sqrt_rad": 0.02,
        "ekf.odom_rot_sigma_per_sqrt_m": 0.005,
        "ekf.corner_range_sigma_m": 0.005,
        "ekf.corner_bearing_sigma_rad": 0.002,
        "ekf.association": "nn",
        "ekf.gate_assoc_chi2": 9.21,
        "ekf.gate_new_chi2": 25.0,
        "ekf.min_sightings_to_confirm": 2,
        "ekf.max_landmarks": 1000,
        "tracker.max_point_range_m": 8.0,
        "tracker.free_space_check": True,
    },
    "mapper": {
        "map": "",
        "localize": False,
        "loop_closure.keyframe_trans_m": 0.5,
        "loop_closure.keyframe_rot_rad": 0.35,
        "loop_closure.max_range_m": 20.0,
        "loop_closure.min_travel_m": 10.0,
        "loop_closure.candidate_radius_m": 3.0,
        "loop_closure.max_window_m": 12.0,
        "loop_closure.min_score": 0.5,
        "loop_closure.max_second_ratio": 0.9,
        "loop_closure.gate_chi2": 16.0,
        "loop_closure.match_cov_scale": 16.0,
        "loop_closure.odom_trans_sigma_per_m": 0.01,
        "loop_closure.odom_rot_sigma_per_m": 0.006,
        "loop_closure.odom_rot_sigma_per_rad": 0.03,
        "loop_closure.fold_revisits": True,
        "loop_closure.fold_after_keyframes": 50,
        "loop_closure.correlative.cell_m": 0.1,
    },
    "recorder": {
        "directory": "recordings",
        "name": "",
        "flush_period_s": 1.0,
        "chunk_size_kb": 1024,
        "max_segment_mb": 512.0,
        "max_segment_s": 0.0,
        "retry_period_s": 10.0,
        "include_health": True,
        "foxglove": True,
    },
}


def config_class(name: str) -> type:
    return BusConfig if name == "bus" else services.spec(name).config_type


def test_every_setting_is_listed_with_its_default():
    assert list(SETTINGS) == ["bus", *services.NAMES]
    for name, listed in SETTINGS.items():
        assert config.settings(config_class(name)) == listed, name
        assert len(listed) <= MOST.get(name, MOST_ELSEWHERE), name


def leaf_fields(cls: type) -> int:
    hints = typing.get_type_hints(cls)
    return sum(leaf_fields(hints[f.name]) if dataclasses.is_dataclass(hints[f.name]) else 1
               for f in dataclasses.fields(cls))


def test_a_configuration_holds_its_settings_and_few_fixed_parameters():
    for name, listed in SETTINGS.items():
        assert len(listed) <= leaf_fields(config_class(name)) <= MOST_FIELDS, name


def documented() -> dict[str, list[str]]:
    """Service -> the setting names of its table in docs/settings.md, in order."""
    out: dict[str, list[str]] = {}
    section = None
    for line in DOC.read_text().splitlines():
        if line.startswith("## "):
            section = line[3:].split()[0]
            out[section] = []
        elif section and (m := re.match(r"\| `([a-z0-9_.]+)` \|", line)):
            out[section].append(m.group(1))
    return out


def test_docs_settings_names_every_setting_once_in_its_services_table():
    tables = documented()
    assert list(tables) == list(SETTINGS)
    for name, listed in SETTINGS.items():
        assert sorted(tables[name]) == sorted(listed), name


@pytest.mark.parametrize("name", services.NAMES)
def test_a_retired_setting_is_refused_in_one_line_naming_what_replaced_it(name):
    cls = config_class(name)
    for retired, replacement in getattr(cls, "RETIRED", {}).items():
        assert retired not in config.settings(cls)
        for layer in ({"sets": [f"{retired}=1"]}, {"file": {name: {retired: 1}}}):
            with pytest.raises(ConfigError) as err:
                config.service_config(services.spec(name), **layer)
            assert str(err.value).count("\n") == 0
            assert str(err.value).startswith(f"{retired!r} (")
            assert str(err.value).endswith(f"is no longer a setting: {replacement}")


def test_a_fixed_parameter_and_an_unknown_name_are_refused_in_one_line():
    slam = services.spec("slam")
    with pytest.raises(ConfigError, match=r"^'ekf.tentative_max_age_updates' \(--set\) is a fixed parameter \(30\)"):
        config.service_config(slam, sets=["ekf.tentative_max_age_updates=5"])
    with pytest.raises(ConfigError, match=r"^unknown setting 'scan_matchng' \(config file\); "
                                          r"did you mean 'scan_matching'\?$"):
        config.service_config(slam, file={"slam": {"scan_matchng": False}})


def test_the_environment_sets_settings_and_nothing_else():
    slam = services.spec("slam")
    env = {"LRFSLAM_SLAM_EKF__ASSOCIATION": "jcbb", "LRFSLAM_SLAM_EKF__TENTATIVE_MAX_AGE_UPDATES": "5"}
    cfg = config.service_config(slam, env=env)
    assert cfg.ekf.association == "jcbb" and cfg.ekf.tentative_max_age_updates == 30
