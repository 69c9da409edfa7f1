"""pporpe.sb3.PPO: Stable-Baselines3's PPO with pporpe's surrogates (issue 12)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import stable_baselines3 as sb3
import torch

from pporpe.sb3 import PPO, zoo_kwargs, zoo_model

ENV = "Pendulum-v1"
SMALL: dict[str, Any] = {
    "n_steps": 128,
    "batch_size": 32,
    "n_epochs": 4,
    "learning_rate": 3e-3,  # large enough that some ratios pass the threshold
    "clip_range": 0.05,
    "seed": 0,
    "device": "cpu",
}
UPDATES = 3


def trained(cls: Any, **kw: Any) -> Any:
    torch.set_num_threads(1)
    model = cls("MlpPolicy", ENV, **{**SMALL, **kw})
    model.learn(UPDATES * SMALL["n_steps"])
    return model


def params(model: Any) -> torch.Tensor:
    return torch.cat([p.detach().flatten() for p in model.policy.parameters()])


@pytest.fixture(scope="module")
def reference() -> Any:
    return trained(sb3.PPO)


def test_ppo_trains_bit_identically_to_stable_baselines3(reference: Any) -> None:
    ours = trained(PPO, surrogate="ppo")
    assert torch.equal(params(ours), params(reference))
    for key in ("train/value_loss", "train/policy_gradient_loss", "train/entropy_loss",
                "train/clip_fraction", "train/approx_kl", "train/loss"):  # fmt: skip
        assert ours.logger.name_to_value[key] == pytest.approx(
            reference.logger.name_to_value[key], rel=1e-6, abs=1e-12
        ), key
    assert ours.logger.name_to_value["train/n_updates"] == UPDATES * SMALL["n_epochs"]


def test_rb_with_eta_zero_is_ppo(reference: Any) -> None:
    assert torch.equal(params(trained(PPO, surrogate="rb", eta=0.0)), params(reference))


def test_rb_and_rpe_change_the_parameters(reference: Any) -> None:
    rb, rpe = trained(PPO, surrogate="rb", eta=0.3), trained(PPO, surrogate="rpe")
    start = params(PPO("MlpPolicy", ENV, **SMALL))
    ref = params(reference)
    assert torch.equal(params(PPO("MlpPolicy", ENV, **{**SMALL, "seed": 0})), start)
    for model in (rb, rpe):
        p = params(model)
        assert not torch.equal(p, ref) and not torch.equal(p, start)
    assert not torch.equal(params(rb), params(rpe))
    logged = rpe.logger.name_to_value
    assert logged["train/rpe_divergence"] > 0.0
    assert logged["train/regularization"] > 0.0  # PPO-RPE regularises every rho != 1
    assert 0.0 <= logged["train/past_threshold_fraction"] <= 1.0


def test_rpe_policy_loss_matches_a_float64_reference() -> None:
    """The policy loss of one minibatch against the formula of eq. (11), written here."""
    model = trained(PPO, surrogate="rpe", rpe_beta=0.4)
    data = next(model.rollout_buffer.get(64))
    eps, beta = 0.05, 0.4
    _, metrics = model._minibatch(data, eps, None)
    with torch.no_grad():
        _, logp, _ = model.policy.evaluate_actions(data.observations, data.actions)
    adv = data.advantages.double()
    adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    rho = torch.exp(logp.double() - data.old_log_prob.double())
    sigma = torch.where(adv >= 0, 1.0, -1.0).double()
    gain = adv.abs() / (eps * (2 * (1 - beta) - beta * sigma * eps))
    mix = 1 - beta + beta * rho
    expected = -(rho * adv - gain * mix * (rho / mix - 1) ** 2).mean()
    assert float(metrics["policy_gradient_loss"]) == pytest.approx(float(expected), rel=1e-4)


def test_spo_trains_and_its_policy_loss_matches_a_float64_reference(reference: Any) -> None:
    """SPO's loss, -mean(rho A - |A|/(2 eps) (rho - 1)^2), written here in float64."""
    model = trained(PPO, surrogate="spo", rpe_beta=0.99)  # rpe_beta is not SPO's
    p = params(model)
    assert not torch.equal(p, params(reference))
    assert not torch.equal(p, params(trained(PPO, surrogate="rpe")))
    logged = model.logger.name_to_value
    assert logged["train/regularization"] > 0.0  # (rho - 1)^2 / (2 eps) > 0 off rho = 1
    assert 0.0 <= logged["train/past_threshold_fraction"] <= 1.0
    data = next(model.rollout_buffer.get(64))
    eps = SMALL["clip_range"]
    _, metrics = model._minibatch(data, eps, None)
    with torch.no_grad():
        _, logp, _ = model.policy.evaluate_actions(data.observations, data.actions)
    adv = data.advantages.double()
    adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    rho = torch.exp(logp.double() - data.old_log_prob.double())
    expected = -(rho * adv - adv.abs() / (2 * eps) * (rho - 1) ** 2).mean()
    # a mean of terms of size ~1 that nearly cancel: float32's rounding, absolute
    assert float(metrics["policy_gradient_loss"]) == pytest.approx(float(expected), abs=1e-6)
    assert abs(float(expected)) > 1e-5  # and the mean is not zero


def test_save_and_load_keep_the_surrogate(tmp_path: Path) -> None:
    model = trained(PPO, surrogate="rpe", rpe_beta=0.3)
    model.save(tmp_path / "m")
    loaded = PPO.load(tmp_path / "m", device="cpu")
    assert (loaded.surrogate, loaded.rpe_beta) == ("rpe", 0.3)
    obs = np.linspace(-1, 1, 3 * 5, dtype=np.float32).reshape(5, 3)
    a, _ = model.predict(obs, deterministic=True)
    b, _ = loaded.predict(obs, deterministic=True)
    np.testing.assert_array_equal(a, b)
    loaded.set_env(model.get_env())
    loaded.learn(SMALL["n_steps"], reset_num_timesteps=False)  # training goes on
    assert not torch.equal(params(loaded), params(model))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (
            {"surrogate": "clip"},
            r"`surrogate` must be one of 'ppo', 'rb', 'rpe', 'spo'; got 'clip'",
        ),
        ({"surrogate": "rb", "eta": -0.1}, r"`eta` must be a finite number >= 0"),
        ({"eta": float("inf")}, r"`eta`"),
        ({"rpe_beta": 1.5}, r"`rpe_beta` must be a number in \[0, 1\]; got 1.5"),
        ({"clip_range": 1.2}, r"`clip_range` \(the paper's eps\) must be in \(0, 1\)"),
        ({"clip_range": "0.2"}, r"`clip_range` \(the paper's eps\) must be in \(0, 1\)"),
        ({"surrogate": "rpe", "rpe_beta": 0.95, "clip_range": 0.1}, r"rpe_beta must be < 0.909"),
        ({"surrogate": "spo", "clip_range": 0.0}, r"`clip_range` \(the paper's eps\) must be in"),
        ({"surrogate": "spo", "clip_range": 1.0}, r"`clip_range` \(the paper's eps\) must be in"),
    ],
)
def test_bad_arguments_are_refused_before_any_work(kwargs: dict[str, Any], match: str) -> None:
    with pytest.raises(ValueError, match=match):  # the env does not exist: nothing was built
        PPO("MlpPolicy", "NoSuchEnv-v0", **kwargs)


def test_rl_zoo3_entries() -> None:
    entry = {
        "n_envs": 2,
        "n_timesteps": 256.0,  # rl-zoo3 writes !!float 1e5
        "policy": "MlpPolicy",
        "normalize": True,
        "n_steps": 64,
        "batch_size": 64,
        "n_epochs": 2,
        "clip_range": "lin_0.2",  # reaches 0 at the last update: floored at 1e-8
        "learning_rate": "lin_1e-3",
        "policy_kwargs": "dict(net_arch=[16, 16], activation_fn=nn.Tanh)",
        "surrogate": "rpe",
    }
    kwargs, experiment = zoo_kwargs(entry)
    assert experiment == {
        "n_envs": 2,
        "n_timesteps": 256.0,
        "normalize": True,
        "policy": "MlpPolicy",
    }
    assert kwargs["clip_range"](0.5) == pytest.approx(0.1)
    assert kwargs["policy_kwargs"] == {"net_arch": [16, 16], "activation_fn": torch.nn.Tanh}
    model, steps = zoo_model(ENV, entry, seed=0, rpe_beta=0.4)
    assert steps == 256 and model.surrogate == "rpe" and model.rpe_beta == 0.4
    model.learn(steps)
    assert model.logger.name_to_value["train/clip_range"] == 0.0
    assert model.policy.mlp_extractor.policy_net[0].out_features == 16
    assert np.isfinite(params(model).numpy()).all()
    with pytest.raises(ValueError, match=r"`clip_range`: a schedule is 'lin_<number>'"):
        zoo_kwargs({"clip_range": "lin_x"})
    with pytest.raises(ValueError, match=r"`n_envs` must be an int >= 1"):
        zoo_model(ENV, {"n_envs": 0})


# -- issue 56: checked at construction and at load; policy_kwargs read as data -------------
TINY: dict[str, Any] = {"n_steps": 64, "batch_size": 32, "n_epochs": 1, "seed": 0, "device": "cpu"}

# rl-baselines3-zoo's policy_kwargs strings of its PPO entries for PyBullet and MuJoCo tasks
# (hyperparams/ppo.yml), written as rl-zoo3 writes them, newlines and trailing commas kept
ZOO_POLICY_KWARGS = [
    "dict(log_std_init=-2,\n                       ortho_init=False,\n"
    "                       activation_fn=nn.ReLU,\n"
    "                       net_arch=[dict(pi=[256, 256], vf=[256, 256])]\n"
    "                       )",  # HalfCheetahBulletEnv-v0, Walker2DBulletEnv-v0, ...
    "dict(log_std_init=-1, ortho_init=False, activation_fn=nn.ReLU, "
    "net_arch=[dict(pi=[256, 256], vf=[256, 256])])",  # AntBulletEnv-v0
    "dict(log_std_init=-2.7, ortho_init=False, activation_fn=nn.ReLU, "
    "net_arch=[dict(pi=[256, 256], vf=[256, 256])])",  # ReacherBulletEnv-v0
    "dict(\n                    log_std_init=-2,\n                    ortho_init=False,\n"
    "                    activation_fn=nn.ReLU,\n"
    "                    net_arch=[dict(pi=[256, 256], vf=[256, 256])]\n"
    "                  )",  # HalfCheetah-v3, Hopper-v3, Humanoid-v3, HumanoidStandup-v3
    "dict(log_std_init=-2, ortho_init=False, activation_fn=nn.ReLU, "
    "net_arch=dict(pi=[256, 256], vf=[256, 256]))",  # the same in SB3 >= 1.8's form
    "dict(log_std_init=-3.29, ortho_init=False)",  # MountainCarContinuous-v0
    "dict(log_std_init=-2,\n ortho_init=False,\n activation_fn=nn.GELU,\n"
    " net_arch=[dict(pi=[256], vf=[256])],\n )",  # CarRacing-v0
    "dict(net_arch=[16, 16], activation_fn=nn.Tanh)",
    "{'net_arch': (64, 64), 'activation_fn': nn.SiLU, 'squash_output': True, 'x': None}",
    "dict(activation_fn=nn.LeakyReLU, net_arch=[], log_std_init=+0.5, full_std=1e-3)",
]


@pytest.mark.parametrize("text", ZOO_POLICY_KWARGS)
def test_zoo_policy_kwargs_read_to_what_rl_zoo3s_eval_gives(text: str) -> None:
    """The values rl-zoo3 (and pporpe before) got with eval(text, {"dict": dict, "nn":
    torch.nn}): equal, lists as lists, tuples as tuples, nn classes the same objects."""
    expected = eval(text, {"__builtins__": {}}, {"dict": dict, "nn": torch.nn})

    def shape(x: Any) -> Any:  # the value with every container's type spelled out
        if isinstance(x, dict):
            return ("dict", [(k, shape(v)) for k, v in x.items()])
        if isinstance(x, list | tuple):
            return (type(x).__name__, [shape(v) for v in x])
        return (type(x), x)

    got = zoo_kwargs({"policy_kwargs": text})[0]["policy_kwargs"]
    assert shape(got) == shape(expected)


def test_a_policy_kwargs_string_that_would_run_a_command_runs_nothing(tmp_path: Path) -> None:
    marker, control = tmp_path / "MARKER", tmp_path / "CONTROL"
    hostile = "dict(x=nn.functional.torch.os.system('touch {}'))"
    # the string is live: evaluated as rl-zoo3 (and pporpe before) did, it runs the command
    eval(hostile.format(control), {"__builtins__": {}}, {"dict": dict, "nn": torch.nn})
    assert control.exists()
    with pytest.raises(ValueError) as refused:
        zoo_kwargs({"policy_kwargs": hostile.format(marker)})
    line = str(refused.value)
    assert line.startswith("`policy_kwargs`: \"nn.functional.torch.os.system('touch ")
    assert "(line 1, column 8) is not allowed; only dict(key=value, ...)" in line
    assert "\n" not in line and not marker.exists()
    with pytest.raises(ValueError, match="policy_kwargs"):
        zoo_model("NoSuchEnv-v0", {"policy_kwargs": hostile.format(marker)})
    assert not marker.exists()


@pytest.mark.parametrize(
    "text",
    [
        "__import__('os').system('true')",
        "dict(x=getattr(nn, 'ReLU'))",
        "dict(**{'a': 1})",
        "{**{'a': 1}}",
        "dict([('a', 1)])",
        "dict(a=[x for x in range(3)])",
        "dict(a=nn.Module)",
        "dict(a=torch.nn.ReLU)",
        "dict(a=nn.ReLU())",
        "dict(a='x' * 10**10)",  # an operator, never computed
        "dict(a=lambda: 0)",
        "dict(a=-'x')",
        "dict(a=1j)",
        "dict(a=b'x')",
        "dict(a=...)",
        "dict(a=[*b])",
        "dict(a=(yield))",
        "[" * 40 + "]" * 40,  # nested deeper than 32
        "[" * 1000 + "]" * 1000,  # deeper than Python's parser goes
        "dict(a=1",  # not an expression
        "x" * 20_000,
        "[1, 2, 3]",  # not a dict
    ],
)
def test_anything_else_in_policy_kwargs_is_refused_in_one_line(text: str) -> None:
    with pytest.raises(ValueError, match=r"^`policy_kwargs`") as refused:
        zoo_kwargs({"policy_kwargs": text})
    assert "\n" not in str(refused.value)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"clip_range": "lin_1.5"}, r"^`clip_range` \(the paper's eps\) lin_1.5 goes from 1.5 to "
         r"0; its start must be in \(0, 1\)"),
        ({"clip_range": "lin_x"}, r"^`clip_range`: a schedule is 'lin_<number>'; got 'lin_x'"),
        ({"clip_range": "lin_nan"}, r"^`clip_range`: a schedule is 'lin_<number>'"),
        ({"clip_range": lambda p: 1.5 * p}, r"^`clip_range` \(a schedule, the paper's eps\) must "
         r"give values in \[0, 1\) for pporpe's surrogates; got 1.5 at progress_remaining=1"),
        ({"clip_range": lambda p: 0.2 if p > 0.5 else -0.1}, r"got -0.1 at progress_remaining=0.5"),
        ({"clip_range": lambda p: 0.2 / int(p > 0.35)}, r"^`clip_range` \(a schedule\) failed at "
         r"progress_remaining=0.3: float division by zero"),
        ({"surrogate": "rpe", "rpe_beta": 0.9, "clip_range": "lin_0.2"},
         r"clip_range=lin_0.2: with this clip_range rpe_beta must be < 0.833333"),
    ],
)  # fmt: skip
def test_a_bad_clip_range_schedule_is_refused_at_construction(
    kwargs: dict[str, Any], match: str
) -> None:
    with pytest.raises(ValueError, match=match):  # the env does not exist: nothing was built
        PPO("MlpPolicy", "NoSuchEnv-v0", **kwargs)
    entry = {k: v for k, v in kwargs.items() if isinstance(v, str | float)}
    if isinstance(kwargs["clip_range"], str):  # the same through an rl-zoo3 entry
        with pytest.raises(ValueError, match=match):
            zoo_model("NoSuchEnv-v0", entry)


def test_a_zoo_schedule_string_is_a_clip_range_like_rl_zoo3s() -> None:
    model = PPO("MlpPolicy", ENV, clip_range="lin_0.2", learning_rate="lin_1e-3", **TINY)
    assert model.clip_range(0.5) == pytest.approx(0.1) and model.clip_range(0.0) == 0.0
    assert model.lr_schedule(0.25) == pytest.approx(2.5e-4)
    assert PPO("MlpPolicy", ENV, clip_range=lambda p: 0.3 * p, **TINY).clip_range(1.0) == 0.3


def test_a_schedule_leaving_the_range_between_checks_stops_the_update_naming_it() -> None:
    model = PPO("MlpPolicy", ENV, **TINY)
    model.clip_range = lambda p: 1.5  # set after the checks
    with pytest.raises(ValueError, match=r"^`clip_range` \(a schedule, the paper's eps\)"):
        model.learn(TINY["n_steps"])


@pytest.fixture(scope="module")
def saved(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("sb3") / "rpe"
    PPO("MlpPolicy", ENV, surrogate="rpe", rpe_beta=0.3, clip_range="lin_0.2", **TINY).save(path)
    return path


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"surrogate": "xyz"}, r"^`surrogate` must be one of 'ppo', 'rb', 'rpe'.*; got 'xyz'$"),
        ({"eta": -1.0}, r"^`eta` must be a finite number >= 0"),
        ({"eta": "0.3"}, r"^`eta` must be a finite number >= 0"),
        ({"rpe_beta": 2.0}, r"^`rpe_beta` must be a number in \[0, 1\]; got 2.0"),
        ({"clip_range": 1.5}, r"^`clip_range` \(the paper's eps\) must be in \(0, 1\)"),
        ({"clip_range": "lin_1.5"}, r"^`clip_range` \(the paper's eps\) lin_1.5 goes from 1.5"),
        ({"rpe_beta": 0.9}, r"rpe_beta must be < 0.833333"),  # with the saved lin_0.2
    ],
)
def test_load_checks_the_saved_values_after_custom_objects(
    saved: Path, changes: dict[str, Any], match: str
) -> None:
    with pytest.raises(ValueError, match=match):
        PPO.load(saved, device="cpu", custom_objects=changes)
    with pytest.raises(ValueError, match=match):  # load's keyword arguments, the same
        PPO.load(saved, device="cpu", **changes)


def test_load_takes_good_custom_objects(saved: Path) -> None:
    model = PPO.load(saved, device="cpu")
    assert (model.surrogate, model.rpe_beta, model.clip_range(0.5)) == ("rpe", 0.3, 0.1)
    model = PPO.load(saved, device="cpu", custom_objects={"surrogate": "rb", "eta": 1,
                                                          "clip_range": "lin_0.4"})  # fmt: skip
    assert (model.surrogate, model.eta, model.clip_range(0.5)) == ("rb", 1.0, 0.2)
    assert isinstance(model.eta, float)
