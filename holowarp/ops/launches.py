"""Recorded Warp launches for loops that repeat the same launches (issue 17).

Torch-free, so that the simulator (``holowarp.sim``) uses it as the torch-facing operators
do (:class:`holowarp.ops._warp.StepCache` adds torch buffers and views on top).
"""

from __future__ import annotations

import functools

from holowarp.device import init_warp

__all__ = ["LaunchCache"]


class LaunchCache:
    """Recorded Warp launches, one per call site, for loops that launch the same kernels on
    the same arrays again and again (a geometry step, the simulator's substeps).

    A fresh ``wp.launch`` packs every argument (about 15 us on this project's CPU, more
    with many arguments); a recorded one (``record_cmd=True``) replays in about 3 us. The
    simulator's substeps launch a few dozen kernels each, so a multi-body frame makes
    thousands of launches, and the packing was a large share of its time.
    """

    def __init__(self):
        self._launches: dict = {}

    def launch(self, site, kernel, dim, inputs=(), outputs=(), device=None) -> None:
        """``wp.launch(kernel, dim, inputs, outputs, device)``, recorded at the first call of
        ``site`` (any hashable; and again when the kernel or device changes) and replayed
        after: arrays are compared by identity, numbers by value, and only those that differ
        are packed again. Structs and vectors are packed on every call, so that fields the
        caller changed in place (the simulator's surface weights, friction_eps) reach the
        kernel whatever Warp keeps of them. Distinct sites may launch from different threads
        at once (:func:`holowarp.device.run_chunks`)."""
        wp, plain, scalar = _warp_types()
        args = (*inputs, *outputs)
        rec = self._launches.get(site)
        if rec is None or rec[0] is not kernel or rec[1] != device or len(rec[4]) != len(args):
            cmd = wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device, record_cmd=True)
            self._launches[site] = rec = [kernel, device, cmd, dim, list(args)]
        else:
            cmd, old = rec[2], rec[4]
            for i, a in enumerate(args):
                o = old[i]
                if isinstance(a, wp.array):
                    if a is o:
                        continue
                elif type(a) is type(o) and (a == o if isinstance(a, plain) else
                                             isinstance(a, scalar) and a.value == o.value):
                    continue
                cmd.set_param_at_index(i, a)
                old[i] = a
            if rec[3] != dim:
                cmd.set_dim(dim)
                rec[3] = dim
        rec[2].launch()


@functools.lru_cache(maxsize=None)
def _warp_types():
    """``(warp, numbers, Warp scalar base)``, looked up once: the module, and the launch
    arguments :meth:`LaunchCache.launch` compares by value, Python numbers and Warp's scalar
    objects (``wp.float32(x)``, by their ``value``)."""
    wp = init_warp()
    return wp, (int, float, bool), type(wp.float32(0.0)).__mro__[-2]
