"""Write the JSON Schema of every wire model to schemas/json/<Model>.json.

    python -m tacf_schemas.export            # regenerate
    python -m tacf_schemas.export --check    # exit 1 if the files differ from the models
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from .models import MODELS

JSON_DIR = Path(__file__).resolve().parent / "json"
#: The draft pydantic writes in: named in each file, since a validator left to its default draft (7, often) ignores
#: 2020-12's keywords, such as the prefixItems that type a box.
DRAFT = "https://json-schema.org/draft/2020-12/schema"
log = logging.getLogger("tacf_schemas.export")


def schema_text(name: str) -> str:
    """The exported file content for one model: sorted keys, 2-space indent, trailing newline."""
    schema = {"$schema": DRAFT, **MODELS[name].model_json_schema(mode="validation")}
    return json.dumps(schema, indent=2, sort_keys=True) + "\n"


def expected_files() -> dict[str, str]:
    return {f"{name}.json": schema_text(name) for name in sorted(MODELS)}


def drift(directory: Path = JSON_DIR) -> list[str]:
    """File names that are missing or stale in `directory`, and in schemas/json/ those of no model."""
    expected = expected_files()
    present = {p.name for p in directory.glob("*.json")} if directory.is_dir() else set()
    stale = [n for n, text in expected.items() if n not in present or (directory / n).read_text() != text]
    return sorted(stale + [p.name for p in _leftovers(directory, expected)])


def _leftovers(directory: Path, expected: dict[str, str]) -> list[Path]:
    """schemas/json/'s files of models that are gone; a folder given with --dir may hold JSON files of its own."""
    if directory.resolve() != JSON_DIR:
        return []
    return [p for p in directory.glob("*.json") if p.name not in expected]


def write(directory: Path = JSON_DIR) -> list[Path]:
    directory.mkdir(parents=True, exist_ok=True)
    expected = expected_files()
    for leftover in _leftovers(directory, expected):
        log.info("removed %s (no such model)", leftover)
        leftover.unlink()
    paths = []
    for name, text in expected.items():
        path = directory / name
        path.write_text(text)
        paths.append(path)
    return paths


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tacf_schemas.export", description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="only compare; exit 1 on drift")
    parser.add_argument("--dir", type=Path, default=JSON_DIR)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.check:
        stale = drift(args.dir)
        for name in stale:
            log.error("out of date: %s", name)
        return 1 if stale else 0
    for path in write(args.dir):
        log.info("wrote %s", path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
