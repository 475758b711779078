"""A reconstruction's resumable state: a typed :class:`RunState`, its checkpoint file, and
the loss history streamed to ``history.jsonl``.

Layout in the run folder:

- ``checkpoints/state.pt``: :class:`Checkpoint` (the settings, the dataset path, the
  :class:`RunState`, the model and optimiser states), written atomically at every stage
  boundary and every ``checkpoint_every`` iterations. Its size is O(model): the loss history
  is not in it.
- ``history.jsonl``: one JSON object per optimisation step, ``{"stage": ..., "iter" or
  "mesh_iter": ..., <loss terms>}``. The checkpoint records how many lines it covers; a
  resumed run first truncates the file to that many, so the steps it repeats are not logged
  twice.

A resumed run must use the same settings and the same dataset: :func:`check_resume` names
what differs. Only the settings that the finish alone reads (:data:`FINISH_ONLY`) may change.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import time
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import torch

from holowarp.errors import InputError
from holowarp.fileio import atomic_path
from holowarp.stages.geometry import BlockResume

__all__ = [
    "CHECKPOINT_VERSION",
    "STATE_FILE",
    "HISTORY_FILE",
    "Phase",
    "BlockResume",
    "RunState",
    "Checkpoint",
    "CheckpointError",
    "HistoryLog",
    "FINISH_ONLY",
    "check_resume",
    "settings_diff",
]

#: Layout version of ``checkpoints/state.pt``.
CHECKPOINT_VERSION = 2
STATE_FILE = "checkpoints/state.pt"
HISTORY_FILE = "history.jsonl"


class CheckpointError(InputError):
    """A checkpoint cannot be used to resume; the message names the file and why."""


class Phase(str, Enum):
    """Where a run stands: the next thing it will do."""

    STAGE0 = "stage0"
    TET_INIT = "tet_init"
    MAIN = "main"
    CLEANUP = "cleanup"


@dataclass
class RunState:
    """Everything a run has done so far, apart from the model itself.

    Attributes:
        phase: the next phase to run.
        main_iter: the next main-loop iteration.
        done: keys of the finished prunes and mesh blocks (``"prune@1200"``, ``"mesh@1600"``).
        stages: per stage, ``{"seconds": float, "iterations": int}``.
        tets_initial, vertices_initial: size of the initial tet mesh.
        prunes: one report dict per prune (see :func:`holowarp.stages.topology.prune`).
        geometry_blocks: one summary dict per finished mesh block.
        mesh_iter: mesh iterations done over all blocks (t of lam(t)).
        block: the interrupted mesh block, if any.
        stage0: stage 0's summary (``psnr_test``, ``gaussians``, ``iters``).
        elapsed: seconds of work before this checkpoint, over all sessions.
        history_lines: lines of ``history.jsonl`` this state covers.
    """

    phase: Phase = Phase.STAGE0
    main_iter: int = 0
    done: list = field(default_factory=list)
    stages: dict = field(default_factory=dict)
    tets_initial: int | None = None
    vertices_initial: int | None = None
    prunes: list = field(default_factory=list)
    geometry_blocks: list = field(default_factory=list)
    mesh_iter: int = 0
    block: BlockResume | None = None
    stage0: dict | None = None
    elapsed: float = 0.0
    history_lines: int = 0

    def add_time(self, stage: str, seconds: float, iterations: int = 0) -> None:
        s = self.stages.setdefault(stage, {"seconds": 0.0, "iterations": 0})
        s["seconds"] += float(seconds)
        s["iterations"] += int(iterations)

    @contextlib.contextmanager
    def timed(self, stage: str, iterations: int = 0):
        """Add the wall time of the ``with`` body (and ``iterations``) to ``stage``."""
        t0 = time.perf_counter()
        yield
        self.add_time(stage, time.perf_counter() - t0, iterations)

    @property
    def first_prune_done(self) -> bool:
        return any(d.startswith("prune@") for d in self.done)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["phase"] = self.phase.value
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "RunState":
        d = dict(d)
        d["phase"] = Phase(d["phase"])
        if d.get("block") is not None:
            d["block"] = BlockResume(**d["block"])
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})


@dataclass
class Checkpoint:
    """The content of ``checkpoints/state.pt``."""

    config: dict
    dataset_path: str | None
    state: RunState
    model: dict | None = None
    optimizers: dict | None = None

    def save(self, out_dir: str | os.PathLike) -> None:
        payload = {"version": CHECKPOINT_VERSION, "config": self.config, "dataset_path": self.dataset_path,
                   "state": self.state.to_dict(), "model": self.model, "optimizers": self.optimizers}
        with atomic_path(Path(out_dir) / STATE_FILE) as tmp:
            torch.save(payload, tmp)

    @classmethod
    def load(cls, out_dir: str | os.PathLike) -> "Checkpoint | None":
        """The checkpoint of ``out_dir``, or None when it has none."""
        path = Path(out_dir) / STATE_FILE
        if not path.is_file():
            return None
        try:
            d = torch.load(path, map_location="cpu", weights_only=False)
        except Exception as e:  # a truncated file cannot happen (atomic writes), a foreign one can
            raise CheckpointError(f"{path}: unreadable checkpoint ({type(e).__name__}: {e})") from None
        if not isinstance(d, dict) or d.get("version") != CHECKPOINT_VERSION:
            found = d.get("version", 1) if isinstance(d, dict) else "unknown"
            raise CheckpointError(f"{path}: checkpoint layout {found} is not this version's ({CHECKPOINT_VERSION}); "
                                  "start the run again in a new --out folder")
        try:
            state = RunState.from_dict(d["state"])
        except (KeyError, TypeError, ValueError) as e:
            raise CheckpointError(f"{path}: damaged checkpoint state ({type(e).__name__}: {e})") from None
        return cls(config=d["config"], dataset_path=d["dataset_path"], state=state, model=d.get("model"),
                   optimizers=d.get("optimizers"))


def settings_diff(current: dict, saved: dict) -> list[str]:
    """Dotted names of the settings that differ between two ``ReconConfig.to_dict()``s."""
    diff = []

    def walk(a, b, prefix=""):
        if isinstance(a, dict) and isinstance(b, dict):
            for k in set(a) | set(b):
                walk(a.get(k), b.get(k), f"{prefix}{k}.")
        elif a != b and not (isinstance(a, (list, tuple)) and list(a) == list(b or [])):
            diff.append(prefix.rstrip("."))

    walk(current, saved)
    return sorted(diff)


#: Settings sections that only the finish reads (cleanup, the element improvement and its
#: surfel refit, the silhouette polish). A resumed run always redoes the finish from the checkpointed model, so these
#: may differ on ``--resume``: that is how a finished run is finished again with other
#: cleanup or improvement settings (``--resume --no-improve``, say).
FINISH_ONLY = ("cleanup", "improve", "polish")


def check_resume(out_dir, ckpt: Checkpoint | None, config_dict: dict, dataset_path, *, resume: bool) -> None:
    """Refuse to overwrite a run without ``resume``, and to resume one with other settings
    (except the :data:`FINISH_ONLY` ones) or another dataset."""
    if ckpt is None:
        return
    if not resume:
        raise CheckpointError(
            f"{out_dir} already holds a reconstruction (checkpoints/state.pt); pass --resume to continue it "
            "or choose another --out"
        )
    diff = [d for d in settings_diff(config_dict, ckpt.config) if d.split(".")[0] not in FINISH_ONLY]
    if diff:
        raise CheckpointError(f"{out_dir}: --resume with different settings than the checkpoint ({', '.join(diff[:8])})")
    if ckpt.dataset_path != (str(dataset_path) if dataset_path else None):
        raise CheckpointError(f"{out_dir}: --resume with a different dataset than the checkpoint "
                              f"({dataset_path} instead of {ckpt.dataset_path})")


class HistoryLog:
    """Append-only loss history in ``history.jsonl`` (see the module docstring)."""

    def __init__(self, out_dir: str | os.PathLike, *, keep_lines: int = 0):
        self.path = Path(out_dir) / HISTORY_FILE
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.lines = self._truncate(keep_lines)
        self._fh = open(self.path, "a", encoding="utf-8")

    def _truncate(self, keep: int) -> int:
        if not self.path.is_file():
            return 0
        with open(self.path, "rb") as fh:
            kept = fh.readlines()[:keep]
        with open(self.path, "wb") as fh:
            fh.writelines(kept)
        return len(kept)

    def append(self, stage: str, record: dict) -> None:
        self._fh.write(json.dumps({"stage": stage, **record}) + "\n")
        self.lines += 1

    def flush(self) -> int:
        """Flush to disk; returns the number of lines written so far."""
        self._fh.flush()
        return self.lines

    def close(self) -> None:
        self._fh.close()

    def read(self) -> dict:
        """The history by stage: ``{stage: [record, ...]}`` in file order."""
        self.flush()
        out: dict = {}
        with open(self.path, encoding="utf-8") as fh:
            for line in fh:
                rec = json.loads(line)
                out.setdefault(rec.pop("stage"), []).append(rec)
        return out
