"""Progress bars and status lines, one convention for every command.

A long job shows a tqdm bar (ETA, current losses) and prints short status lines. Both are
controlled by one flag, ``progress``: ``False`` (the commands' ``--quiet``) silences them.
Bars additionally turn themselves off when stderr is not a terminal (a log file, CI, a pipe),
where tqdm's cursor codes would fill the file with hundreds of redraws; status lines are
then printed plainly, one per event.
"""

from __future__ import annotations

import logging
import math
import sys

__all__ = ["bars_enabled", "bar", "say", "Bars", "LossBuffer", "LOG_EVERY"]

#: Optimisation steps between host reads of the loss terms (:class:`LossBuffer`).
LOG_EVERY = 10

log = logging.getLogger("holowarp")


def _interactive() -> bool:
    try:
        if sys.stderr.isatty():
            return True
    except (AttributeError, ValueError):  # replaced or closed stderr
        return False
    return "ipykernel" in sys.modules  # notebooks render tqdm's widgets themselves


def bars_enabled(progress: bool) -> bool:
    """Whether bars are drawn: ``progress`` is on and stderr is a terminal (or a notebook)."""
    return bool(progress) and _interactive()


def bar(total: int | None, *, desc: str, unit: str = "it", initial: int = 0, progress: bool = True):
    """A tqdm bar over ``total`` units (disabled per :func:`bars_enabled`)."""
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=initial, desc=desc, unit=unit, dynamic_ncols=True,
                disable=not bars_enabled(progress))


def say(message: str, progress: bool = True) -> None:
    """Print a status line to stderr (without breaking a live bar) unless ``progress`` is off;
    always log it."""
    log.info(message)
    if not progress:
        return
    if bars_enabled(progress):
        from tqdm.auto import tqdm

        tqdm.write(message, file=sys.stderr)
    else:
        print(message, file=sys.stderr, flush=True)


class Bars:
    """Named bars, one per stage, created on first use and closed explicitly."""

    def __init__(self, progress: bool):
        self.progress = bool(progress)
        self._bars: dict = {}

    def get(self, name: str, total: int, initial: int = 0):
        """The bar called ``name`` (created with ``total`` and ``initial`` the first time);
        ``None`` when bars are off."""
        if not bars_enabled(self.progress):
            return None
        if name not in self._bars:
            self._bars[name] = bar(total, desc=name, initial=initial, progress=self.progress)
        return self._bars[name]

    def advance(self, name: str, total: int, done: int, **postfix) -> None:
        """Count one unit on bar ``name`` (created with ``total`` and ``done`` units already
        done), showing ``postfix`` (the previous one stays when none is given)."""
        b = self.get(name, total, done)
        if b is not None:
            b.update(1)
            if postfix:
                b.set_postfix(**postfix, refresh=False)

    def close(self, *names: str) -> None:
        """Close the named bars (all of them when no name is given)."""
        for k in names or list(self._bars):
            b = self._bars.pop(k, None)
            if b is not None:
                b.close()


class LossBuffer:
    """Loss terms left where they were computed and read on the host every ``every`` steps.

    Reading a loss with ``float()`` after every step is a device sync on CUDA (the host
    waits for the step's kernels to finish before queueing the next). Steps hand their
    terms here as 0-dim tensors instead; every ``every`` steps all pending values come back
    in one transfer, each step's record goes to ``sink(stage, record)`` (so the history
    still has every step), and a non-finite ``loss`` raises
    :class:`holowarp.errors.RunError` naming the step. Call :meth:`flush` before a
    checkpoint and at the end of a phase.
    """

    def __init__(self, sink, every: int = LOG_EVERY):
        self.sink, self.every = sink, max(1, int(every))
        self._pending: list[tuple[str, dict, dict]] = []

    def add(self, stage: str, head: dict, terms: dict) -> list[tuple[str, dict]]:
        """Queue one step: ``head`` holds host values (iteration numbers), ``terms`` maps
        names to 0-dim tensors or floats. Returns what a flush wrote (usually nothing)."""
        self._pending.append((stage, dict(head), dict(terms)))
        return self.flush() if len(self._pending) >= self.every else []

    def flush(self) -> list[tuple[str, dict]]:
        """Read every pending value (one host transfer), write the records; returns them."""
        import torch

        from holowarp.errors import RunError

        if not self._pending:
            return []
        tensors = [v.detach().reshape(()).double() for _, _, t in self._pending for v in t.values()
                   if isinstance(v, torch.Tensor)]
        values = iter(torch.stack(tensors).tolist() if tensors else [])
        out = []
        for stage, head, terms in self._pending:
            out.append((stage, {**head, **{k: next(values) if isinstance(v, torch.Tensor) else v
                                           for k, v in terms.items()}}))
        self._pending = []
        for stage, rec in out:
            self.sink(stage, rec)
        for stage, rec in out:
            if not math.isfinite(rec.get("loss", 0.0)):
                raise RunError(f"{stage} step {rec}: non-finite loss; the optimisation diverged")
        return out
