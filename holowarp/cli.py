"""One command-line convention for every ``python -m holowarp.*`` command.

- ``--device cpu|cuda[:N]`` on every command (one code path; CUDA without a GPU is an error);
- ``--quiet`` hides progress bars and status lines (bars also hide themselves when stderr is
  not a terminal, see :mod:`holowarp.progress`);
- ``--threads N``: CPU threads of holowarp's kernel drivers (default ``$HOLOWARP_THREADS``,
  else the cores this process may use shared among the holowarp commands running at the
  time, :func:`holowarp.device.cpu_threads`; results do not depend on it); torch's own
  intra-op pool is kept at one thread in every command: its tensors are small, and a
  spinning OpenMP pool per process is what made two runs side by side crawl;
- ``--preset fast|paper`` wherever a command has presets;
- errors: one line ``error: ...`` on stderr naming the file or argument; exit status 2 when
  the input cannot be used (:class:`holowarp.errors.InputError`), 1 when the work started
  and failed (:class:`holowarp.errors.RunError`), 0 on success.

Commands build their parser with :func:`parser` and run their body through :func:`run`.
"""

from __future__ import annotations

import argparse
import logging
import sys

from holowarp.config import valid_seed
from holowarp.errors import InputError, RunError, one_line

__all__ = ["PRESET_NAMES", "parser", "add_device", "add_quiet", "add_preset", "run", "fail"]

#: The preset names every command with presets accepts (see :mod:`holowarp.config`).
PRESET_NAMES = ("fast", "paper")


def parser(prog: str, description: str, *, epilog: str | None = None) -> argparse.ArgumentParser:
    """An ``ArgumentParser`` for ``python -m {prog}`` whose help keeps the epilog's layout."""
    return argparse.ArgumentParser(prog=f"python -m {prog}", description=description, epilog=epilog,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)


def add_device(p: argparse.ArgumentParser, *, note: str = "", threads: bool = True) -> None:
    p.add_argument("--device", default="cpu", metavar="DEV",
                   help="cpu, cuda or cuda:N (default: cpu)" + (f"; {note}" if note else ""))
    if threads:
        p.add_argument("--threads", type=int, default=None, metavar="N",
                       help="CPU threads for holowarp's kernels (default: $HOLOWARP_THREADS, else the cores shared "
                            "among the holowarp commands running; results do not depend on it; >= 1)")


def add_quiet(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quiet", action="store_true",
                   help="no progress bars or status lines (bars are off anyway when stderr is not a terminal)")
    # Earlier releases spelled it --no-progress in some commands.
    p.add_argument("--no-progress", dest="quiet", action="store_true", help=argparse.SUPPRESS)


def add_preset(p: argparse.ArgumentParser, *, default: str = "fast", what: str = "schedule and resolution") -> None:
    p.add_argument("--preset", choices=PRESET_NAMES, default=default,
                   help=f"{what} (default: {default}; paper = the paper's numbers, fast = a CPU-sized run)")


def fail(message: str) -> None:
    """Raise the :class:`InputError` for a bad argument (``run`` prints it, exit 2)."""
    raise InputError(message)


def _set_threads(threads) -> None:
    import os

    from holowarp.device import set_cpu_threads

    if threads is not None:
        if threads < 1:
            raise InputError(f"--threads must be >= 1, got {threads}")
        set_cpu_threads(threads)
    os.environ.setdefault("OMP_NUM_THREADS", "1")  # read by torch when it starts its pool
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)


def _check_seed(seed) -> None:
    if seed is not None and not valid_seed(seed):
        raise InputError(f"--seed {seed}: must be an integer in [0, 2**63)")


def run(body, args) -> int:
    """Call ``body(args)`` and turn holowarp's errors into the convention above.

    ``body`` returns an exit status (``None`` means 0).
    """
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    from holowarp.device import registered_run

    try:
        _set_threads(getattr(args, "threads", None))
        _check_seed(getattr(args, "seed", None))
        with registered_run():  # running commands share the cores (holowarp.device.cpu_threads)
            rc = body(args)
    except InputError as e:
        print(f"error: {one_line(e)}", file=sys.stderr)
        return 2
    except RunError as e:
        print(f"error: {one_line(e)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    return 0 if rc is None else int(rc)
