"""The pipeline benchmark's bookkeeping (issue 17): the rasteriser alone is timed on the views
the timed iterations drew, and the overhead factor is their total over its total."""

from __future__ import annotations

import types

import pytest
import torch

import holowarp.bench.pipeline as bench


def test_phase_times_the_rasteriser_on_the_views_of_the_timed_steps(monkeypatch):
    # A simulated clock: step i costs its view's rasteriser (1, 2 or 3 ms) plus 2 ms of other
    # work. A factor taken from one view alone would be 3, 2 or 1.67; the timed views give 2.
    now = [0.0]
    monkeypatch.setattr(bench, "time", types.SimpleNamespace(perf_counter=lambda: now[0]))
    cost = lambda i: 1e-3 * (1 + i % 3)  # noqa: E731
    calls = []

    def step(i):
        calls.append(("step", i))
        now[0] += cost(i) + 2e-3

    def raster(i):
        calls.append(("raster", i))
        now[0] += cost(i)

    rec = bench._phase("demo", step, 6, 2, raster, torch.device("cpu"), warmup=2)
    timed = [c for i in range(2, 8) for c in (("step", i), ("raster", i))]
    # Warm-up steps and one warm-up raster, then each timed step followed by its view's
    # rasteriser (in turns, so both see the machine in the same state), then the probed steps.
    assert calls == [("step", 0), ("step", 1), ("raster", 0), *timed, ("step", 8), ("step", 9)]
    assert rec["overhead_factor"] == pytest.approx(24 / 12, abs=0.01)
    assert rec["raster_ms"] == pytest.approx(2.0) and rec["ms_per_iter"] == pytest.approx(4.0)


def test_probe_counts_host_data_as_uploads_but_not_warp_memory_wrapped_in_place():
    import numpy as np
    import warp as wp

    from holowarp.bench.probe import Probe

    rng = np.random.default_rng()
    host = rng.normal(size=(7, 3)).astype(np.float32)
    warp_cpu = wp.array(host, dtype=wp.vec3, device="cpu")
    with Probe("cpu") as probe:
        with probe.region():
            torch.tensor(host)  # uploads: host data, three ways
            torch.as_tensor(host)
            torch.from_numpy(host)
            torch.as_tensor(torch.ones(3))  # not an upload: already a tensor
            wrapped = wp.to_torch(warp_cpu)  # not an upload: Warp's memory, wrapped in place
    assert probe.summary()["uploads_per_iter"] == 3
    np.testing.assert_array_equal(wrapped.numpy(), host)


def test_probe_times_replayed_recorded_launches_like_fresh_ones():
    # The geometry step and the simulator replay recorded launches (LaunchCache) instead of
    # calling wp.launch; a probe that missed them counted their kernels as host time.
    import numpy as np
    import warp as wp

    from holowarp.bench.probe import Probe
    from holowarp.kernels import tet_energy as K
    from holowarp.ops.launches import LaunchCache

    rng = np.random.default_rng()
    x = rng.normal(size=(9, 3)).astype(np.float32)
    tets = np.stack([rng.permutation(9)[:4] for _ in range(5)]).astype(np.int32)
    args = [wp.array(x, dtype=wp.vec3, device="cpu"), wp.array(tets, dtype=wp.vec4i, device="cpu")]
    vol = wp.zeros(5, dtype=wp.float32, device="cpu")
    kernel = K.signed_volume_kernel.get_overload(K.signed_volume_kernel.infer_argument_types([*args, vol]))
    cache = LaunchCache()
    with Probe("cpu") as probe:
        with probe.region():
            for _ in range(3):  # recorded at the first call, replayed after
                cache.launch("vol", kernel, 5, args, [vol], "cpu")
    s = probe.summary()
    assert s["launches_per_iter"] == 3
    assert list(s["top_kernels_ms"]) == [kernel.key]
    a, b, c, d = (x[tets[:, k]] for k in range(4))
    np.testing.assert_allclose(vol.numpy(), np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a)) / 6, rtol=1e-5, atol=1e-6)
    assert wp.Launch.launch.__qualname__ == "Launch.launch"  # put back on exit
