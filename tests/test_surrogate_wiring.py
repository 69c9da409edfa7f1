"""Every surrogate of :data:`pporpe.surrogates.METHODS` is wired everywhere a method is named.

A surrogate is one name in ``pporpe.surrogates.Method``; the places that must know it are
listed in ``docs/architecture.md`` (recipe "Add a surrogate"). This file fails, naming the
place, when one of them is missed: the validation of the configs, the CLI's choices, a grid
spec, the fused kernel's closed form (which falls through to another method's formula for
a code it does not know), the reports' labels, colours and line styles, the analytic
figure, and Stable-Baselines3's ``surrogate``.
"""

from __future__ import annotations

from pathlib import Path
from typing import get_args

import pytest
import torch

from pporpe import surrogates as S
from pporpe.batch.config import BatchConfig
from pporpe.cli import build_parser
from pporpe.experiments.grids.spec import parse_spec
from pporpe.experiments.reports.figures import (
    METHOD_COLORS,
    METHOD_LABELS,
    METHOD_STYLES,
    negative_loss_figure,
)
from pporpe.online.config import OnlineConfig
from pporpe.online.fused_engine.kernels.inputs import METHOD_CODES
from pporpe.online.fused_engine.kernels.surrogates import surrogate_closed

METHODS = list(S.METHODS)
FORMS = list(get_args(S.RPEForm))


def test_the_methods_are_the_literals_names() -> None:
    assert METHODS == list(get_args(S.Method)) and len(set(METHODS)) == len(METHODS) >= 3


@pytest.mark.parametrize("method", METHODS)
def test_the_surrogate_functions_take_it(method: str) -> None:
    """Its parameters validate at their defaults; objective, loss and regularisation amount
    are finite on both sides of every threshold, and the objective is rho * A at rho = 1."""
    S.check_surrogate_params(method)
    ratio = torch.tensor([0.5, 0.85, 1.0, 1.0, 1.15, 1.6], dtype=torch.float64)
    adv = torch.tensor([1.0, -1.0, 2.0, -0.5, 1.0, -1.0], dtype=torch.float64)
    for form in FORMS:
        obj = S.surrogate_objective(method, ratio, adv, rpe_form=form)  # type: ignore[arg-type]
        assert torch.isfinite(obj).all() and obj.shape == ratio.shape, (method, form)
        assert torch.allclose(obj[2:4], adv[2:4], atol=1e-12), (method, form)
    assert torch.isfinite(S.surrogate_loss(method, ratio, adv))  # type: ignore[arg-type]
    reg = S.regularization_amount(method, ratio, adv)  # type: ignore[arg-type]
    assert torch.isfinite(torch.as_tensor(reg.amount)).all()


@pytest.mark.parametrize("method", METHODS)
def test_both_learners_configs_take_it(method: str) -> None:
    assert OnlineConfig(method=method, compile=False).method == method  # type: ignore[arg-type]
    assert BatchConfig(method=method).method == method  # type: ignore[arg-type]


@pytest.mark.parametrize("method", METHODS)
def test_pporpe_train_and_a_grid_spec_take_it(method: str, tmp_path: Path) -> None:
    for learner in ("online", "batch"):
        args = build_parser().parse_args(
            ["train", "--learner", learner, "--method", method, "--out", str(tmp_path)]
        )
        assert args.method == method
    spec = parse_spec({"name": "wiring", "methods": [method], "seeds": 1,
                       "tasks": [{"env": "Pendulum-v1", "steps": 10}]})  # fmt: skip
    assert spec.methods == [method]


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("form", FORMS)
def test_the_fused_kernel_computes_its_objective(method: str, form: str) -> None:
    """The fused engine (the online learner's default) has a code for it, and its closed
    form is :func:`pporpe.surrogates.surrogate_objective` (A = +-1, on both sides of every
    threshold; its derivative is held to autograd in ``tests/test_fused.py``)."""
    assert (method, form) in METHOD_CODES, f"no fused-kernel code for {(method, form)}"
    code = METHOD_CODES[(method, form)]
    eps, beta, eta = 0.1, 0.5, 0.3
    rho = torch.tensor([0.4, 0.8, 0.95, 1.0, 1.05, 1.2, 1.9], dtype=torch.float64)
    for sigma in (1.0, -1.0):
        adv = torch.full_like(rho, sigma)
        ref = S.surrogate_objective(method, rho, adv, eps, beta, eta, form)  # type: ignore[arg-type]
        for x, want in zip(rho.tolist(), ref.tolist(), strict=True):
            got = surrogate_closed(code, x, sigma, eps, beta, eta)[0]
            assert got == pytest.approx(want, rel=1e-12, abs=1e-12), (method, form, x, sigma)


def test_the_reports_label_colour_and_style_every_method() -> None:
    for table in (METHOD_LABELS, METHOD_COLORS, METHOD_STYLES):
        assert set(METHODS) <= set(table), sorted(set(METHODS) - set(table))
    assert len({METHOD_LABELS[m] for m in METHODS}) == len(METHODS)
    assert len({METHOD_COLORS[m] for m in METHODS}) == len(METHODS)


def test_the_analytic_figure_draws_every_method() -> None:
    fig = negative_loss_figure()
    for ax in fig.axes:
        labels = [line.get_label() for line in ax.lines]
        for m in METHODS:
            assert any(label.startswith(METHOD_LABELS[m]) for label in labels), (m, labels)


@pytest.mark.parametrize("method", METHODS)
def test_stable_baselines3_takes_it(method: str) -> None:
    pytest.importorskip("stable_baselines3")
    from pporpe.sb3 import PPO

    model = PPO("MlpPolicy", "Pendulum-v1", surrogate=method, n_steps=64, batch_size=64)
    assert model.surrogate == method
