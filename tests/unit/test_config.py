"""Configuration layering: defaults < file < environment < flags, with errors for typos."""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest

from lrfslam.errors import ConfigError
from lrfslam.runtime import config


@dataclass(frozen=True)
class Inner:
    bin_deg: float = 20.0
    arms_m: tuple[float, ...] = (0.3, 0.6)
    resid_m: float | None = 0.05


@dataclass(frozen=True)
class Outer:
    mode: str = "default"
    count: int = 3
    on: bool = True
    inner: Inner = field(default_factory=Inner)


def test_precedence_file_env_flags():
    table = {"mode": "paper", "count": 4, "inner": {"bin_deg": 10}}
    env = {"X_COUNT": "5", "X_INNER__ARMS_M": "0.1,0.2,0.4"}
    cfg = config.load(Outer, table=table, env=env, env_prefix="X", sets=["count=6", "inner.resid_m=none"])
    assert cfg.mode == "paper"                 # file
    assert cfg.inner.bin_deg == 10.0           # file, nested, coerced to float
    assert cfg.inner.arms_m == (0.1, 0.2, 0.4)  # env, tuple
    assert cfg.count == 6                      # flag beats env beats file
    assert cfg.inner.resid_m is None
    assert config.load(Outer) == Outer()


def test_base_preset_is_overridden_only_where_set():
    base = Outer(mode="paper", count=9, inner=Inner(bin_deg=10.0))
    cfg = config.load(Outer, sets=["inner.arms_m=[1.0]"], base=base)
    assert cfg == Outer(mode="paper", count=9, inner=Inner(bin_deg=10.0, arms_m=(1.0,)))


@pytest.mark.parametrize("sets, match", [
    (["cuont=1"], "unknown setting 'cuont'"),
    (["count=1.5"], "count"),
    (["on=maybe"], "on"),
    (["count"], "name=value"),
])
def test_bad_settings_fail_clearly(sets, match):
    with pytest.raises(ConfigError, match=match):
        config.load(Outer, sets=sets)


def test_read_file(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text('[slam]\ncount = 2\n[bus]\nrobot = "r2"\n')
    assert config.read_file(p)["bus"]["robot"] == "r2"
    p.write_text("[slam\n")
    with pytest.raises(ConfigError, match="c.toml"):
        config.read_file(p)
    with pytest.raises(ConfigError, match="cannot read"):
        config.read_file(tmp_path / "missing.toml")


def test_a_config_file_with_an_unknown_table_names_the_nearest_one(tmp_path):
    path = tmp_path / "old.toml"
    path.write_text('[feature]\nmode = "paper"\n')   # the service was renamed "features"
    with pytest.raises(ConfigError, match=r"unknown table \[feature\] \(did you mean \[features\]\?\)"):
        config.read_file(path, ("bus", "denoise", "features", "slam"))
    assert config.read_file(path) == {"feature": {"mode": "paper"}}   # no tables given: not checked
