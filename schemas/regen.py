"""Regenerate (or check) the Python modules compiled from ``schemas/proto``.

    python -m schemas.regen          # rewrite schemas/gen/*_pb2.py
    python -m schemas.regen --check  # exit 1 if the committed modules are out of date

The generator is ``grpcio-tools``' bundled protoc, pinned in pyproject's ``dev`` extra so the
output is byte-for-byte reproducible.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

PROTO_ROOT = Path(__file__).parent / "proto"
GEN_DIR = Path(__file__).parent / "gen"


def generate(out_dir: Path) -> list[Path]:
    """Compile every ``.proto`` under PROTO_ROOT into ``out_dir``; return the written files."""
    from grpc_tools import protoc  # dev-only dependency

    sources = sorted(str(p.relative_to(PROTO_ROOT)) for p in PROTO_ROOT.rglob("*.proto"))
    out_dir.mkdir(parents=True, exist_ok=True)
    rc = protoc.main(["protoc", f"-I{PROTO_ROOT}", f"--python_out={out_dir}", f"--pyi_out={out_dir}", *sources])
    if rc != 0:
        raise RuntimeError(f"protoc failed with exit code {rc}")
    return sorted(p for p in out_dir.rglob("*_pb2.py*"))


def stale_files() -> list[str]:
    """Names of generated files that differ from a fresh generation (empty when up to date)."""
    with tempfile.TemporaryDirectory() as tmp:
        fresh = generate(Path(tmp))
        diffs = []
        for f in fresh:
            rel = f.relative_to(tmp)
            committed = GEN_DIR / rel
            if not committed.exists() or committed.read_bytes() != f.read_bytes():
                diffs.append(str(rel))
        return diffs


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="only check, write nothing")
    args = parser.parse_args(argv)
    if args.check:
        diffs = stale_files()
        if diffs:
            sys.stderr.write(f"generated code is stale: {', '.join(diffs)}; run python -m schemas.regen\n")
            return 1
        return 0
    written = generate(GEN_DIR)
    sys.stdout.write("\n".join(str(p) for p in written) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
