"""Tests of pporpe.networks.mlp."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from pporpe.nn.mlp import ACTIVATIONS, mlp, mlp_num_params


def _count(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


def test_default_is_the_papers_network() -> None:
    net = mlp(7, 3)
    linears = [m for m in net if isinstance(m, nn.Linear)]
    norms = [m for m in net if isinstance(m, nn.LayerNorm)]
    acts = [m for m in net if isinstance(m, nn.SiLU)]
    assert len(linears) == 6 and len(norms) == 5 and len(acts) == 5
    assert [lin.out_features for lin in linears] == [100] * 5 + [3]
    assert linears[0].in_features == 7
    # Order within a block: Linear -> LayerNorm -> Swish; output layer last.
    kinds = [type(m) for m in net]
    assert kinds == [nn.Linear, nn.LayerNorm, nn.SiLU] * 5 + [nn.Linear]


@pytest.mark.parametrize(
    ("in_dim", "out_dim", "layers", "units", "layer_norm"),
    [(7, 3, 5, 100, True), (1, 1, 1, 4, True), (26, 13, 2, 32, False), (5, 1, 3, 8, False)],
)
def test_shapes_and_parameter_count(
    in_dim: int, out_dim: int, layers: int, units: int, layer_norm: bool
) -> None:
    net = mlp(in_dim, out_dim, layers=layers, units=units, layer_norm=layer_norm)
    expected = (
        (in_dim + 1) * units
        + (layers - 1) * (units + 1) * units
        + (units + 1) * out_dim
        + (2 * units * layers if layer_norm else 0)
    )
    assert _count(net) == expected == mlp_num_params(in_dim, out_dim, layers, units, layer_norm)
    for batch in [(), (4,), (2, 3)]:
        out = net(torch.randn(*batch, in_dim))
        assert out.shape == (*batch, out_dim)


def test_layer_norm_false_removes_layer_norm() -> None:
    net = mlp(4, 2, layers=3, units=16, layer_norm=False)
    assert not any(isinstance(m, nn.LayerNorm) for m in net)
    assert sum(isinstance(m, nn.Linear) for m in net) == 4


def test_swish_matches_x_sigmoid_x() -> None:
    net = mlp(3, 2, activation="swish")
    act = net[2]
    x = torch.linspace(-20.0, 20.0, 401, dtype=torch.float64)
    torch.testing.assert_close(act(x), x * torch.sigmoid(x))


@pytest.mark.parametrize(("name", "cls"), [("relu", nn.ReLU), ("tanh", nn.Tanh)])
def test_other_activations(name: str, cls: type[nn.Module]) -> None:
    net = mlp(3, 2, layers=2, units=8, activation=name)
    assert sum(isinstance(m, cls) for m in net) == 2
    assert not any(isinstance(m, nn.SiLU) for m in net)


@pytest.mark.parametrize(
    ("kwargs", "param"),
    [
        ({"in_dim": 0}, "in_dim"),
        ({"out_dim": -1}, "out_dim"),
        ({"layers": 0}, "layers"),
        ({"units": 0}, "units"),
        ({"units": 2.5}, "units"),
        ({"layers": True}, "layers"),
        ({"activation": "gelu"}, "activation"),
        ({"init": "xavier"}, "init"),
        ({"output_gain": -1.0}, "output_gain"),
    ],
)
def test_bad_arguments_raise(kwargs: dict[str, object], param: str) -> None:
    args: dict[str, object] = {"in_dim": 3, "out_dim": 2}
    args.update(kwargs)
    with pytest.raises(ValueError) as info:
        mlp(**args)  # type: ignore[arg-type]
    assert param in str(info.value)
    if param == "activation":
        for name in ACTIVATIONS:
            assert name in str(info.value)


def test_orthogonal_init_and_output_gain() -> None:
    torch.manual_seed(0)
    net = mlp(6, 4, layers=2, units=16, init="orthogonal", output_gain=0.01)
    linears = [m for m in net if isinstance(m, nn.Linear)]
    w = linears[1].weight.detach()
    torch.testing.assert_close(w @ w.T, torch.eye(16), atol=1e-5, rtol=0)
    for lin in linears:
        assert torch.all(lin.bias == 0)
    out_w = linears[-1].weight.detach()
    torch.testing.assert_close(out_w @ out_w.T, 1e-4 * torch.eye(4), atol=1e-8, rtol=0)

    small = mlp(6, 4, output_gain=0.0)
    assert torch.all(small(torch.randn(5, 6)) == 0)
