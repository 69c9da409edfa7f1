"""K stacked networks lie in memory as K runs alone do (:mod:`pporpe.nn.stacked`).

On some CPUs (an AMD EPYC with AVX2 and MKL 2024.2) ``F.linear`` of the same numbers rounds
differently when an operand starts off a 16-byte boundary or has other strides; these tests
check the layout that makes a population member compute what its run alone computes on
such a machine, and that every form :func:`linear_mode` picks for a layout agrees with
``F.linear`` on operands laid out as a run alone's, on draws the probe never saw.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pporpe.batch import BatchConfig
from pporpe.batch.model import ActorCritic
from pporpe.batch.stacked import StackedActorCritic
from pporpe.nn.stacked import (
    ALIGNMENT,
    LinearLayout,
    aligned,
    linear_mode,
    padded_rows,
    stacked_linear,
)

BYTES = 4 * ALIGNMENT


@pytest.fixture(autouse=True)
def one_thread() -> Iterator[None]:
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize("n", [1, 15, 16, 17, 1001])
def test_padded_rows_start_on_64_byte_boundaries(n: int) -> None:
    rows = padded_rows(5, n)
    assert rows.shape == (5, n) and not rows.any()
    assert [rows[k].data_ptr() % BYTES for k in range(5)] == [0] * 5
    assert rows.stride() == (-(-n // ALIGNMENT) * ALIGNMENT, 1)


def test_aligned_keeps_an_aligned_tensor_and_copies_another_with_its_strides() -> None:
    base = torch.arange(4 * 32 * 10, dtype=torch.float32).view(4, 32, 10)
    first = base[0, :, :5]  # offset 0: starts on the boundary
    assert aligned(first).data_ptr() == first.data_ptr()
    view = base.view(-1)[3 : 3 + 320].view(32, 10)[:, :5]  # 12 bytes past the boundary
    assert view.data_ptr() % BYTES == 12
    copy = aligned(view)
    assert copy.data_ptr() % BYTES == 0 and copy.data_ptr() != view.data_ptr()
    assert copy.stride() == view.stride() == (10, 1)
    assert torch.equal(copy, view)


def test_members_parameters_lie_where_a_run_alones_lie() -> None:
    """Every parameter view of member k starts at the same address modulo 64 bytes as the
    same parameter of a run alone."""
    cfg = BatchConfig(env="Pendulum-v1", layers=2, units=24)
    low, high = np.array([-2.0], dtype=np.float32), np.array([2.0], dtype=np.float32)
    alone = ActorCritic(3, low, high, cfg)
    assert alone.theta.data_ptr() % BYTES == 0
    pop = StackedActorCritic(alone, 3)
    run_views = [*alone._pol, alone._extra, *alone._val]
    member_views = [*pop._pol, pop._extra, *pop._val]
    for k in range(3):
        assert [v[k].data_ptr() % BYTES for v in member_views] == [
            v.data_ptr() % BYTES for v in run_views
        ]


def test_linear_layout_of_a_members_layer() -> None:
    """The layout of a layer whose input is a strided view (observations in the first 5 of
    10 columns) and whose weight and bias lie in padded rows."""
    flat = padded_rows(3, 40)  # rows of 48 floats
    w = flat[:, 2:32].view(3, 6, 5)
    b = flat[:, 32:38]
    x = torch.zeros(3, 7, 10)[:, :, :5]
    assert LinearLayout.of(x, w, b) == LinearLayout((70, 10, 1), 0, 48, 2, 32)
    assert LinearLayout.of(x, w, b) != LinearLayout.packed(3, 7, 5, 6)
    with pytest.raises(ValueError, match="views of the rows of one"):
        LinearLayout.of(x, w, torch.zeros(3, 6))


def test_a_strided_input_is_probed_in_its_layout() -> None:
    """A minibatch's observations are a strided view (stride 10 for 5 features): the form
    chosen for that layout gives, for every member, what F.linear gives on a run alone's
    strided input of its own, on draws the probe did not see."""
    members, rows, fan_in, fan_out = 3, 32, 5, 8
    for draw in range(200, 204):
        gen = torch.Generator().manual_seed(draw)
        x = torch.randn(members, rows, 10, generator=gen)[:, :, :fan_in]
        flat = padded_rows(members, fan_out * fan_in + fan_out)
        flat.copy_(torch.randn(members, fan_out * fan_in + fan_out, generator=gen))
        w = flat[:, : fan_out * fan_in].view(members, fan_out, fan_in)
        b = flat[:, fan_out * fan_in :]
        mode = linear_mode(rows, fan_in, fan_out, False, members, LinearLayout.of(x, w, b))
        out = stacked_linear(x, w, b, mode)
        for k in range(members):
            xk = torch.empty_strided((rows, fan_in), (10, 1))  # a run alone's view
            xk.copy_(x[k])
            run = flat[k].clone()
            ref = F.linear(
                xk, run[: fan_out * fan_in].view(fan_out, fan_in), run[fan_out * fan_in :]
            )
            assert torch.equal(out[k], ref), (mode, draw, k)


@pytest.mark.parametrize(
    "rows,fan_in,fan_out", [(2, 16, 1), (1, 11, 6), (8, 16, 6), (32, 8, 1), (64, 64, 64)]
)
@pytest.mark.parametrize("grad", [False, True])
def test_the_chosen_form_equals_f_linear_on_fresh_tensors(
    rows: int, fan_in: int, fan_out: int, grad: bool
) -> None:
    """On draws the probe did not see, each member's output (and, with ``grad``, its input
    and weight gradients) equal ``F.linear`` on fresh tensors of its own, as a run alone
    computes them; weights in padded rows as a population holds them."""
    members = 4
    mode = linear_mode(rows, fan_in, fan_out, grad, members)
    for draw in range(100, 106):
        gen = torch.Generator().manual_seed(draw)
        x = torch.randn(members, rows, fan_in, generator=gen)
        flat = padded_rows(members, fan_out * fan_in + fan_out)  # a population's layout
        flat.copy_(torch.randn(members, fan_out * fan_in + fan_out, generator=gen))
        seed = torch.randn(members, rows, fan_out, generator=gen)
        flat.requires_grad_(grad)
        xs = x.clone().requires_grad_(grad)
        w = flat[:, : fan_out * fan_in].view(members, fan_out, fan_in)
        b = flat[:, fan_out * fan_in :]
        with torch.set_grad_enabled(grad):
            out = stacked_linear(xs, w, b, mode)
            grads = torch.autograd.grad(out, [xs, w], seed) if grad else ()
        for k in range(members):
            run = torch.zeros(fan_out * fan_in + fan_out)  # a run alone's flat vector
            run.copy_(flat[k].detach())
            run.requires_grad_(grad)
            xk = x[k].clone().requires_grad_(grad)
            wk = run[: fan_out * fan_in].view(fan_out, fan_in)
            with torch.set_grad_enabled(grad):
                ref = F.linear(xk, wk, run[fan_out * fan_in :])
            assert torch.equal(out[k].detach(), ref.detach()), (mode, draw, k)
            if grad:
                dx, dw = torch.autograd.grad(ref, [xk, wk], seed[k])
                assert torch.equal(grads[0][k], dx), (mode, draw, k)
                assert torch.equal(grads[1][k], dw), (mode, draw, k)
