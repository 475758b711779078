"""File helpers: atomic writes, checked inputs, quiet third-party readers.

Atomic writes: a reader never sees a half-written output. Every writer in holowarp writes to a temporary file in the destination's folder and renames
it over the destination only after the write succeeded (``os.replace`` is atomic on POSIX
and Windows within one filesystem). A failed or interrupted write leaves any previous good
file untouched.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import tempfile
from pathlib import Path

__all__ = ["atomic_path", "atomic_write_text", "atomic_write_json", "atomic_save_npz", "check_input_file", "quiet_stdio"]


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None):
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    Args:
        path: the final destination. Its parent folder is created if missing.
        suffix: suffix of the temporary file (defaults to ``path``'s own, so libraries that
            pick the format from the extension still work).

    The temporary file is removed if the body raises.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = path.suffix if suffix is None else suffix
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".tmp" + suffix, dir=path.parent)
    os.close(fd)
    # mkstemp creates 0600 files; outputs get the permissions a plain open() would give.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically and return the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def atomic_write_json(path: str | os.PathLike, obj, *, indent: int = 2) -> Path:
    """Write ``obj`` as JSON to ``path`` atomically; NaN/inf are written as strings.

    JSON has no NaN or infinity; writing them bare makes files other tools reject, so they
    become ``"nan"``, ``"inf"`` and ``"-inf"``.
    """

    def clean(x):
        if isinstance(x, dict):
            return {str(k): clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        if hasattr(x, "tolist") and not isinstance(x, (str, bytes)):
            return clean(x.tolist())
        if isinstance(x, float) and (x != x or x in (float("inf"), float("-inf"))):
            return "nan" if x != x else ("inf" if x > 0 else "-inf")
        if isinstance(x, Path):
            return str(x)
        return x

    return atomic_write_text(path, json.dumps(clean(obj), indent=indent) + "\n")


def atomic_save_npz(path: str | os.PathLike, **arrays) -> Path:
    """``numpy.savez_compressed`` to ``path`` atomically."""
    import numpy as np

    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)
    return Path(path)


def check_input_file(path: str | os.PathLike, *, error: type[Exception], what: str = "file") -> Path:
    """``path`` as a :class:`Path` if it names a readable, non-empty file; otherwise raise
    ``error`` with a message that starts with the path and says why."""
    path = Path(path)
    if not path.exists():
        raise error(f"{path}: no such file")
    if path.is_dir():
        raise error(f"{path}: is a folder, expected a {what}")
    if not os.access(path, os.R_OK):
        raise error(f"{path}: not readable (permission denied)")
    if path.stat().st_size == 0:
        raise error(f"{path}: {what} is empty")
    return path


@contextlib.contextmanager
def quiet_stdio():
    """Silence Python-level stdout/stderr chatter of third-party readers (meshio, trimesh)."""
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        yield
