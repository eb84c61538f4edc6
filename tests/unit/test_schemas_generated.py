"""The committed protobuf modules are exactly what schemas/ generates."""

from __future__ import annotations

import pytest

pytest.importorskip("grpc_tools", reason="grpcio-tools is in the test extra")

from lrfslam.tools import gen_schemas


def test_generated_code_matches_the_schemas(capsys):
    assert gen_schemas.main(["--check"]) == 0, capsys.readouterr().out


def test_every_schema_file_is_generated(tmp_path):
    generated = {p.name for p in gen_schemas.generate(tmp_path)}
    protos = {p.stem for p in gen_schemas.SCHEMAS.rglob("*.proto")}
    assert {f"{s}_pb2.py" for s in protos} <= generated
