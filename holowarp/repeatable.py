"""Repeatable fTetWild: the tet initialisation (method.md §4) as a function of the run's seed.

fTetWild, through pytetwild's extension, seeds its random choices from ``std::random_device``,
so two tetrahedralisations of one surface differ (bob's surface at edge length 0.05: seventeen
calls gave seventeen meshes of 12.1k-13.4k tets, with one thread, pinned to one core, with
address-space randomisation off and with libc's ``srand`` fixed alike), and with them every
later stage of a run. Everything else in a run is already a function of the seed.

:func:`random_device` compiles (once, into the user cache) and loads with ``RTLD_GLOBAL`` a
library that defines ``std::random_device::_M_getval`` (``assets/native``). Loaded before
pytetwild's extension, its definition is the one the extension binds to, and every draw then
comes from a SplitMix64 stream that :meth:`SeededRandomDevice.seed` resets, and libc's
``rand``, which fTetWild also calls, is seeded with it. With it, one surface, one seed and one
machine give one mesh in a fresh process: three processes tetrahedralising a run's stage-0
hull gave one hash, as did two whole runs. fTetWild's output also depends on the process's
history (a second call with the same seed in the same process gave another mesh, the same
one in every process), so :mod:`holowarp` calls it once per run, at the tet initialisation.
The library is loaded at the first tetrahedralisation; native code loaded after it that reads
``std::random_device`` (none in a run, but e.g. an extension imported later by the caller)
draws from the same stream, and so becomes repeatable too.

Where it cannot work, tetrahedralisation goes on as before and :func:`status` says why (one
warning per process): not Linux (other loaders do not interpose this way), no C++ compiler
(``$CXX``, ``c++``, ``g++`` or ``clang++``), the compile failed, ``HOLOWARP_NO_NATIVE`` is set,
or pytetwild's extension was loaded before this module could load the library.
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

__all__ = ["SeededRandomDevice", "random_device", "unbound", "status", "cache_dir"]

SOURCE = Path(__file__).resolve().parent / "assets" / "native" / "seeded_random_device.cpp"
_EXTENSION = "pytetwild.PyfTetWildWrapper"

_state: dict = {"loaded": False, "device": None, "reason": None, "warned": False}


class SeededRandomDevice:
    """The loaded library: :meth:`seed` resets the stream, :meth:`draws` counts the draws
    since (0 after a tetrahedralisation means the extension did not bind to it)."""

    def __init__(self, lib: ctypes.CDLL):
        self._lib = lib
        lib.holowarp_seed_random_device.argtypes = [ctypes.c_uint64]
        lib.holowarp_seed_random_device.restype = None
        lib.holowarp_random_device_draws.argtypes = []
        lib.holowarp_random_device_draws.restype = ctypes.c_uint64

    def seed(self, seed: int) -> None:
        if not 0 <= int(seed) < 2**64:
            raise ValueError(f"random_device seed must lie in [0, 2**64), got {seed!r}")
        self._lib.holowarp_seed_random_device(int(seed))

    def draws(self) -> int:
        return int(self._lib.holowarp_random_device_draws())


def cache_dir() -> Path:
    """Where the compiled library lives: ``$HOLOWARP_CACHE``, else ``$XDG_CACHE_HOME/holowarp``,
    else ``~/.cache/holowarp``."""
    if os.environ.get("HOLOWARP_CACHE"):
        return Path(os.environ["HOLOWARP_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "holowarp"


def _compiler() -> str | None:
    for name in (os.environ.get("CXX"), "c++", "g++", "clang++"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def _build() -> tuple[Path | None, str | None]:
    """(path of the compiled library, None) or (None, reason)."""
    cxx = _compiler()
    if cxx is None:
        return None, "no C++ compiler ($CXX, c++, g++ or clang++) to build the seeded random device"
    src = SOURCE.read_bytes()
    tag = hashlib.sha256(src + cxx.encode()).hexdigest()[:16]
    out = cache_dir() / "native" / f"seeded_random_device-{tag}.so"
    if out.is_file():
        return out, None
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
        os.close(fd)
    except OSError as e:
        return None, f"cannot write the seeded random device into {out.parent} ({e}); set $HOLOWARP_CACHE"
    try:
        r = subprocess.run([cxx, "-shared", "-fPIC", "-O2", "-o", tmp, str(SOURCE)], capture_output=True, text=True,
                           timeout=120)
        if r.returncode != 0:
            lines = (r.stderr or r.stdout or "").strip().splitlines()
            first = next((ln for ln in lines if "error" in ln), lines[0] if lines else f"exit status {r.returncode}")
            return None, f"{cxx} could not build {SOURCE.name}: {first.strip()}"
        os.replace(tmp, out)  # atomic: a concurrent run never loads a half-written library
        return out, None
    except (OSError, subprocess.SubprocessError) as e:
        return None, f"building {SOURCE.name} failed ({type(e).__name__}: {e})"
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def random_device() -> SeededRandomDevice | None:
    """The seedable random device, loaded before pytetwild's extension (call this before
    importing pytetwild); None where it cannot work (:func:`status` says why, and the first
    such call logs one warning)."""
    if not _state["loaded"]:
        _state["loaded"] = True
        if os.environ.get("HOLOWARP_NO_NATIVE"):
            _state["reason"] = "HOLOWARP_NO_NATIVE is set"
        elif not sys.platform.startswith("linux"):
            _state["reason"] = f"interposing std::random_device is only done on Linux, not {sys.platform}"
        elif _EXTENSION in sys.modules:
            _state["reason"] = "pytetwild's extension was loaded before the seeded random device"
        else:
            path, reason = _build()
            if path is None:
                _state["reason"] = reason
            else:
                try:
                    _state["device"] = SeededRandomDevice(ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL))
                except (OSError, AttributeError) as e:  # unloadable, or not our library
                    _state["reason"] = f"{path}: cannot load ({e}); delete it to rebuild"
    if _state["device"] is None:
        _warn_once()
    return _state["device"]


def unbound() -> None:
    """Record that a tetrahedralisation drew nothing from the device: the extension is bound
    to libstdc++'s own (it was loaded first)."""
    _state["device"] = None
    _state["reason"] = "pytetwild's extension did not bind to the seeded random device (loaded before it?)"
    _warn_once()


def status() -> dict:
    """``{"repeatable": bool, "reason": str | None}``: whether fTetWild's output is a function
    of the seed in this process (as far as known: before the first tetrahedralisation, True
    means the library is loaded)."""
    return {"repeatable": _state["device"] is not None, "reason": _state["reason"]}


def _warn_once() -> None:
    if not _state["warned"]:
        _state["warned"] = True
        logging.getLogger("holowarp").warning(
            "fTetWild's tetrahedralisation is not repeatable here (%s): two runs with one seed give "
            "different meshes; a run repeats exactly only when resumed after its tet initialisation",
            _state["reason"])
