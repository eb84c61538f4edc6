"""The key-expression registry: every absolute key is built and parsed in ``msgs/topics.py``."""

import pytest
from hypothesis import given
from hypothesis import strategies as st

from lrfslam.msgs import topics

names = st.from_regex(r"[A-Za-z0-9_\-.]{1,12}", fullmatch=True)


@given(robot=names, service=names)
def test_service_keys_parse_back_to_robot_and_service(robot, service):
    for make in (topics.alive, topics.status, topics.health_key):
        assert topics.robot_and_service(make(robot, service)) == (robot, service)


def test_wildcards_cover_every_service_of_one_robot():
    assert topics.alive("r1", topics.ANY) == "lrf/r1/alive/*"
    assert topics.status("r1", topics.ANY) == "lrf/r1/svc/*/status"
    assert topics.health_key("r1", topics.ANY) == "lrf/r1/health/*"


@pytest.mark.parametrize("key", ["lrf/r1/scan", "lrf/r1/svc/slam", "other/r1/alive/slam", "lrf/r1/alive/slam/x"])
def test_other_keys_are_not_service_keys(key):
    with pytest.raises(KeyError):
        topics.robot_and_service(key)


def test_health_names_are_recognised():
    assert topics.is_health(topics.health("slam").name)
    assert not any(topics.is_health(tp.name) for tp in topics.DATA_TOPICS)
