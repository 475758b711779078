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

__all__ = [
    "atomic_path",
    "atomic_write_text",
    "atomic_write_json",
    "atomic_save_npz",
    "check_input_file",
    "check_output_dir",
    "check_output_file",
    "quiet_stdio",
]


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


def _writable_ancestor(path: Path, what: str, named: Path | None = None) -> Path:
    """The nearest existing ancestor of ``path``: it must be a folder we can create files in
    (errors name ``named``, default ``path``)."""
    from holowarp.errors import InputError

    named = path if named is None else named
    anc = path
    while not anc.exists():
        if anc.parent == anc:
            break
        anc = anc.parent
    if not anc.is_dir():
        raise InputError(f"{what} {named}: {anc} is a file, so {named} cannot be created")
    try:
        fd, probe = tempfile.mkstemp(prefix=".holowarp-write-test.", dir=anc)
    except OSError as e:
        raise InputError(f"{what} {named}: cannot write into {anc} ({e.strerror})") from None
    os.close(fd)
    os.unlink(probe)
    return anc


def check_output_dir(path: str | os.PathLike, *, what: str = "--out") -> Path:
    """``path`` as a :class:`Path` if it is (or can be created as) a writable folder; otherwise
    :class:`holowarp.errors.InputError` naming ``what`` and the reason. Call it before any work,
    so a bad output path fails in a second, not after an hour of computing."""
    from holowarp.errors import InputError

    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{what} {path}: is a file, expected a folder")
    _writable_ancestor(path, what)
    return path


def check_output_file(path: str | os.PathLike, *, what: str = "output") -> Path:
    """``path`` as a :class:`Path` if a file can be written there (its folder exists or can be
    created, and is writable; ``path`` is not a folder); otherwise an InputError."""
    from holowarp.errors import InputError

    path = Path(path)
    if path.is_dir():
        raise InputError(f"{what} {path}: is a folder, expected a file path")
    if path.exists() and not os.access(path, os.W_OK):
        raise InputError(f"{what} {path}: the file exists and is not writable")
    _writable_ancestor(path.parent, what, named=path)
    return path
