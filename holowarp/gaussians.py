"""The Gaussian-surfel model of stage 0 (method.md §3) and its 3DGS-layout PLY files.

:class:`GaussianModel` holds the learnable surfel parameters with their activations

- ``means`` [N, 3] (metres, world),
- ``log_scales`` [N, 2] (scales = exp, along the rotation's first two axes),
- ``quats`` [N, 4] (wxyz, normalised where used; the surfel normal is the third axis),
- ``opacity_logits`` [N] (opacity = sigmoid),
- ``sh_dc`` [N, 3] (degree-0 spherical harmonics; colour = 0.5 + C0 * sh_dc, clamped >= 0,
  the 3DGS convention, so ``f_dc`` in the PLY means what 3DGS viewers expect),

an Adam optimiser over them, and the adaptive density control of 3DGS/2DGS (clone, split,
prune, opacity reset) that keeps the optimiser's moments aligned with the parameters.

PLY layout (3DGS viewers): ``x y z nx ny nz f_dc_0..2 opacity scale_0 scale_1 scale_2
rot_0..3`` as little-endian float32; ``opacity`` is a logit, scales are logs, ``rot`` is wxyz.
``scale_2`` is ``log(1e-6)`` (flat) so 3D viewers draw the surfels as disks, and ``nx ny nz``
hold the surfel normals (3DGS writes zeros there; its viewers ignore them).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch

from holowarp.fileio import atomic_path

__all__ = [
    "SH_C0",
    "FLAT_LOG_SCALE",
    "PARAM_NAMES",
    "GaussianModel",
    "PlyError",
    "write_gaussians_ply",
    "load_gaussians_ply",
    "quat_to_rotmat",
    "quats_facing",
    "rgb_to_sh_dc",
    "sh_dc_to_rgb",
]

#: Degree-0 spherical-harmonics constant 1 / (2 sqrt(pi)).
SH_C0 = 0.28209479177387814
#: log of the third (normal-direction) scale written for 3D viewers: a flat disk.
FLAT_LOG_SCALE = math.log(1e-6)
#: Learnable tensors of :class:`GaussianModel`, in PLY/optimiser order.
PARAM_NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh_dc")

_PLY_FIELDS = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
    + ["scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
)


class PlyError(ValueError):
    """A Gaussian PLY file cannot be read; the message names the file and the reason."""


def rgb_to_sh_dc(rgb):
    """Degree-0 SH coefficient whose colour is ``rgb`` (3DGS convention)."""
    return (rgb - 0.5) / SH_C0


def sh_dc_to_rgb(sh_dc):
    """Colour of a degree-0 SH coefficient (not clamped)."""
    return sh_dc * SH_C0 + 0.5


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [N, 3, 3] of wxyz quaternions [N, 4] (normalised here)."""
    q = torch.nn.functional.normalize(quats, dim=-1)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))  # fmt: skip



def quats_facing(normals) -> np.ndarray:
    """wxyz quaternions [N, 4] of the shortest rotations taking +z onto ``normals`` [N, 3]
    (unit vectors), i.e. surfels whose normal (third axis) is ``normals``. The rotation is
    undefined for a normal of exactly -z (the result is then not a unit quaternion)."""
    d = np.asarray(normals, dtype=np.float64)
    axis = np.cross(np.array([0.0, 0.0, 1.0]), d)
    s = np.linalg.norm(axis, axis=1)
    ang = np.arctan2(s, d[:, 2])
    axis = axis / np.maximum(s, 1e-12)[:, None]
    return np.concatenate([np.cos(ang / 2)[:, None], axis * np.sin(ang / 2)[:, None]], 1)


def _logit(p):
    p = np.clip(np.asarray(p, dtype=np.float64), 1e-7, 1 - 1e-7)
    return np.log(p / (1 - p))


def write_gaussians_ply(
    path: str | os.PathLike,
    *,
    means,  # [N, 3]
    quats,  # [N, 4] wxyz
    scales,  # [N, 2] linear
    opacities,  # [N] in (0, 1)
    colors=None,  # [N, 3] RGB
    sh_dc=None,  # [N, 3]; overrides colors
    normals=None,  # [N, 3]; default: the rotations' third axes
) -> Path:
    """Write surfels as a 3DGS-layout binary PLY (atomically). Tensors or arrays accepted.

    Give either ``colors`` (RGB; stored as ``f_dc = (rgb - 0.5) / C0``) or ``sh_dc``.
    """

    def arr(x, name, shape):
        if x is None:
            raise ValueError(f"write_gaussians_ply: {name} is required")
        a = x.detach().cpu().double().numpy() if isinstance(x, torch.Tensor) else np.asarray(x, np.float64)
        if a.shape[1:] != shape[1:] or (len(a) != shape[0] and shape[0] >= 0):
            raise ValueError(f"write_gaussians_ply: {name} has shape {a.shape}, expected {shape}")
        return a

    m = arr(means, "means", (-1, 3))
    n = len(m)
    q = arr(quats, "quats", (n, 4))
    s = arr(scales, "scales", (n, 2))
    o = arr(opacities, "opacities", (n,))
    if sh_dc is not None:
        dc = arr(sh_dc, "sh_dc", (n, 3))
    else:
        dc = rgb_to_sh_dc(arr(colors, "colors", (n, 3)))
    qn = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    if normals is None:
        nrm = quat_to_rotmat(torch.from_numpy(qn))[:, :, 2].numpy()
    else:
        nrm = arr(normals, "normals", (n, 3))
    data = np.empty((n, len(_PLY_FIELDS)), dtype="<f4")
    data[:, 0:3] = m
    data[:, 3:6] = nrm
    data[:, 6:9] = dc
    data[:, 9] = _logit(o)
    data[:, 10:12] = np.log(np.maximum(s, 1e-30))
    data[:, 12] = FLAT_LOG_SCALE
    data[:, 13:17] = qn
    header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {n}\n"
    header += "".join(f"property float {f}\n" for f in _PLY_FIELDS) + "end_header\n"
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(data.tobytes())
    return path


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


def load_gaussians_ply(path: str | os.PathLike) -> dict:
    """Read a 3DGS-layout PLY (ours or any 3DGS/2DGS trainer's) into NumPy arrays.

    Returns:
        dict with ``means`` [N, 3], ``quats`` [N, 4] (wxyz, unit), ``scales`` [N, 2] (linear,
        the first two), ``opacities`` [N] (in (0, 1)), ``sh_dc`` [N, 3], ``colors`` [N, 3]
        (RGB from ``sh_dc``, clamped to [0, 1]) and ``normals`` [N, 3] (the rotations'
        third axes), all float64.

    Raises:
        PlyError: missing file, not a binary little-endian vertex PLY, or missing fields.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise PlyError(f"{path}: cannot read Gaussian PLY ({e.strerror or e})") from None
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply") or end < 0:
        raise PlyError(f"{path}: not a PLY file (no 'ply' magic or 'end_header')")
    lines = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt = next((ln.split()[1] for ln in lines if ln.startswith("format")), None)
    if fmt != "binary_little_endian":
        raise PlyError(f"{path}: PLY format {fmt!r} is not supported (expected binary_little_endian)")
    count, props, in_vertex = None, [], False
    for ln in lines:
        parts = ln.split()
        if not parts:
            continue
        if parts[0] == "element":
            in_vertex = parts[1] == "vertex"
            if in_vertex:
                count = int(parts[2])
            elif count is None:
                raise PlyError(f"{path}: element {parts[1]!r} before 'vertex' is not supported")
        elif parts[0] == "property" and in_vertex:
            if parts[1] == "list" or parts[1] not in _PLY_TYPES:
                raise PlyError(f"{path}: unsupported vertex property {' '.join(parts[1:])!r}")
            props.append((parts[2], "<" + _PLY_TYPES[parts[1]]))
    if count is None:
        raise PlyError(f"{path}: no vertex element")
    dtype = np.dtype(props)
    body = raw[end + len(b"end_header\n") :]
    if len(body) < count * dtype.itemsize:
        raise PlyError(f"{path}: truncated ({len(body)} bytes for {count} vertices of {dtype.itemsize})")
    v = np.frombuffer(body, dtype=dtype, count=count)
    names = set(v.dtype.names)
    need = {"x", "y", "z", "opacity", "scale_0", "scale_1", "rot_0", "rot_1", "rot_2", "rot_3"}
    if not need <= names:
        raise PlyError(f"{path}: missing Gaussian fields {sorted(need - names)}")

    def col(*fields):
        return np.stack([np.asarray(v[f], np.float64) for f in fields], axis=1)

    means = col("x", "y", "z")
    q = col("rot_0", "rot_1", "rot_2", "rot_3")
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    dc = col("f_dc_0", "f_dc_1", "f_dc_2") if {"f_dc_0", "f_dc_1", "f_dc_2"} <= names else np.zeros((count, 3))
    logits = np.asarray(v["opacity"], np.float64)
    return {
        "means": means,
        "quats": q,
        "scales": np.exp(col("scale_0", "scale_1")),
        "opacities": 1.0 / (1.0 + np.exp(-logits)),
        "sh_dc": dc,
        "colors": np.clip(sh_dc_to_rgb(dc), 0.0, 1.0),
        "normals": quat_to_rotmat(torch.from_numpy(q))[:, :, 2].numpy(),
    }


class GaussianModel:
    """Learnable 2D Gaussian surfels with activations, Adam and density control.

    Args:
        means: [N, 3]; log_scales: [N, 2]; quats: [N, 4] wxyz; opacity_logits: [N];
        sh_dc: [N, 3]. Copied to ``device`` as float32 leaf tensors.

    Example:
        >>> g = GaussianModel.from_points(points, colors)
        >>> g.setup_optimizer({"means": 1.6e-4, "log_scales": 5e-3, "quats": 1e-3,
        ...                    "opacity_logits": 0.05, "sh_dc": 2.5e-3})
        >>> out = g.render(viewmat, K, 128, 128); out["rgb"].mean().backward(); g.step()
    """

    def __init__(self, means, log_scales, quats, opacity_logits, sh_dc, *, device="cpu"):
        self.device = torch.device(device)
        vals = dict(means=means, log_scales=log_scales, quats=quats, opacity_logits=opacity_logits, sh_dc=sh_dc)
        self.params: dict[str, torch.Tensor] = {}
        n = None
        for name in PARAM_NAMES:
            t = torch.as_tensor(vals[name]).detach().to(self.device, torch.float32).clone()
            if n is None:
                n = t.shape[0]
            if t.shape[0] != n:
                raise ValueError(f"GaussianModel: {name} has {t.shape[0]} rows, means has {n}")
            self.params[name] = t.requires_grad_(True)
        self.optimizer: torch.optim.Adam | None = None

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_points(
        cls,
        points,  # [N, 3]
        colors=None,  # [N, 3] RGB in [0, 1]
        *,
        scales=None,  # [N] or [N, 2] linear; default: mean distance to the 3 nearest points
        opacity: float = 0.1,
        seed: int = 0,
        device="cpu",
    ) -> "GaussianModel":
        """Surfels at ``points`` with random orientations (3DGS-style initialisation)."""
        pts = np.asarray(points, dtype=np.float64)
        n = len(pts)
        if n == 0:
            raise ValueError("GaussianModel.from_points: no points")
        if scales is None:
            from scipy.spatial import cKDTree

            k = min(4, n)
            d, _ = cKDTree(pts).query(pts, k=k)
            s = np.sqrt(np.mean(d[:, 1:] ** 2, axis=1)) if k > 1 else np.full(n, 0.01)
            scales = np.maximum(s, 1e-7)
        s = np.asarray(scales, dtype=np.float64)
        s = np.repeat(s[:, None], 2, axis=1) if s.ndim == 1 else s
        rng = np.random.default_rng(seed)
        q = rng.normal(size=(n, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        c = np.full((n, 3), 0.5) if colors is None else np.asarray(colors, dtype=np.float64)
        return cls(
            pts, np.log(s), q, np.full(n, _logit(opacity)), rgb_to_sh_dc(c), device=device
        )

    @classmethod
    def from_ply(cls, path, *, device="cpu") -> "GaussianModel":
        g = load_gaussians_ply(path)
        return cls(g["means"], np.log(g["scales"]), g["quats"], _logit(g["opacities"]), g["sh_dc"], device=device)

    # ---------------------------------------------------------------- activations
    @property
    def num(self) -> int:
        return int(self.params["means"].shape[0])

    @property
    def means(self) -> torch.Tensor:
        return self.params["means"]

    @property
    def quats(self) -> torch.Tensor:
        return self.params["quats"]

    def scales(self) -> torch.Tensor:
        return torch.exp(self.params["log_scales"])

    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.params["opacity_logits"])

    def colors(self) -> torch.Tensor:
        return torch.clamp_min(sh_dc_to_rgb(self.params["sh_dc"]), 0.0)

    def normals(self) -> torch.Tensor:
        return quat_to_rotmat(self.params["quats"].detach())[:, :, 2]

    def render(self, viewmat, K, width: int, height: int, *, background=None) -> dict:
        """:func:`holowarp.ops.rasterize_surfels` of the current surfels."""
        from holowarp.ops import rasterize_surfels

        if background is not None:
            background = torch.as_tensor(background, dtype=torch.float32, device=self.device)
        return rasterize_surfels(
            self.means, self.quats, self.scales(), self.opacities(), self.colors(),
            torch.as_tensor(viewmat, dtype=torch.float64), torch.as_tensor(K, dtype=torch.float64),
            width, height, background,
        )  # fmt: skip

    # ---------------------------------------------------------------- optimiser
    def setup_optimizer(self, lrs: dict[str, float]) -> torch.optim.Adam:
        """One Adam param group per parameter (named), eps 1e-15 as in 3DGS."""
        missing = set(PARAM_NAMES) - set(lrs)
        if missing:
            raise ValueError(f"setup_optimizer: no learning rate for {sorted(missing)}")
        groups = [{"params": [self.params[n]], "lr": float(lrs[n]), "name": n} for n in PARAM_NAMES]
        self.optimizer = torch.optim.Adam(groups, lr=0.0, eps=1e-15)
        return self.optimizer

    def set_lr(self, name: str, lr: float):
        for g in self.optimizer.param_groups:
            if g["name"] == name:
                g["lr"] = float(lr)

    def step(self):
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    def _rebuild(self, keep: torch.Tensor | None = None, extra: dict[str, torch.Tensor] | None = None):
        """Replace every parameter by ``param[keep]`` followed by ``extra[name]`` rows,
        carrying Adam's moments along (zeros for new rows)."""
        for name in PARAM_NAMES:
            old = self.params[name]
            data = old.detach()
            state = self.optimizer.state.pop(old, None) if self.optimizer is not None else None
            if keep is not None:
                data = data[keep]
                if state:
                    state = {k: (v[keep] if torch.is_tensor(v) and v.ndim > 0 else v) for k, v in state.items()}
            if extra is not None:
                add = extra[name].detach().to(data)
                data = torch.cat([data, add], 0)
                if state:
                    state = {
                        k: (torch.cat([v, torch.zeros_like(add)], 0) if torch.is_tensor(v) and v.ndim > 0 else v)
                        for k, v in state.items()
                    }
            new = data.clone().requires_grad_(True)
            self.params[name] = new
            if self.optimizer is not None:
                for g in self.optimizer.param_groups:
                    if g["name"] == name:
                        g["params"][0] = new
                if state:
                    self.optimizer.state[new] = state

    # ---------------------------------------------------------------- density control
    def prune(self, remove: torch.Tensor):
        """Drop the surfels where ``remove`` [N] bool is set."""
        self._rebuild(keep=~remove.to(self.device))

    def clone(self, select: torch.Tensor):
        """Duplicate the selected surfels (small ones under-reconstructing a region)."""
        sel = select.to(self.device)
        self._rebuild(extra={n: self.params[n].detach()[sel] for n in PARAM_NAMES})

    def split(self, select: torch.Tensor, *, n_split: int = 2, generator: torch.Generator | None = None):
        """Replace each selected surfel by ``n_split`` smaller ones sampled in its plane
        (positions ~ N(mean, scales along the two tangent axes), scales / (0.8 n_split))."""
        sel = select.to(self.device)
        k = int(sel.sum())
        if k == 0:
            return
        p = {n: self.params[n].detach()[sel].repeat(n_split, *([1] * (self.params[n].ndim - 1))) for n in PARAM_NAMES}
        std = torch.exp(p["log_scales"])
        noise = torch.randn(std.shape, generator=generator, device="cpu").to(std) * std
        R = quat_to_rotmat(p["quats"])
        p["means"] = p["means"] + R[:, :, 0] * noise[:, :1] + R[:, :, 1] * noise[:, 1:2]
        p["log_scales"] = p["log_scales"] - math.log(0.8 * n_split)
        self._rebuild(keep=~sel, extra=p)

    def reset_opacity(self, max_opacity: float = 0.01):
        """Clamp opacities to ``max_opacity`` and clear their Adam moments (3DGS reset)."""
        old = self.params["opacity_logits"]
        with torch.no_grad():
            old.copy_(torch.minimum(old, torch.full_like(old, float(_logit(max_opacity)))))
        if self.optimizer is not None and old in self.optimizer.state:
            for v in self.optimizer.state[old].values():
                if torch.is_tensor(v) and v.ndim > 0:
                    v.zero_()

    # ---------------------------------------------------------------- persistence
    def state_dict(self) -> dict:
        out = {n: self.params[n].detach().cpu().clone() for n in PARAM_NAMES}
        if self.optimizer is not None:
            out["optimizer"] = self.optimizer.state_dict()
        return out

    def load_state_dict(self, state: dict, lrs: dict[str, float] | None = None):
        """Restore parameters (and the optimiser, if ``state`` has one and ``lrs`` is given)."""
        for n in PARAM_NAMES:
            self.params[n] = state[n].to(self.device, torch.float32).clone().requires_grad_(True)
        if lrs is not None:
            self.setup_optimizer(lrs)
            if "optimizer" in state:
                self.optimizer.load_state_dict(state["optimizer"])

    def save_ply(self, path) -> Path:
        """Write the surfels as a 3DGS-layout PLY (see :func:`write_gaussians_ply`)."""
        with torch.no_grad():
            return write_gaussians_ply(
                path, means=self.means, quats=self.quats, scales=self.scales(), opacities=self.opacities(),
                sh_dc=self.params["sh_dc"],
            )  # fmt: skip
