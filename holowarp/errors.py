"""The two kinds of failure every holowarp command distinguishes.

- :class:`InputError`: the request cannot be carried out as given (a missing or malformed
  file, an argument out of range, a dataset that cannot be reconstructed). Raised before any
  work wherever it can be detected then; the message is one line that names the file or the
  argument and the reason. Commands exit with status 2.
- :class:`RunError`: the work started and could not finish (a simulation that diverged, an
  optimisation that produced non-finite values). Commands exit with status 1.

Every domain error type derives from one of them (``DatasetError``, ``MeshIOError``, ...), so
a command catches these two and nothing else.
"""

from __future__ import annotations

import re

__all__ = ["InputError", "RunError", "one_line", "pxr_reason"]


class InputError(ValueError):
    """The input cannot be used; the message names the file or argument and the reason."""


class RunError(RuntimeError):
    """The work started but could not finish; the message says where and why."""


def one_line(message: object) -> str:
    """``message`` folded onto one line: C++ libraries (pxr, VTK) raise multi-line texts
    whose first line alone often lacks the reason, so every non-empty line is kept, joined
    with ``" | "``, with runs of whitespace collapsed."""
    lines = [" ".join(part.split()) for part in str(message).splitlines()]
    return " | ".join(x for x in lines if x)


_PXR_ERROR = re.compile(r"Error in '[^']*' at line \d+ in file [^:]*: '(.*?)'\s*$", re.M | re.S)


def pxr_reason(exc: BaseException) -> str:
    """The human part of a pxr (USD) error: pxr raises ``Tf.ErrorException`` whose text is one
    block per C++ frame, "Error in '<function>' at line N in file <source> : '<message>'"; keep
    the messages only, in order, joined with "; "."""
    text = str(exc)
    found = [" ".join(m.split()) for m in _PXR_ERROR.findall(text)]
    return "; ".join(found) if found else one_line(text)
