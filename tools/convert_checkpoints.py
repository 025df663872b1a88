"""Convert checkpoints to the current format (`lgnn.learn.checkpoints`), into a new folder.

Each `*.npz` checkpoint of SOURCE is written to TARGET under the same name by
`lgnn.learn.train.convert_checkpoint`: the same parameters, optimiser state, history,
settings and training environment, leaves named by pytree path, compressed, and
`converted_from` (the source's format and sha256). The sources are only read; TARGET
must be another folder (it is created). Rollouts of a converted checkpoint are
bit-identical to the original's (tests/test_checkpoints.py).

Records keyed on a checkpoint's bytes (`lgnn.records.file_digest`) do not follow a
converted file by themselves: its `converted_from.sha256` names the bytes they keyed on.

    PYTHONPATH=. python tools/convert_checkpoints.py results/benchmark/checkpoints /tmp/converted
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import lgnn

lgnn.configure()

from lgnn.errors import ConfigError, LgnnError  # noqa: E402
from lgnn.learn import models, train  # noqa: E402


def convert_folder(source: Path, target: Path) -> list[tuple[Path, int, int]]:
    """Convert every checkpoint `source/*.npz` to `target/` (created); returns
    `(target file, bytes before, bytes after)` each, in name order."""
    if not source.is_dir():
        raise ConfigError(f"{source}: no such folder")
    if target.resolve() == source.resolve():
        raise ConfigError(f"{target}: the converted checkpoints go to another folder (the sources are never rewritten)")
    target.mkdir(parents=True, exist_ok=True)
    sizes = []
    for path in sorted(source.glob("*.npz")):
        converted = target / path.name
        train.convert_checkpoint(path, converted)
        sizes.append((converted, path.stat().st_size, converted.stat().st_size))
    return sizes


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", type=Path, help="folder of checkpoints (*.npz), only read")
    parser.add_argument("target", type=Path, help="folder the converted checkpoints are written to")
    parser.add_argument("--model-code", action="append", default=[], metavar="MODULE:ATTR",
                        help="a model defined outside lgnn that a checkpoint names (lgnn.learn.models.load_spec)")
    args = parser.parse_args(argv)
    try:
        for reference in args.model_code:
            models.load_spec(reference)
        sizes = convert_folder(args.source, args.target)
    except LgnnError as err:
        print(f"convert_checkpoints: error: {err}", file=sys.stderr)
        return 2
    for path, before, after in sizes:
        print(f"{path}: {before} -> {after} bytes")
    if sizes:
        print(f"{len(sizes)} checkpoints: {sum(s[1] for s in sizes)} -> {sum(s[2] for s in sizes)} bytes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
