"""Checks that fail fast, before any work of a reconstruction (numbers in
:class:`holowarp.config.PreflightConfig`): enough training views, masks that are neither
empty nor the whole frame, and a visual hull of the masks that spans a volume."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from holowarp.carve import inside_hull, look_region
from holowarp.config import PreflightConfig
from holowarp.errors import InputError
from holowarp.progress import say
from holowarp.stages.tet_init import HullError, scaled_hull

__all__ = ["ReconstructionError", "preflight", "prepare_dataset"]


class ReconstructionError(InputError):
    """The reconstruction cannot start or continue; the message says why."""


def preflight(dataset, config: PreflightConfig = PreflightConfig(), *, device: str = "cpu") -> None:
    """Run the checks on ``dataset``.

    Raises:
        ReconstructionError: naming the problem (and the views).
    """
    n = dataset.num_views
    ntrain = len(dataset.train_idx)
    if n < config.min_views or ntrain < config.min_views:
        raise ReconstructionError(
            f"dataset {dataset.name}: {n} views ({ntrain} for training); at least {config.min_views} training views "
            "are needed"
        )
    flat = dataset.masks.reshape(n, -1)
    empty = np.flatnonzero(flat.max(axis=1) < 0.5)
    if len(empty):
        raise ReconstructionError(f"dataset {dataset.name}: the masks of views {empty[:10].tolist()} are empty")
    full = np.flatnonzero(flat.mean(axis=1) > config.full_mask_fraction)
    if len(full):
        raise ReconstructionError(
            f"dataset {dataset.name}: the masks of views {full[:10].tolist()} cover the whole frame; "
            "the object must be seen against background"
        )
    _check_visual_hull(dataset, config.hull_grid, device)


def _check_visual_hull(dataset, grid: int, device: str) -> None:
    """Carve a coarse grid over the region the training cameras look at; fail if the carved
    set cannot span a 3D hull (too few or inconsistent views).

    The grid spans the nearest camera's distance on each side, so a thin object (a plate a
    few percent of its size thick) can fall between the nodes of ``grid``: the carve is
    retried at 2x and 4x the resolution before the views are called inconsistent.
    """
    views = dataset.train_idx
    focus, r = look_region(dataset.viewmats[views])
    for level in (grid, 2 * grid, 4 * grid):
        g = np.linspace(-r, r, level)
        pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3) + focus
        inside = inside_hull(dataset, pts, views, device=device)
        try:
            scaled_hull(pts[inside])
            return
        except HullError as e:
            error = e
    raise ReconstructionError(
        f"dataset {dataset.name}: the masks' visual hull degenerates ({error}); "
        "the views do not agree on a 3D object (too few views, wrong poses or masks?)"
    ) from None


def prepare_dataset(dataset_path, out_dir, config, *, device: str = "cpu", progress: bool = True,
                    resuming: bool = False):
    """The dataset a reconstruction runs on, loaded at ``config.resolution`` and checked by
    :func:`preflight`: ``dataset_path``, or, when it is None, the built-in default object
    synthesised into ``out_dir/data``. Returns ``(dataset, data_dir)``."""
    from holowarp.data import load_dataset

    if dataset_path is None:
        from holowarp.synthesis import default_dataset

        data_dir = default_dataset(Path(out_dir) / "data", res=config.resolution, device=device, progress=progress)
    elif not Path(dataset_path).exists():
        raise ReconstructionError(f"dataset {dataset_path}: no such folder")
    else:
        data_dir = Path(dataset_path)
    dataset = load_dataset(data_dir, res=config.resolution, test_every=config.test_every)
    preflight(dataset, config.preflight, device=device)
    say(f"reconstructing {dataset.name}: {len(dataset.train_idx)} training / {len(dataset.test_idx)} test views at "
        f"{dataset.width}x{dataset.height}, preset {config.preset}, device {device}" + (", resuming" if resuming else ""),
        progress)
    return dataset, data_dir
