"""``make bench``: speed and accuracy figures, printed as tables and saved as JSON.

Figures come from here, never from timed tests. Each ``bench_*.py`` module beside
this file is one benchmark with ``TITLE``, ``run() -> dict`` and ``report(dict) ->
lines``. Run ``python tests/benchmarks/run.py [--only NAME] --out out/bench.json``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import platform
import sys
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent


def show(name: str, module: Any, results: dict[str, Any], out: Path | None = None) -> None:
    """Print one bench's title and table; also write its results as JSON to ``out``."""
    print(f"{name}: {module.TITLE}")
    for line in module.report(results):
        print(line)
    if out:  # a bench run alone on a fresh clone must not lose its results to a folder
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(results, indent=2) + "\n")


def main() -> int:
    """Run every benchmark (or those named), print tables, write the JSON file."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("out/bench.json"))
    parser.add_argument("--only", action="append", help="run only this bench (e.g. extraction)")
    args = parser.parse_args()
    # Benches import their siblings (harsh_frames, timing) and the shared test builders
    # (tests.helpers) by name.
    sys.path[:0] = [str(HERE), str(HERE.parents[1])]
    names = sorted(p.stem.removeprefix("bench_") for p in HERE.glob("bench_*.py"))
    if args.only:
        unknown = set(args.only) - set(names)
        if unknown:
            parser.error(f"unknown bench {sorted(unknown)}; known: {names}")
        names = [n for n in names if n in args.only]
    results: dict[str, Any] = {"machine": platform.platform(), "python": platform.python_version()}
    for name in names:
        module = importlib.import_module(f"bench_{name}")
        results[name] = module.run()
        show(name, module, results[name])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
