"""Dispatch ``python -m holowarp.bench NAME ...`` to ``holowarp.bench.NAME.main``."""

from __future__ import annotations

import importlib
import sys

from holowarp.bench import BENCHMARKS


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in BENCHMARKS:
        print(f"usage: python -m holowarp.bench {{{','.join(BENCHMARKS)}}} [--json] [--device cpu|cuda] ...")
        if argv and argv[0] not in ("-h", "--help"):
            print(f"error: unknown benchmark {argv[0]!r}", file=sys.stderr)
            return 2
        return 0
    mod = importlib.import_module(f"holowarp.bench.{argv[0]}")
    return int(mod.main(argv[1:]) or 0)


if __name__ == "__main__":
    sys.exit(main())
