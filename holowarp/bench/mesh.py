"""``python -m holowarp.bench mesh [--json] [--device cpu|cuda]``: rasteriser and tet energies.

Times, as medians of forward + backward:

- the triangle rasteriser (``holowarp.ops.rasterize_mesh``) on ``--faces`` boundary
  triangles (an icosphere filling the view) at ``--res``² pixels, with a mask-L1 plus
  normal loss as the geometry stage uses it (method.md §6);
- the tet energies (``holowarp.energies``) on a jittered box of about ``--tets`` tets: the
  weighted bi-harmonic energy, the inversion penalty, the HC-Laplacian energy and the
  eikonal + smoothness losses, one by one and all together.

The issue's targets on the 2-core CPU: rasteriser (20k triangles, 256²) and energies
(200k tets) each under 100 ms. With ``--device cuda`` (1M tets, 512² are the issue's GPU
sizes) the same code runs on the GPU; without one the JSON says so.

Unless ``--no-accuracy``, it also reports the worst finite-difference error of every term
(``max |analytic - FD| / max |FD|`` over all coordinates of a small random problem): float64
central differences of the float64 Warp kernels for the energies, of the float64 torch
reference for the rasteriser, plus float32 differences of the Warp rasteriser itself.

Torch runs single-threaded by default (``--threads``): the Warp CPU kernels are serial
anyway, and on a shared 2-core machine torch's thread pool only adds spin-wait noise.
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import torch

from holowarp.bench import median_ms, peak_rss_mb
from holowarp.device import DeviceError, resolve_device

__all__ = ["main"]


def _sync(device: str):
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _raster_bench(device: str, faces: int, res: int, repeat: int) -> dict:
    import trimesh

    from holowarp.camera import intrinsics_from_fov, look_at
    from holowarp.ops import rasterize_mesh
    from holowarp.ops.mesh_raster import mesh_face_neighbors

    sub = max(0, round(math.log(max(faces, 20) / 20) / math.log(4)))
    m = trimesh.creation.icosphere(subdivisions=sub, radius=0.5)
    V = torch.tensor(m.vertices, dtype=torch.float32, device=device, requires_grad=True)
    F = torch.tensor(m.faces, dtype=torch.int32, device=device)
    viewmat = look_at((0.0, -2.0, 0.3))
    K = intrinsics_from_fov(math.radians(39.3), res, res)
    mask = torch.zeros((res, res), device=device)
    mask[res // 4 : 3 * res // 4, res // 4 : 3 * res // 4] = 1.0
    n_gs = torch.nn.functional.normalize(torch.randn((res, res, 3), device=device), dim=-1)

    def forward():
        out = rasterize_mesh(V, F, viewmat, K, res, res)
        _sync(device)
        return out

    def forward_backward():
        out = rasterize_mesh(V, F, viewmat, K, res, res)
        hit = (out["face_id"] >= 0).float()
        loss = 20.0 * (out["alpha"] - mask).abs().mean() + 0.25 * (hit * (1.0 - (n_gs * out["normal"]).sum(-1))).sum()
        V.grad = None
        loss.backward()
        _sync(device)

    out = forward()
    return {
        "faces": int(F.shape[0]),
        "resolution": res,
        "covered_pixel_fraction": round(float((out["face_id"] >= 0).float().mean()), 3),
        "forward_ms": round(median_ms(forward, repeat=repeat), 2),
        "forward_backward_ms": round(median_ms(forward_backward, repeat=repeat), 2),
        "edge_adjacency_uncached_ms": round(median_ms(lambda: (mesh_face_neighbors(F), _sync(device)), repeat=repeat), 2),
    }


def _energy_bench(device: str, tets: int, repeat: int) -> dict:
    from holowarp.energies import TetEnergies, eikonal_loss, smoothness_loss
    from holowarp.primitives import box_tetmesh

    n = max(1, round((tets / 6) ** (1 / 3)))
    mesh = box_tetmesh((n, n, n), (1.0, 1.0, 1.0))
    rng = np.random.default_rng(0)
    rest = mesh.vertices + rng.uniform(-0.1, 0.1, mesh.vertices.shape) / n
    energies = TetEnergies(mesh, rest, weights="surface", device=device)
    x = torch.tensor(rest + rng.normal(scale=0.05 / n, size=rest.shape), dtype=torch.float32, device=device, requires_grad=True)
    phi = torch.tensor(rng.normal(size=mesh.num_vertices), dtype=torch.float32, device=device, requires_grad=True)
    edges = torch.as_tensor(np.array(mesh.edges()), device=device)
    bf = mesh.boundary_faces()
    energies.hc_topology(bf)  # topology set-up happens once per topology change, not per step

    terms = {
        "biharmonic": lambda: energies.biharmonic(x),
        "inversion_penalty": lambda: energies.inversion_penalty(x, 2.0),
        "hc_laplacian": lambda: energies.hc_laplacian(x, bf, 1.0),
        "eikonal_smooth": lambda: 3.0 * eikonal_loss(phi, edges, x) + 3.0 * smoothness_loss(phi, edges),
    }

    def run(fns):
        def step():
            x.grad = None
            phi.grad = None
            sum(f() for f in fns).backward()
            _sync(device)

        return step

    timings = {k: round(median_ms(run([f]), repeat=repeat), 2) for k, f in terms.items()}
    return {
        "tets": mesh.num_tets,
        "vertices": mesh.num_vertices,
        "edges": int(edges.shape[0]),
        "boundary_faces": int(bf.shape[0]),
        "forward_backward_ms": timings,
        "all_forward_backward_ms": round(median_ms(run(list(terms.values())), repeat=repeat), 2),
        "capture_rest_ms": round(median_ms(lambda: energies.capture_rest(rest), repeat=max(1, repeat // 2)), 2),
    }


# --- accuracy -----------------------------------------------------------------------------


def _fd_rel_err(fn, x: torch.Tensor, eps: float, rows=None) -> float:
    """max |analytic - central FD| / max |FD| over the coordinates of ``rows``."""
    xg = x.detach().clone().requires_grad_(True)
    fn(xg).backward()
    g = xg.grad
    rows = range(x.shape[0]) if rows is None else rows
    fd = torch.zeros_like(g, dtype=torch.float64)
    flat = x.detach().clone()
    with torch.no_grad():
        for i in rows:
            for j in range(x.shape[1] if x.ndim > 1 else 1):
                idx = (i, j) if x.ndim > 1 else (i,)
                old = flat[idx].item()
                flat[idx] = old + eps
                fp = fn(flat).item()
                flat[idx] = old - eps
                fm = fn(flat).item()
                flat[idx] = old
                fd[idx] = (fp - fm) / (2 * eps)
    rows = list(rows)
    return float((g.double()[rows] - fd[rows]).abs().max() / fd[rows].abs().max().clamp_min(1e-300))


def _accuracy() -> dict:
    import trimesh

    from holowarp.camera import intrinsics_from_fov, look_at
    from holowarp.energies import TetEnergies, biharmonic_weights, eikonal_loss, smoothness_loss
    from holowarp.ops import rasterize_mesh, tet_energy
    from holowarp.ops.mesh_raster_ref import rasterize_mesh_ref
    from holowarp.primitives import box_tetmesh

    rng = np.random.default_rng(1)
    mesh = box_tetmesh((3, 3, 3), (1.0, 1.0, 0.8))
    rest = mesh.vertices + rng.normal(scale=0.03, size=mesh.vertices.shape)
    x = torch.tensor(rest + rng.normal(scale=0.06, size=rest.shape))
    x[5] += torch.tensor([0.0, 0.6, -0.7])  # invert some tets for the penalty
    w = biharmonic_weights(mesh.tets, mesh.surface_vertices())
    E = TetEnergies(mesh, rest, weights=w)
    edges = torch.as_tensor(np.array(mesh.edges()))
    phi = torch.tensor(rng.normal(scale=0.3, size=mesh.num_vertices))
    bf = mesh.boundary_faces()
    topo = E.hc_topology(bf)
    Wf = torch.tensor(rng.normal(size=(mesh.num_tets, 3, 3)))
    eps = 1e-6
    errs = {
        "deformation_gradient": _fd_rel_err(lambda z: (E.deformation_gradients(z) * Wf).sum(), x, eps),
        "biharmonic": _fd_rel_err(E.biharmonic, x, eps),
        "inversion_penalty_p2": _fd_rel_err(lambda z: E.inversion_penalty(z, 2.0), x, eps),
        "inversion_penalty_p4": _fd_rel_err(lambda z: E.inversion_penalty(z, 4.0), x, eps),
        "eikonal_phi": _fd_rel_err(lambda p: eikonal_loss(p, edges, x), phi, eps),
        "eikonal_x": _fd_rel_err(lambda z: eikonal_loss(phi, edges, z), x, eps),
        "smoothness_phi": _fd_rel_err(lambda p: smoothness_loss(p, edges), phi, eps),
    }
    for lam in (0.0, 1.0):
        target, normal = tet_energy.hc_targets(x, topo)
        errs[f"hc_laplacian_lam{int(lam)}_targets_held"] = _fd_rel_err(
            lambda z: tet_energy.hc_energy(z, topo, target, normal, lam), x, eps
        )

    m = trimesh.creation.icosphere(subdivisions=1, radius=0.5)
    V = m.vertices * (1.0 + 0.15 * rng.uniform(-1, 1, size=(len(m.vertices), 1)))
    F = torch.as_tensor(np.array(m.faces, dtype=np.int32))
    res = 24
    vm = look_at((0.4, -2.5, 0.8))
    K = intrinsics_from_fov(math.radians(39.3), res, res)
    K[0, 2] += 0.21
    K[1, 2] -= 0.13
    wa = torch.tensor(rng.normal(size=(res, res)))
    wn = torch.tensor(rng.normal(size=(res, res, 3)))
    v64 = torch.tensor(V)
    errs["raster_alpha_ref_float64"] = _fd_rel_err(lambda z: (rasterize_mesh_ref(z, F, vm, K, res, res)["alpha"] * wa).sum(), v64, 1e-7)
    errs["raster_normal_ref_float64"] = _fd_rel_err(lambda z: (rasterize_mesh_ref(z, F, vm, K, res, res)["normal"] * wn).sum(), v64, 1e-7)
    v32 = torch.tensor(V, dtype=torch.float32)
    errs["raster_alpha_warp_float32"] = _fd_rel_err(
        lambda z: (rasterize_mesh(z, F, vm, K, res, res)["alpha"].double() * wa).sum(), v32, 1e-4
    )
    # normal is piecewise constant per face: skip coordinates whose step changes a face id
    vn = v32.clone().requires_grad_(True)
    (rasterize_mesh(vn, F, vm, K, res, res)["normal"].double() * wn).sum().backward()
    fdn = torch.zeros_like(vn.grad, dtype=torch.float64)
    keep = torch.ones_like(fdn, dtype=torch.bool)
    with torch.no_grad():
        for i in range(V.shape[0]):
            for j in range(3):
                a, b = v32.clone(), v32.clone()
                a[i, j] += 1e-3
                b[i, j] -= 1e-3
                oa, ob = rasterize_mesh(a, F, vm, K, res, res), rasterize_mesh(b, F, vm, K, res, res)
                keep[i, j] = torch.equal(oa["face_id"], ob["face_id"])
                fdn[i, j] = ((oa["normal"].double() - ob["normal"].double()) * wn).sum() / 2e-3
    errs["raster_normal_warp_float32_same_face_ids"] = float(
        (vn.grad.double() - fdn)[keep].abs().max() / fdn[keep].abs().max()
    )
    # the Warp gradient against the float64 reference's autograd gradient
    vw = v32.clone().requires_grad_(True)
    vr = v64.clone().requires_grad_(True)
    ow, orf = rasterize_mesh(vw, F, vm, K, res, res), rasterize_mesh_ref(vr, F, vm, K, res, res)
    ((ow["alpha"].double() * wa).sum() + (ow["normal"].double() * wn).sum()).backward()
    ((orf["alpha"] * wa).sum() + (orf["normal"] * wn).sum()).backward()
    errs["raster_warp_vs_ref_gradient"] = float((vw.grad.double() - vr.grad).abs().max() / vr.grad.abs().max())
    return {k: float(f"{v:.2e}") for k, v in errs.items()}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m holowarp.bench mesh")
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    p.add_argument("--faces", type=int, default=20_000, help="approximate boundary triangles for the rasteriser")
    p.add_argument("--res", type=int, default=256, help="image side in pixels")
    p.add_argument("--tets", type=int, default=200_000, help="approximate tets for the energies")
    p.add_argument("--repeat", type=int, default=7)
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads (0: torch's default)")
    p.add_argument("--no-accuracy", action="store_true", help="skip the finite-difference accuracy section")
    p.add_argument("--json", action="store_true", help="print JSON only")
    args = p.parse_args(argv)

    try:
        device = resolve_device(args.device)
    except DeviceError as e:
        p.error(str(e))
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    out = {
        "benchmark": "mesh",
        "device": device,
        "torch_threads": torch.get_num_threads(),
        "rasterizer": _raster_bench(device, args.faces, args.res, args.repeat),
        "energies": _energy_bench(device, args.tets, args.repeat),
    }
    out["targets_ms"] = {"rasterizer_forward_backward": 100.0, "energies_all_forward_backward": 100.0}
    out["meets_targets"] = {
        "rasterizer": out["rasterizer"]["forward_backward_ms"] < 100.0,
        "energies": out["energies"]["all_forward_backward_ms"] < 100.0,
    }
    if device == "cpu":
        try:
            resolve_device("cuda")
            out["cuda"] = "available: rerun with --device cuda --tets 1000000 --res 512"
        except DeviceError:
            out["cuda"] = "no CUDA GPU on this machine; CUDA figures not measured"
    if not args.no_accuracy:
        out["fd_worst_relative_error"] = _accuracy()
    out["peak_rss_mb"] = round(peak_rss_mb(), 1)

    if args.json:
        print(json.dumps(out, indent=2))
    else:
        r, e = out["rasterizer"], out["energies"]
        print(f"rasterizer: {r['faces']} faces at {r['resolution']}^2 on {device}")
        print(f"  forward {r['forward_ms']} ms, forward+backward {r['forward_backward_ms']} ms")
        print(f"energies: {e['tets']} tets, {e['edges']} edges on {device}")
        for k, v in e["forward_backward_ms"].items():
            print(f"  {k:20s} {v} ms")
        print(f"  all together        {e['all_forward_backward_ms']} ms")
        if "fd_worst_relative_error" in out:
            print("worst FD relative error:")
            for k, v in out["fd_worst_relative_error"].items():
                print(f"  {k:40s} {v:.2e}")
        print(f"peak RSS {out['peak_rss_mb']} MiB")
    return 0
