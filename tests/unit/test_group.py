"""Stages sharing a process (``lrfslam group``, ``lrfslam up --group``): what a group may hold, refused
before anything starts. Live, tests/integration/test_play.py (its outputs equal the offline pipeline's)
and test_up_supervision.py (killed and restarted)."""

from __future__ import annotations

import pytest

from lrfslam.errors import ConfigError
from lrfslam.runtime.runner import group_stages
from lrfslam.tools import up
from lrfslam.tools.group import main as group_main


def test_a_group_is_two_or_more_stages_in_pipeline_order():
    assert group_stages("mapper, slam,denoise") == ["denoise", "slam", "mapper"]
    for bad in ("slam", "slam,slam", "slam,recorder", "sensor,denoise", "", "slam,nonsense"):
        with pytest.raises(ConfigError, match="two or more different stages"):
            group_stages(bad)


def test_group_refuses_a_bad_group_or_setting_in_one_line(caplog):
    assert group_main(["slam,recorder"]) == 2
    assert group_main(["slam,mapper", "--set", "denoise.histogram.bin_deg=5"]) == 2   # not in the group
    assert group_main(["slam,mapper", "--set", "slam.no_such_setting=1"]) == 2
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert len(errors) == 3 and "two or more different stages" in errors[0], errors
    assert "denoise" in errors[1] and "no_such_setting" in errors[2], errors


@pytest.mark.parametrize("argv", [["--group", "slam"], ["--group", "slam,mapper", "--skip", "mapper"]])
def test_up_refuses_a_group_it_cannot_start_before_starting_anything(argv, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        up.main([*argv, "--recordings", str(tmp_path / "rec")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "two or more different stages" in err or "mapper is left out by --skip" in err, err
    assert not (tmp_path / "rec").exists()
