r"""Per-member random streams for the policy samples, drawn in blocks.

Each member owns a ``torch.Generator`` seeded with its seed. Noise is drawn in blocks
of ``block`` steps: one block is ``block * act_dim`` points ``(U, V)`` uniform on the
unit disk (uniform pairs on ``(-1, 1)^2`` kept where ``0 < W = U^2 + V^2 < 1``). The
acceptance test does not depend on the policy, so the rejection happens when the block
is drawn and a step consumes exactly one point per action dimension; the stream of a
member depends only on its seed, never on K, its slot or other members.

From one point (``W = U^2 + V^2``):

* Student-t with ``df`` degrees of freedom (Bailey 1994, polar method)::

      T = U * sqrt(df * (W^(-2/df) - 1) / W)

* standard normal (Marsaglia's polar method)::

      Z = U * sqrt(-2 log(W) / W)

A checkpoint stores the generator state at the start of the current block and the
position in it; loading redraws the block, so the continuation is bitwise identical.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = ["NoiseBank", "polar_normal", "polar_student_t"]


def polar_student_t(points: Tensor, df: Tensor) -> Tensor:
    """Student-t samples from unit-disk points ``[..., 2]`` (Bailey's polar method).

    ``df`` broadcasts against ``points[..., 0]``. Computed in the points' dtype.
    """
    u = points[..., 0]
    w = points[..., 0].square() + points[..., 1].square()
    df = df.to(points.dtype)
    # W^(-2/df) - 1 = expm1(-(2/df) log W): accurate for large df as well
    return u * torch.sqrt(df * torch.expm1((-2.0 / df) * torch.log(w)) / w)


def polar_normal(points: Tensor) -> Tensor:
    """Standard normal samples from unit-disk points ``[..., 2]`` (Marsaglia's polar method)."""
    u = points[..., 0]
    w = points[..., 0].square() + points[..., 1].square()
    return u * torch.sqrt(-2.0 * torch.log(w) / w)


def _draw_block(gen: torch.Generator, n: int) -> Tensor:
    """``n`` points uniform on the open unit disk (without the centre), float64 ``[n, 2]``."""
    chunk = int(n * 1.3) + 64
    parts: list[Tensor] = []
    have = 0
    while have < n:
        c = torch.rand(chunk, 2, dtype=torch.float64, generator=gen).mul_(2.0).sub_(1.0)
        w = c.square().sum(1)
        c = c[(w > 0.0) & (w < 1.0)]
        parts.append(c)
        have += c.shape[0]
    return torch.cat(parts)[:n]


class NoiseBank:
    """Blocks of unit-disk points for K members (float64, ``[K, block, act_dim, 2]``)."""

    def __init__(self, k: int, act_dim: int, block: int = 1024) -> None:
        self.K, self.act_dim, self.block = k, act_dim, block
        self.buf = torch.zeros(k, block, act_dim, 2, dtype=torch.float64)
        self.pos = np.zeros(k, dtype=np.int64)
        self.gens: list[torch.Generator] = [torch.Generator() for _ in range(k)]
        self.block_state: list[Tensor] = [g.get_state() for g in self.gens]
        self._buf_np = self.buf.numpy()  # the same memory, indexed by numpy (cheaper)
        self._arange = np.arange(k)

    def _refill(self, k: int) -> None:
        self.block_state[k] = self.gens[k].get_state()
        pts = _draw_block(self.gens[k], self.block * self.act_dim)
        self.buf[k] = pts.view(self.block, self.act_dim, 2)
        self.pos[k] = 0

    def reset(self, k: int, seed: int) -> None:
        """Start member ``k``'s stream afresh from ``seed``."""
        self.gens[k] = torch.Generator().manual_seed(int(seed))
        self._refill(k)

    def take(self, mask: np.ndarray) -> Tensor:
        """Points of the current step ``[K, act_dim, 2]``; advances the members in ``mask``.

        Rows of members outside ``mask`` are returned too (their next points) but not
        consumed.
        """
        spent = self.pos >= self.block
        if spent.any():
            for k in np.nonzero(mask & spent)[0]:
                self._refill(int(k))
        pts = self._buf_np[self._arange, np.minimum(self.pos, self.block - 1)]
        self.pos += mask
        return torch.from_numpy(pts)

    def state(self, k: int) -> dict[str, Any]:
        """Generator state at the start of the current block and the position in it."""
        return {"gen_state": self.block_state[k].clone(), "pos": int(self.pos[k])}

    def load(self, k: int, state: dict[str, Any]) -> None:
        """Restore :meth:`state` (redraws the block from the stored generator state)."""
        gen = torch.Generator()
        gen.set_state(state["gen_state"].clone())
        self.gens[k] = gen
        self._refill(k)
        self.pos[k] = int(state["pos"])
