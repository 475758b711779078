"""fTetWild made a function of the seed (:mod:`holowarp.repeatable`).

Each case runs in a fresh interpreter: what the library can do depends on what the process
loaded before it (pytetwild's extension binds to ``std::random_device`` once, when it loads).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

_SCRIPT = r"""
import hashlib, json, sys
import numpy as np, trimesh
if sys.argv[2] == "pytetwild-first":
    import pytetwild  # noqa: F401  (binds the extension to libstdc++'s own device)
from holowarp import repeatable
from holowarp.tetmesh import tetrahedralize_surface

s = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
s.vertices[:, 0] *= 1.3
if sys.argv[2] == "initial":  # the tet initialisation of a run, which passes the run's seed on
    from holowarp.config import TetInitConfig
    from holowarp.stages.tet_init import initial_tetmesh
    m = initial_tetmesh(s.vertices, config=TetInitConfig(edge_length_fac=0.12), seed=int(sys.argv[1]))
else:
    m = tetrahedralize_surface(s.vertices, s.faces, edge_length_fac=0.12, seed=int(sys.argv[1]))
h = hashlib.sha256(np.asarray(m.vertices, "<f8").tobytes() + np.asarray(m.tets, "<i8").tobytes()).hexdigest()
print(json.dumps({"hash": h, "tets": m.num_tets, **repeatable.status()}))
"""


def _tetrahedralise(seed: int, *, env: dict | None = None, mode: str = "plain") -> dict:
    r = subprocess.run([sys.executable, "-c", _SCRIPT, str(seed), mode], capture_output=True, text=True, timeout=300,
                       env={**os.environ, **(env or {})})
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    out["stderr"] = r.stderr
    return out


def test_one_seed_gives_one_mesh_across_processes(tmp_path):
    cache = {"HOLOWARP_CACHE": str(tmp_path / "cache")}  # a clean cache: the library is built here
    a = _tetrahedralise(7, env=cache)
    if not a["repeatable"]:
        pytest.skip(f"no seeded random device on this machine: {a['reason']}")
    b = _tetrahedralise(7, env=cache)
    assert a["tets"] > 100 and a["hash"] == b["hash"]
    assert list((tmp_path / "cache" / "native").glob("seeded_random_device-*.so"))
    assert "not repeatable" not in a["stderr"] + b["stderr"]


def test_the_runs_seed_reaches_fTetWild_through_the_tet_initialisation(tmp_path):
    cache = {"HOLOWARP_CACHE": str(tmp_path / "cache")}
    a = _tetrahedralise(7, env=cache, mode="initial")
    if not a["repeatable"]:
        pytest.skip(f"no seeded random device on this machine: {a['reason']}")
    b, c = _tetrahedralise(7, env=cache, mode="initial"), _tetrahedralise(8, env=cache, mode="initial")
    assert a["hash"] == b["hash"] and a["hash"] != c["hash"] and min(a["tets"], c["tets"]) > 100


@pytest.mark.parametrize("env, mode, why", [
    ({"HOLOWARP_NO_NATIVE": "1"}, "plain", "HOLOWARP_NO_NATIVE"),
    ({"CXX": "/bin/false", "HOLOWARP_CACHE": "{tmp}"}, "plain", "could not build"),
    ({"HOLOWARP_CACHE": "/proc/holowarp-cache"}, "plain", "cannot write"),
    ({}, "pytetwild-first", "loaded before"),
])
def test_where_it_cannot_seed_fTetWild_still_meshes_and_says_why_once(tmp_path, env, mode, why):
    env = {k: v.replace("{tmp}", str(tmp_path)) for k, v in env.items()}
    if env.get("CXX") == "/bin/false" and not os.path.exists("/bin/false"):
        pytest.skip("no /bin/false to stand in for a broken compiler")
    out = _tetrahedralise(3, env=env, mode=mode)
    assert out["tets"] > 100 and out["repeatable"] is False and why in out["reason"], out
    assert out["stderr"].count("not repeatable") == 1, out["stderr"]
