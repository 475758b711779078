"""Dense plain-PyTorch reference of ``holowarp.ops.rasterize_mesh`` (tests only).

Same definitions as the Warp rasteriser (see ``holowarp.kernels.mesh_raster``), written the
slow, obvious way: every pixel against every face, the edge adjacency from a Python dict,
and torch autograd for the gradients. It runs in any float dtype, so the tests take float64
finite differences of it. Cost is pixels x faces: keep images and meshes small.
"""

from __future__ import annotations

import torch

__all__ = ["rasterize_mesh_ref"]

_AA_BAND_PX = 0.5


def _cross2(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _edge_neighbors(faces) -> list[list[int]]:
    owners: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for f, tri in enumerate(faces.tolist()):
        for k in range(3):
            a, b = tri[k], tri[(k + 1) % 3]
            owners.setdefault((min(a, b), max(a, b)), []).append((f, k))
    nbr = [[-1, -1, -1] for _ in range(len(faces))]
    for users in owners.values():
        if len(users) == 2:
            (f0, k0), (f1, k1) = users
            nbr[f0][k0] = f1
            nbr[f1][k1] = f0
    return nbr


def _antialias(covered, contour, verts, xs, ys, P, H: int, W: int, dt, dev):
    """Coverage (HW,) with the analytic silhouette band at pixels whose coverage differs from
    a 4-neighbour's (the reference of the Warp ``antialias_kernel``)."""
    alpha = covered.to(dt).clone()
    cf, ck = torch.nonzero(contour, as_tuple=True)
    if cf.numel():
        A = verts[cf, ck]  # [C, 2]
        B = verts[cf, (ck + 1) % 3]
        E = B - A
        cov2 = covered.reshape(H, W)
        for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            qx, qy = xs + dx, ys + dy
            valid = (qx >= 0) & (qx < W) & (qy >= 0) & (qy < H)
            qcov = cov2[qy.clamp(0, H - 1), qx.clamp(0, W - 1)]
            diff = (valid & (qcov != cov2)).reshape(-1)
            idx = torch.nonzero(diff).squeeze(1)
            if idx.numel() == 0:
                continue
            p = P[idx]  # [n, 2]
            d = torch.tensor([dx, dy], dtype=dt, device=dev)
            den = _cross2(d[None], E)  # [C]
            ap = A[None] - p[:, None]  # [n, C, 2]
            safe = torch.where(den == 0, torch.ones_like(den), den)
            s = _cross2(ap, E[None]) / safe
            t = _cross2(ap, d[None, None]) / safe
            hit = (den != 0) & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1)
            inside_p = covered[idx]
            # nearest crossing to the uncovered centre
            key = torch.where(inside_p[:, None], s, -s).detach()
            key = torch.where(hit, key, torch.full_like(key, -10.0))
            kbest, j = key.max(dim=1)
            found = kbest > -5
            sd = -_cross2(E[j], p - A[j]) / E[j].norm(dim=1)
            v = (_AA_BAND_PX + sd).clamp(0.0, 1.0)
            cur = alpha[idx]
            newv = torch.where(inside_p, torch.minimum(cur, v), torch.maximum(cur, v))
            alpha = alpha.index_put((idx,), torch.where(found, newv, cur))
    return alpha


def rasterize_mesh_ref(vertices, faces, viewmat, K, width: int, height: int, *, near: float = 1.0e-3) -> dict:
    """Dense reference rasteriser.

    Args:
        vertices: (V, 3) float tensor (any float dtype; autograd supported).
        faces: (F, 3) integer tensor.
        viewmat: (4, 4) world-to-camera; K: (3, 3) intrinsics (tensors or arrays).
        width, height: image size.

    Returns:
        dict with ``alpha`` (H, W), ``normal`` (H, W, 3), ``depth`` (H, W), ``face_id``
        (H, W) int64, in ``vertices``' dtype.
    """
    dt, dev = vertices.dtype, vertices.device
    viewmat = torch.as_tensor(viewmat, dtype=dt, device=dev)
    K = torch.as_tensor(K, dtype=dt, device=dev)
    faces = torch.as_tensor(faces, device=dev).long()
    F = faces.shape[0]
    H, W = int(height), int(width)

    pc = vertices @ viewmat[:3, :3].T + viewmat[:3, 3]
    q = pc @ K.T
    uv = q[:, :2] / q[:, 2:3]
    z = pc[:, 2]

    a, b, c = uv[faces[:, 0]], uv[faces[:, 1]], uv[faces[:, 2]]  # [F, 2]
    area2 = _cross2(b - a, c - a)
    zf = z[faces]  # [F, 3]
    front = (zf > near).all(dim=1) & (area2 < -1e-12)

    x0 = vertices[faces[:, 0]]
    m = torch.cross(vertices[faces[:, 1]] - x0, vertices[faces[:, 2]] - x0, dim=1)
    fnormal = m / m.norm(dim=1, keepdim=True).clamp_min(1e-300)

    nbr = torch.tensor(_edge_neighbors(faces), dtype=torch.long, device=dev).reshape(F, 3)
    front_pad = torch.cat([front, torch.zeros(1, dtype=torch.bool, device=dev)])
    contour = front[:, None] & ~front_pad[nbr]  # -1 indexes the padded False

    ys, xs = torch.meshgrid(torch.arange(H, device=dev), torch.arange(W, device=dev), indexing="ij")
    P = torch.stack([xs, ys], -1).reshape(-1, 2).to(dt) + 0.5  # [HW, 2]

    verts = torch.stack([a, b, c], 1)  # [F, 3, 2]
    ea = verts  # edge k starts at vertex k
    eb = verts.roll(-1, dims=1)  # and ends at vertex k + 1
    # edge functions, >= 0 inside front faces
    cfun = -_cross2((eb - ea)[None], P[:, None, None, :] - ea[None])  # [HW, F, 3]
    inside = (cfun >= 0).all(-1) & front[None]
    izf = torch.where(front[:, None], 1.0 / zf, torch.zeros_like(zf))
    iz = (cfun[..., 1] * izf[None, :, 0] + cfun[..., 2] * izf[None, :, 1] + cfun[..., 0] * izf[None, :, 2]) / (-area2)[None]
    iz = torch.where(inside, iz, torch.full_like(iz, -1.0))
    best_iz, best_f = iz.max(dim=1)
    covered = best_iz > 0
    face_id = torch.where(covered, best_f, torch.full_like(best_f, -1))
    depth = torch.where(covered, 1.0 / best_iz.clamp_min(1e-300), torch.zeros_like(best_iz))
    normal = torch.where(covered[:, None], fnormal[best_f.clamp_min(0)], torch.zeros(1, 3, dtype=dt, device=dev))

    alpha = _antialias(covered, contour, verts, xs, ys, P, H, W, dt, dev)
    return {
        "alpha": alpha.reshape(H, W),
        "normal": normal.reshape(H, W, 3),
        "depth": depth.reshape(H, W),
        "face_id": face_id.reshape(H, W),
    }
