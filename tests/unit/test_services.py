"""The process graph: ``services.NAMES`` is an order the specs' inputs and outputs agree with."""

from __future__ import annotations

from lrfslam import services
from lrfslam.tools import up


def test_every_service_takes_its_inputs_from_services_before_it():
    produced: set[str] = set()
    for name in services.NAMES:
        spec = services.spec(name)
        if spec.raw_inputs:
            assert name == services.NAMES[-1], "a service that takes everything comes last"
        missing = {t.name for t in spec.inputs} - produced
        assert not missing, f"{name} takes {sorted(missing)} from no service before it"
        produced |= {t.name for t in spec.outputs}


def test_up_starts_consumers_before_their_producers():
    assert up.START_ORDER == tuple(reversed(services.NAMES))
    assert up.START_ORDER[0] == "recorder" and up.START_ORDER[-1] == "sensor"
