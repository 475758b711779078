"""Vertex optimiser of the geometry stage (method.md §6): uniform Adam + cosine schedule.

``UniformAdam`` is Adam with ONE second-moment normaliser shared by every element of every
parameter in a group ("AdamUniform" of Nicolet et al. 2021, "Large Steps in Inverse
Rendering", as used by TetSphere Splatting), plus a cap on each vertex's displacement per
step. A shared normaliser keeps the relative sizes of the gradient entries, so the step is
a uniformly scaled gradient-momentum step: vertices with small gradients are not blown up
to the same step length as vertices with large ones, which is what keeps a mesh smooth.

``cosine_lr`` anneals the learning rate from 2e-4 to 1e-4 (method.md §6).
"""

from __future__ import annotations

import math

import torch

__all__ = ["LR_START", "LR_END", "UniformAdam", "cosine_lr"]

#: Vertex learning rate at the start and end of a geometry block, method.md §6.
LR_START = 2.0e-4
LR_END = 1.0e-4


class UniformAdam(torch.optim.Optimizer):
    """Adam with one shared second-moment normaliser per parameter group.

    Per element, the first moment ``m`` and second moment ``v`` follow Adam (with bias
    correction). The normaliser is the MAXIMUM of ``sqrt(v_hat)`` over all elements of all
    parameters in the group (the infinity norm, as Nicolet et al.):
    ``step = lr * m_hat / (max sqrt(v_hat) + eps)``. Then each vertex's displacement (a row
    over the last dimension of a parameter with >= 2 dims, e.g. (N, 3) positions; single
    elements for 1-D parameters) is scaled down to length ``max_step`` when longer.

    Args:
        params: parameters or parameter groups.
        lr: learning rate (metres per unit normalised step for positions).
        betas: Adam's moment decay rates.
        eps: added to the shared normaliser.
        max_step: largest displacement of one vertex in one step, metres; ``None`` for no
            cap.
    """

    def __init__(self, params, lr: float = LR_START, betas=(0.9, 0.999), eps: float = 1.0e-8, max_step: float | None = None):
        if not lr >= 0.0:
            raise ValueError(f"UniformAdam: lr must be >= 0, got {lr}")
        b1, b2 = betas
        if not (0.0 <= b1 < 1.0 and 0.0 <= b2 < 1.0):
            raise ValueError(f"UniformAdam: betas must lie in [0, 1), got {betas}")
        if not eps >= 0.0:
            raise ValueError(f"UniformAdam: eps must be >= 0, got {eps}")
        if max_step is not None and not max_step > 0.0:
            raise ValueError(f"UniformAdam: max_step must be > 0 or None, got {max_step}")
        super().__init__(params, dict(lr=lr, betas=(float(b1), float(b2)), eps=eps, max_step=max_step))
        self._cache = None  # the Warp path's buffers and launches (holowarp.ops._warp.StepCache)

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            b1, b2 = group["betas"]
            params = [p for p in group["params"] if p.grad is not None]
            if not params:
                continue
            if len(params) == 1 and self._rows_step(params[0], group):
                continue
            m_hats, v_maxes = [], []
            for p in params:
                if p.grad.is_sparse:
                    raise RuntimeError("UniformAdam does not support sparse gradients")
                st = self._state(p)
                t = st["step"]
                g = p.grad
                st["exp_avg"].mul_(b1).add_(g, alpha=1.0 - b1)
                st["exp_avg_sq"].mul_(b2).addcmul_(g, g, value=1.0 - b2)
                m_hats.append(st["exp_avg"] / (1.0 - b1**t))
                v_maxes.append(st["exp_avg_sq"].max() / (1.0 - b2**t) if p.numel() else p.new_zeros(()))
            # one normaliser for the whole group (stays on device: no host sync)
            denom = torch.stack([v.to(params[0].dtype) for v in v_maxes]).max().sqrt() + group["eps"]
            for p, m_hat in zip(params, m_hats):
                upd = m_hat * (group["lr"] / denom)
                cap = group["max_step"]
                if cap is not None:
                    if upd.ndim >= 2:
                        n = upd.norm(dim=-1, keepdim=True)
                    else:
                        n = upd.abs()
                    upd = upd * torch.clamp(cap / n.clamp_min(torch.finfo(upd.dtype).tiny), max=1.0)
                p.sub_(upd)
        return loss

    def _state(self, p: torch.Tensor) -> dict:
        """``p``'s state with its step count advanced: ``step``, and the moments ``exp_avg``
        and ``exp_avg_sq`` (zeros at the first step), contiguous (the Warp path writes them
        through views)."""
        st = self.state[p]
        if not st:
            st["step"] = 0
            st["exp_avg"] = torch.zeros_like(p, memory_format=torch.contiguous_format)
            st["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.contiguous_format)
        for k in ("exp_avg", "exp_avg_sq"):
            if not st[k].is_contiguous():  # a loaded state may hold other strides
                st[k] = st[k].contiguous()
        st["step"] += 1
        return st

    def _rows_step(self, p: torch.Tensor, group: dict) -> bool:
        """The step of a group whose one parameter is (N, 3) rows (the geometry stage's
        vertices) in two Warp passes (:func:`holowarp.ops.adam.uniform_adam_rows_`) instead
        of about a dozen torch ops; False, having done nothing, for other parameters."""
        from holowarp.ops.adam import rows_supported, uniform_adam_rows_

        if not rows_supported(p):
            return False
        st = self._state(p)
        if self._cache is None:
            from holowarp.ops._warp import StepCache

            self._cache = StepCache()
        uniform_adam_rows_(p, st["exp_avg"], st["exp_avg_sq"], st["step"], lr=group["lr"], betas=group["betas"],
                           eps=group["eps"], max_step=group["max_step"], cache=self._cache)
        return True


def cosine_lr(step: int, total: int, lr_start: float = LR_START, lr_end: float = LR_END) -> float:
    """Cosine-annealed learning rate (method.md §6).

    ``lr(t) = lr_end + (lr_start - lr_end) (1 + cos(pi t / total)) / 2`` for ``t`` in
    ``[0, total]``; steps past ``total`` stay at ``lr_end``.
    """
    if total <= 0:
        raise ValueError(f"cosine_lr: total must be positive, got {total}")
    t = min(max(int(step), 0), int(total))
    return lr_end + 0.5 * (lr_start - lr_end) * (1.0 + math.cos(math.pi * t / total))
