"""Where an iteration's time goes: Warp kernels, torch ops, host work, and device syncs.

:class:`Probe` is a debug-mode instrument for the pipeline benchmark. While it is active:

- every ``wp.launch``, every replay of a recorded one (``wp.Launch.launch``: the geometry
  step's :class:`holowarp.ops._warp.StepCache` and the simulator replay their launches) and
  Warp's scan/sort utilities are timed; on CUDA the device is
  synchronised around each launch so the wall time is the kernel's. Launches from the CPU
  thread pool overlap, so kernel time is the length of the *union* of the launch intervals;
- every torch op is timed at the dispatcher (a ``TorchDispatchMode``: each ATen op once,
  forward and backward; the Warp launches inside our autograd functions are not ATen ops);
- every read of a device value on the host counts as a sync: ``item``/``float``/``int``/
  ``bool`` (ATen's ``_local_scalar_dense``), data-dependent shapes (``nonzero``,
  ``masked_select``, boolean-mask indexing, ``unique``), ``numpy``, ``tolist``, and copies
  off a CUDA device; every tensor made from host data (``torch.tensor``, ``as_tensor`` of
  a non-tensor, ``from_numpy``) counts as an upload, except Warp memory that
  ``wp.to_torch`` wraps in place. On CPU none of these block; on CUDA each is a round
  trip, so they are counted on either device.

Instrumentation slows each op down, so the benchmark takes the ms per iteration from a run
without the probe and only the shares and counts from the probed one.
"""

from __future__ import annotations

import contextlib
import threading
import time

import torch
import warp as wp
from torch.utils._python_dispatch import TorchDispatchMode

__all__ = ["Probe"]

_SYNC_OPS = {"_local_scalar_dense", "nonzero", "masked_select", "unique", "_unique", "_unique2", "unique_dim",
             "unique_consecutive"}
_UPLOADS = ("tensor", "as_tensor", "from_numpy")


def _device_memory(obj) -> bool:
    """True for what a tensor can wrap without a copy from the host: a tensor, a Warp array
    (``wp.to_torch`` on CUDA), or NumPy's view of one (``wp.to_torch`` on the CPU)."""
    return isinstance(obj, (torch.Tensor, wp.array)) or isinstance(getattr(obj, "base", None), wp.array)


class _OpTimer(TorchDispatchMode):
    """Times every ATen op and counts the ones that read device values on the host."""

    def __init__(self, probe):
        super().__init__()
        self.probe = probe

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        p = self.probe
        name = func.overloadpacket.__name__
        if name in _SYNC_OPS:
            p._syncs += 1
        elif name == "index" and any(isinstance(i, torch.Tensor) and i.dtype == torch.bool
                                     for i in (args[1] if len(args) > 1 else ()) if i is not None):
            p._syncs += 1
        elif name == "_to_copy" and args and args[0].device.type == "cuda" and kwargs \
                and str(kwargs.get("device", "")).startswith("cpu"):
            p._syncs += 1
        t0 = time.perf_counter()
        out = func(*args, **(kwargs or {}))
        dt = time.perf_counter() - t0
        p._torch_s += dt
        p.op_ms[name] = p.op_ms.get(name, 0.0) + dt * 1e3
        return out


class Probe:
    """Instrument a block of code; :meth:`region` measures one iteration.

    Usage::

        with Probe(device) as probe:
            for it in range(n):
                with probe.region():
                    step(it)
        probe.summary()  # shares of the probed time, per-iteration medians of the counts
    """

    def __init__(self, device: str = "cpu"):
        self.cuda = str(device).startswith("cuda")
        self.records: list[dict] = []
        self._intervals: list[tuple[float, float]] = []
        self._lock = threading.Lock()
        self._syncs = self._uploads = self._launches = 0
        self._torch_s = 0.0
        self.kernel_ms: dict[str, float] = {}  # summed over all regions, by kernel
        self.op_ms: dict[str, float] = {}  # summed over all regions, by ATen op
        self._patched: list[tuple[object, str, object]] = []
        self._active = False

    # ------------------------------------------------------------------ patching
    def _patch(self, owner, name, make):
        orig = getattr(owner, name)
        self._patched.append((owner, name, orig if name in vars(owner) else None))
        setattr(owner, name, make(orig))

    def _timed_launch(self, orig):
        def launch(*args, **kwargs):
            if not self._active or kwargs.get("record_cmd"):  # recording runs nothing
                return orig(*args, **kwargs)
            if self.cuda:
                wp.synchronize_device()
            t0 = time.perf_counter()
            try:
                return orig(*args, **kwargs)
            finally:
                if self.cuda:
                    wp.synchronize_device()
                t1 = time.perf_counter()
                first = args[0] if args else None  # a kernel, or a recorded Launch (its self)
                key = (getattr(first, "key", None) or getattr(getattr(first, "kernel", None), "key", None)
                       or getattr(orig, "__name__", "warp"))
                with self._lock:
                    self._intervals.append((t0, t1))
                    self._launches += 1
                    self.kernel_ms[key] = self.kernel_ms.get(key, 0.0) + (t1 - t0) * 1e3
        return launch

    def _counted(self, orig, kind):
        def wrapper(*args, **kwargs):
            if self._active and threading.current_thread() is threading.main_thread():
                if kind == "sync":
                    self._syncs += 1
                elif not (args and _device_memory(args[0])):
                    self._uploads += 1
            return orig(*args, **kwargs)
        return wrapper

    def __enter__(self):
        self._patch(wp, "launch", self._timed_launch)
        self._patch(wp.Launch, "launch", self._timed_launch)
        for name in ("array_scan", "radix_sort_pairs"):
            self._patch(wp.utils, name, self._timed_launch)
        for name in ("numpy", "tolist"):
            self._patch(torch.Tensor, name, lambda o: self._counted(o, "sync"))
        for name in _UPLOADS:
            self._patch(torch, name, lambda o: self._counted(o, "upload"))
        return self

    def __exit__(self, *exc):
        for owner, name, orig in reversed(self._patched):
            if orig is None:  # inherited: drop the override
                delattr(owner, name)
            else:
                setattr(owner, name, orig)
        self._patched.clear()
        return False

    # ------------------------------------------------------------------ measuring
    @contextlib.contextmanager
    def region(self):
        """Measure the enclosed code as one iteration (appends a record)."""
        self._intervals, self._syncs, self._uploads, self._launches = [], 0, 0, 0
        self._torch_s = 0.0
        self._active = True
        t0 = time.perf_counter()
        with _OpTimer(self):
            yield
            if self.cuda:
                torch.cuda.synchronize()
        total = time.perf_counter() - t0
        self._active = False
        kernel_s = _union(self._intervals)
        # Launch wall time includes Warp's argument packing. Torch ops and Warp launches run
        # one after the other on the main thread (Warp does not call torch), so they add up.
        self.records.append({"ms": total * 1e3, "kernel_ms": kernel_s * 1e3, "torch_ms": self._torch_s * 1e3,
                             "syncs": self._syncs, "uploads": self._uploads, "launches": self._launches})

    def summary(self) -> dict:
        """Totals over the records as shares of the probed time, and per-iteration medians
        of the counts."""
        if not self.records:
            return {}
        tot = sum(r["ms"] for r in self.records)
        kern = sum(r["kernel_ms"] for r in self.records)
        tch = min(sum(r["torch_ms"] for r in self.records), tot - kern)
        med = lambda k: float(sorted(r[k] for r in self.records)[len(self.records) // 2])  # noqa: E731
        return {
            "kernel_share": round(kern / tot, 3),
            "torch_share": round(tch / tot, 3),
            "host_share": round(max(tot - kern - tch, 0.0) / tot, 3),
            "syncs_per_iter": med("syncs"),
            "uploads_per_iter": med("uploads"),
            "launches_per_iter": med("launches"),
            "probed_ms_per_iter": round(tot / len(self.records), 2),
            "top_kernels_ms": _top(self.kernel_ms, len(self.records)),
            "top_torch_ops_ms": _top(self.op_ms, len(self.records)),
        }


def _top(d: dict, n: int, k: int = 6) -> dict:
    """The ``k`` largest entries of ``d`` per iteration (``n`` iterations), ms."""
    return {name: round(v / n, 2) for name, v in sorted(d.items(), key=lambda kv: -kv[1])[:k]}


def _union(intervals) -> float:
    """Total length of the union of (start, end) intervals."""
    total, end = 0.0, float("-inf")
    for a, b in sorted(intervals):
        if a > end:
            total += b - a
            end = b
        elif b > end:
            total += b - end
            end = b
    return total
