"""Shared fixtures: paths to the shared test meshes, a seeded RNG, CPU-only Warp."""

from __future__ import annotations

import os
import zlib
from pathlib import Path

import numpy as np
import pytest

# Tests run Warp on the CPU backend; silence its banner.
os.environ.setdefault("WARP_QUIET", "1")
# One kernel thread unless a test asks for more: results are then those of the recorded
# regression hash, and parallel tests (pytest -n) do not oversubscribe the cores.
os.environ.setdefault("HOLOWARP_THREADS", "1")

REPO = Path(__file__).resolve().parents[1]
SHARED_MESHES = REPO.parent / "shared" / "data" / "meshes"
ASSETS = REPO / "holowarp" / "assets"


@pytest.fixture(scope="module")
def one_torch_thread():
    """Run a module's tests with one torch thread. Small tensors gain nothing from
    intra-op threads, and on a loaded 2-core machine torch's thread pool spins, so one
    thread keeps the runtime predictable."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture
def rng(request):
    """A fresh, reproducible-per-test random generator (seeded from the test's name)."""
    seed = zlib.crc32(request.node.nodeid.encode())
    return np.random.default_rng(seed)


def shared_mesh(name: str) -> Path:
    """Path of a shared test object (``spot``, ``bob``, ``fandisk``); skip if absent."""
    files = {
        "spot": SHARED_MESHES / "spot" / "spot.obj",
        "bob": SHARED_MESHES / "bob" / "bob_tri.obj",
        "fandisk": SHARED_MESHES / "fandisk" / "fandisk.obj",
    }
    p = files[name]
    if not p.is_file() and name == "bob":
        p = ASSETS / "bob" / "bob_tri.obj"
    if not p.is_file():
        pytest.skip(f"test mesh {p} is not available")
    return p
