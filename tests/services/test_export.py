"""Map export: JSON with the landmarks and trajectory of the last state, and a PNG plot."""

from __future__ import annotations

import json

import numpy as np
from test_steps import chain, run, sim_outputs

from lrfslam.msgs import topics
from lrfslam.runtime.recording import RecordingWriter
from lrfslam.tools import export


def test_export_writes_json_and_png(tmp_path):
    outs = sim_outputs(40)
    states, _ = run("slam", chain(outs))
    path = tmp_path / "r.mcap"
    with RecordingWriter(path) as w:
        for o in [o for o in outs if o.topic in (topics.TRUTH, topics.ODOM)] + \
                 [type(outs[0])(topics.SLAM_STATE, s) for s in states]:
            w.write(o.topic.name, o.topic.schema, o.topic.codec.encode(o.value), o.value.stamp_ns)
    assert export.main([str(path), "-o", str(tmp_path / "out")]) == 0
    doc = json.loads((tmp_path / "out" / "map.json").read_text())
    last = states[-1]
    assert [lm["id"] for lm in doc["landmarks"]] == last.landmark_ids.tolist()
    assert len(doc["trajectory"]) == len(states)
    np.testing.assert_allclose([doc["trajectory"][-1][k] for k in ("x_m", "y_m", "theta_rad")], last.pose)
    png = (tmp_path / "out" / "map.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000


def test_ellipse_is_the_95_percent_contour():
    cov = np.array([[4.0, 0.0], [0.0, 1.0]])
    pts = export.ellipse(np.zeros(2), cov)
    d2 = np.einsum("ni,ij,nj->n", pts, np.linalg.inv(cov), pts)
    np.testing.assert_allclose(d2, export.CHI2_2D_95)
