"""Device selection shared by every command: one code path, ``--device cpu|cuda``.

Warp and torch name devices the same way (``"cpu"``, ``"cuda"``, ``"cuda:0"``), so a single
string selects both. Asking for CUDA on a machine without a GPU fails early with a clear
message instead of deep inside a kernel launch.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor

from holowarp.errors import InputError

__all__ = ["DeviceError", "resolve_device", "init_warp", "cpu_threads", "set_cpu_threads", "THREADS_ENV", "live_runs",
           "registered_run", "run_chunks", "thread_chunks", "CPU_PIECES"]

#: Environment variable that sets how many CPU threads holowarp's Warp kernel drivers use.
THREADS_ENV = "HOLOWARP_THREADS"
_cpu_threads: int | None = None
_POOL: ThreadPoolExecutor | None = None
_POOL_SIZE = 0

#: What Warp's native library prints to stderr at start-up on a machine without a CUDA
#: driver. On such a machine every run is a CPU run and the line is noise; a CUDA request
#: there fails with :class:`DeviceError` instead.
_NO_DRIVER_LINE = "Could not find or load the NVIDIA CUDA driver"


class DeviceError(InputError):
    """The requested compute device is not available."""


_warp_ready = False


@contextlib.contextmanager
def _filtered_native_stderr():
    """Capture what native code writes to file descriptor 2 and re-emit all of it except
    Warp's missing-driver warning (it is written with C ``fprintf``, below Python's
    ``sys.stderr``)."""
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, ValueError, OSError):  # no real stderr (embedded, captured)
        yield
        return
    sys.stderr.flush()
    saved = os.dup(fd)
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        os.dup2(tmp.fileno(), fd)
        try:
            yield
        finally:
            sys.stderr.flush()
            os.dup2(saved, fd)
            os.close(saved)
            tmp.seek(0)
            text = tmp.read().decode(errors="replace")
            kept = [line for line in text.splitlines(keepends=True) if _NO_DRIVER_LINE not in line]
            if kept:
                sys.stderr.write("".join(kept))
                sys.stderr.flush()


def init_warp():
    """Initialise Warp once, quietly, and return the ``warp`` module."""
    global _warp_ready
    import warp as wp

    if not _warp_ready:
        wp.config.quiet = True
        # Warp >= 1.10 ignores ``quiet``; its banner and module-load lines go to stdout and
        # would corrupt JSON printed by commands, so raise the log level too.
        if hasattr(wp, "LOG_WARNING") and hasattr(wp.config, "log_level"):
            wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
        with _filtered_native_stderr():
            wp.init()
        _warp_ready = True
    return wp


def resolve_device(device: str | None = "cpu") -> str:
    """Validate a device string and return the canonical Warp/torch name.

    Args:
        device: ``"cpu"``, ``"cuda"`` or ``"cuda:N"``. ``None`` means ``"cpu"``.

    Returns:
        ``"cpu"`` or ``"cuda:N"``.

    Raises:
        DeviceError: the name is unknown, or CUDA was asked for and Warp sees no GPU.
    """
    device = "cpu" if device is None else str(device).strip().lower()
    if device == "cpu":
        return "cpu"
    if device == "cuda" or device.startswith("cuda:"):
        wp = init_warp()
        if not wp.is_cuda_available():
            raise DeviceError(f"--device {device}: no CUDA GPU is visible to Warp on this machine; use --device cpu")
        idx = 0 if device == "cuda" else device.split(":", 1)[1]
        try:
            idx = int(idx)
        except ValueError:
            raise DeviceError(f"--device {device}: expected cuda or cuda:N") from None
        if not 0 <= idx < wp.get_cuda_device_count():
            raise DeviceError(f"--device {device}: only {wp.get_cuda_device_count()} CUDA device(s) present")
        return f"cuda:{idx}"
    raise DeviceError(f"--device {device!r}: expected 'cpu', 'cuda' or 'cuda:N'")


def _available_cores() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # not Linux
        return max(1, os.cpu_count() or 1)


#: Where running holowarp commands register, so that the default thread count can share the
#: cores among them (:func:`cpu_threads`).
RUNS_DIR = os.path.join(tempfile.gettempdir(), f"holowarp-runs-{os.getuid() if hasattr(os, 'getuid') else 0}")
_RECHECK_S = 2.0
_shared: tuple[float, int] | None = None  # (time of the last count, threads it gave)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # exists, owned by someone else
        return True
    return True


def live_runs() -> int:
    """How many holowarp commands are registered in :data:`RUNS_DIR` and still running
    (at least 1: this one). Stale entries of processes that died are removed."""
    n = 0
    try:
        names = os.listdir(RUNS_DIR)
    except OSError:
        return 1
    for name in names:
        if not name.isdigit():
            continue
        if _alive(int(name)):
            n += 1
        else:
            with contextlib.suppress(OSError):
                os.remove(os.path.join(RUNS_DIR, name))
    return max(1, n)


@contextlib.contextmanager
def registered_run():
    """Register this process as a running holowarp command for the duration of the block."""
    path = os.path.join(RUNS_DIR, str(os.getpid()))
    try:
        os.makedirs(RUNS_DIR, exist_ok=True)
        with open(path, "w"):
            pass
    except OSError:  # a read-only or full temp dir: sharing is only an optimisation
        path = None
    try:
        yield
    finally:
        if path is not None:
            with contextlib.suppress(OSError):
                os.remove(path)


def cpu_threads() -> int:
    """CPU threads the kernel drivers split their heaviest launches over.

    Warp runs a CPU launch on one thread; the drivers of the rasterisers cut their per-pixel
    launches into pieces and run them on this many threads at once (the GIL is released while
    a kernel runs). Default: ``$HOLOWARP_THREADS`` if set (or :func:`set_cpu_threads`, the
    commands' ``--threads``), else the cores this process may use divided among the holowarp
    commands running at the moment (:func:`live_runs`, re-counted every two seconds), so two
    runs started side by side each take half the cores instead of both fighting for all of
    them. The pieces do not depend on the thread count, so neither do the results. Torch's
    own intra-op threads are set separately (commands use one: their tensors are small).
    """
    global _cpu_threads, _shared
    if _cpu_threads is None:
        env = os.environ.get(THREADS_ENV, "").strip()
        if env:
            try:
                _cpu_threads = max(1, int(env))
            except ValueError:
                raise DeviceError(f"${THREADS_ENV}={env!r}: expected a whole number of threads") from None
    if _cpu_threads is not None:
        return _cpu_threads
    import time

    now = time.monotonic()
    if _shared is None or now - _shared[0] > _RECHECK_S:
        _shared = (now, max(1, _available_cores() // live_runs()))
    return _shared[1]


def set_cpu_threads(n: int | None) -> None:
    """Set :func:`cpu_threads` (``None``: back to the default)."""
    global _cpu_threads, _shared
    if n is not None and int(n) < 1:
        raise DeviceError(f"threads must be >= 1, got {n}")
    _cpu_threads = None if n is None else int(n)
    _shared = None


#: Pieces a CPU launch is cut into (:func:`thread_chunks`): fixed, so that launches whose
#: pieces accumulate into their own buffers sum them in the same order on any thread count.
CPU_PIECES = 8


def thread_chunks(total: int, device: str, *, align: int = 256, always: bool = False) -> list[tuple[int, int]]:
    """``[(offset, count), ...]`` covering ``range(total)`` in :data:`CPU_PIECES` pieces of
    whole ``align``-thread blocks (several per thread balance tiles of unequal cost). One
    piece on CUDA, and on one CPU thread unless ``always``: launches that sum per-piece
    buffers pass ``always=True`` so that their result never depends on the thread count."""
    if device != "cpu" or total <= align or (cpu_threads() == 1 and not always):
        return [(0, total)]
    blocks = -(-total // align)
    pieces = min(blocks, CPU_PIECES)
    edges = [round(blocks * k / pieces) * align for k in range(pieces + 1)]
    edges[-1] = total
    return [(a, b - a) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def run_chunks(fn, chunks, *, kernel=None, device: str = "cpu") -> list:
    """``[fn(*chunk) for chunk in chunks]``, run on :func:`cpu_threads` threads when there
    are several (Warp releases the GIL while a CPU kernel runs); results in chunk order.

    The calling thread works too: it and ``cpu_threads() - 1`` pool threads take the chunks
    in order from one shared counter, so a call costs one hand-over per helper rather than
    one future per chunk (about 90 us against 115 us for two one-thread launches), which the simulator's
    short parallel sweeps feel. ``kernel``'s module is loaded first, so no two threads ever
    compile or load it. The rasterisers' drivers and the simulator share the pool.
    """
    global _POOL, _POOL_SIZE
    threads = cpu_threads()
    n = min(threads, len(chunks))
    if n <= 1:
        return [fn(*c) for c in chunks]
    if kernel is not None:
        kernel.module.load(init_warp().get_device(device))
    helpers = threads - 1
    if _POOL is None or _POOL_SIZE != helpers:
        if _POOL is not None:
            _POOL.shutdown(wait=True)
        _POOL, _POOL_SIZE = ThreadPoolExecutor(max_workers=helpers, thread_name_prefix="holowarp-kernel"), helpers
    results = [None] * len(chunks)
    counter = itertools.count()  # next() on it is atomic under the GIL

    def work():
        for k in iter(counter.__next__, None):
            if k >= len(chunks):
                return
            results[k] = fn(*chunks[k])

    futures = [_POOL.submit(work) for _ in range(n - 1)]
    try:
        work()
    finally:
        for f in futures:
            f.result()
    return results
