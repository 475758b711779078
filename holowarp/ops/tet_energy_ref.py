"""Dense plain-PyTorch references of the tetrahedral energies (tests only).

Independent of the Warp path: the face adjacency comes from a Python dict of sorted face
triples, the Laplacians are dense matrices, and gradients come from torch autograd. Any
float dtype works, so the tests take float64 finite differences of these. Dense matrices
cost (M x M): keep meshes small.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = [
    "face_adjacency_ref",
    "deformation_gradients_ref",
    "biharmonic_ref",
    "inversion_penalty_ref",
    "hc_targets_ref",
    "hc_energy_ref",
    "eikonal_ref",
    "smoothness_ref",
]


def _long(a, device=None) -> torch.Tensor:
    if isinstance(a, torch.Tensor):
        return a.to(device=device, dtype=torch.long)
    return torch.as_tensor(np.array(a, dtype=np.int64), device=device)


def face_adjacency_ref(tets) -> torch.Tensor:
    """(M, 4) long: tet across the face opposite local vertex k, -1 if none (or non-manifold)."""
    tets = _long(tets).tolist()
    owners: dict[tuple, list] = {}
    for e, t in enumerate(tets):
        for k in range(4):
            face = tuple(sorted(t[:k] + t[k + 1 :]))
            owners.setdefault(face, []).append((e, k))
    adj = [[-1] * 4 for _ in tets]
    for users in owners.values():
        if len(users) == 2:
            (e0, k0), (e1, k1) = users
            adj[e0][k0] = e1
            adj[e1][k1] = e0
    return torch.tensor(adj, dtype=torch.long).reshape(-1, 4)


def _ds(x, tets):
    tets = _long(tets, x.device)
    x0 = x[tets[:, 0]]
    return torch.stack([x[tets[:, 1]] - x0, x[tets[:, 2]] - x0, x[tets[:, 3]] - x0], dim=2)  # columns


def deformation_gradients_ref(x, tets, rest_x) -> torch.Tensor:
    """``F = Ds Dm^-1`` (M, 3, 3), with ``Dm`` from ``rest_x``."""
    return _ds(x, tets) @ torch.linalg.inv(_ds(rest_x.to(x.dtype), tets))


def _laplacian(adj, dtype, device):
    adj = _long(adj)
    M = adj.shape[0]
    L = torch.zeros((M, M), dtype=dtype, device=device)
    for e in range(M):
        for n in adj[e].tolist():
            if n >= 0:
                L[e, e] += 1
                L[e, n] -= 1
    return L


def biharmonic_ref(x, tets, rest_x, weights=None) -> torch.Tensor:
    """``sum_e w_e ||(L F)_e||_F^2`` with the dense face-adjacency Laplacian."""
    F = deformation_gradients_ref(x, tets, rest_x)
    L = _laplacian(face_adjacency_ref(tets), x.dtype, x.device)
    G = torch.einsum("ab,bij->aij", L, F)
    w = torch.ones(F.shape[0], dtype=x.dtype, device=x.device) if weights is None else weights.to(x.dtype)
    return (w * (G * G).sum(dim=(1, 2))).sum()


def inversion_penalty_ref(x, tets, rest_x, p: float) -> torch.Tensor:
    """``sum_e max(-det F_e, 0)^p``."""
    F = deformation_gradients_ref(x, tets, rest_x)
    return torch.relu(-torch.linalg.det(F)).pow(p).sum()


def _umbrella(faces, N, dtype, device):
    faces = _long(faces)
    A = torch.zeros((N, N), dtype=dtype, device=device)
    for f in faces.tolist():
        for k in range(3):
            a, b = f[k], f[(k + 1) % 3]
            A[a, b] = 1
            A[b, a] = 1
    deg = A.sum(1, keepdim=True)
    return A / deg.clamp_min(1), deg.squeeze(1) > 0


def hc_targets_ref(x, faces, x_orig=None, alpha: float = 0.0, beta: float = 0.5):
    """HC targets and outward area-weighted unit normals for every vertex (N, 3) each,
    plus the (N,) bool mask of surface vertices. Differentiable (no stop-gradient here)."""
    N = x.shape[0]
    W, surf = _umbrella(faces, N, x.dtype, x.device)
    o = x if x_orig is None else x_orig.to(x.dtype)
    p = W @ x
    b = p - (alpha * o + (1 - alpha) * x)
    target = p - (beta * b + (1 - beta) * (W @ b))
    faces = _long(faces, x.device)
    m = torch.cross(x[faces[:, 1]] - x[faces[:, 0]], x[faces[:, 2]] - x[faces[:, 0]], dim=1)
    n = torch.zeros_like(x).index_add(0, faces.reshape(-1), m.repeat_interleave(3, dim=0))
    n = n / n.norm(dim=1, keepdim=True).clamp_min(1e-300)
    return target, n, surf


def hc_energy_ref(x, faces, lam_cond: float, *, target=None, normal=None, x_orig=None, alpha=0.0, beta=0.5):
    """``sum_S ||d_t||^2 + lam_cond min(d_n,0)^2 + max(d_n,0)^2``, ``d = target - x``.

    ``target``/``normal`` (N, 3) are taken as given constants when supplied (the Warp op's
    stop-gradient convention); otherwise computed from ``x`` and detached.
    """
    t, n, surf = hc_targets_ref(x.detach(), faces, x_orig=x_orig, alpha=alpha, beta=beta)
    target = t if target is None else target
    normal = n if normal is None else normal
    d = (target.detach() - x)[surf]
    nn = normal.detach()[surf]
    dn = (d * nn).sum(1)
    dt = d - dn[:, None] * nn
    return (dt * dt).sum() + lam_cond * torch.clamp(dn, max=0).pow(2).sum() + torch.clamp(dn, min=0).pow(2).sum()


def eikonal_ref(phi, edges, x) -> torch.Tensor:
    edges = _long(edges, phi.device)
    l = (x[edges[:, 0]] - x[edges[:, 1]]).norm(dim=1)
    return ((phi[edges[:, 0]] - phi[edges[:, 1]]).abs() / l - 1).pow(2).mean()


def smoothness_ref(phi, edges) -> torch.Tensor:
    edges = _long(edges, phi.device)
    return (phi[edges[:, 0]] - phi[edges[:, 1]]).pow(2).mean()
