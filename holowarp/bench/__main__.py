"""Dispatch ``python -m holowarp.bench NAME ...`` to ``holowarp.bench.NAME.main``;
``--help`` lists every benchmark with its options."""

from __future__ import annotations

import contextlib
import importlib
import io
import sys

from holowarp.bench import BENCHMARKS


def _help() -> str:
    lines = [f"usage: python -m holowarp.bench {{{','.join(BENCHMARKS)}}} [options]", "",
             "Benchmarks print JSON (with --json): median times, ratios to the reference each names, peak memory.", ""]
    for name in BENCHMARKS:
        mod = importlib.import_module(f"holowarp.bench.{name}")
        doc = (mod.__doc__ or "").strip().splitlines()[0] if mod.__doc__ else ""
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf), contextlib.suppress(SystemExit):
            mod.main(["--help"])
        text = buf.getvalue().splitlines()
        start = next((i + 1 for i, ln in enumerate(text) if ln.rstrip().endswith(("options:", "arguments:"))), len(text))
        opts = [ln for ln in text[start:] if ln.strip() and "--help" not in ln]
        lines += [f"{name}: {doc}"] + [f"  {ln}" for ln in opts] + [""]
    return "\n".join(lines)


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(_help())
        return 0
    if argv[0] not in BENCHMARKS:
        print(f"error: unknown benchmark {argv[0]!r}; choose one of {', '.join(BENCHMARKS)} (see --help)", file=sys.stderr)
        return 2
    mod = importlib.import_module(f"holowarp.bench.{argv[0]}")
    return int(mod.main(argv[1:]) or 0)


if __name__ == "__main__":
    sys.exit(main())
