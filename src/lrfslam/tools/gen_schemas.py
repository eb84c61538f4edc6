"""Regenerate ``src/lrfslam/msgs/v*/*_pb2.py`` from ``schemas/`` (needs grpcio-tools).

    python -m lrfslam.tools.gen_schemas           # rewrite the generated modules
    python -m lrfslam.tools.gen_schemas --check   # exit 1 if they are out of date

The generated code is committed so installing the package needs no protoc;
a test runs ``--check`` so the two can never drift apart.
"""

from __future__ import annotations

import argparse
import filecmp
import shutil
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
SCHEMAS = ROOT / "schemas"
OUT = ROOT / "src"


def generate(out_dir: Path) -> list[Path]:
    """Run protoc on every schema into ``out_dir``; the generated files, relative to it."""
    from grpc_tools import protoc

    protos = sorted(p.relative_to(SCHEMAS).as_posix() for p in SCHEMAS.rglob("*.proto"))
    args = ["protoc", f"-I{SCHEMAS}", f"--python_out={out_dir}", f"--pyi_out={out_dir}", *protos]
    if protoc.main(args) != 0:
        raise SystemExit("protoc failed")
    return sorted(p.relative_to(out_dir) for p in out_dir.rglob("*_pb2.py*"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lrfslam.tools.gen_schemas", description=__doc__)
    parser.add_argument("--check", action="store_true", help="only compare; exit 1 when out of date")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        files = generate(Path(tmp))
        stale = [f for f in files if not (OUT / f).exists() or not filecmp.cmp(Path(tmp) / f, OUT / f, shallow=False)]
        if args.check:
            for f in stale:
                print(f"out of date: src/{f}")
            return 1 if stale else 0
        for f in stale:
            (OUT / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(Path(tmp) / f, OUT / f)
            print(f"wrote src/{f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
