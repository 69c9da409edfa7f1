"""``pporpe train``'s flags are generated from the config dataclasses: every field is a
flag whose help is its docstring and whose value reaches the config; a flag not given keeps
the config's default, which differs between the learner kinds."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from pporpe.batch.config import BatchConfig
from pporpe.cli import _batch_config, _online_config, _train_flags, build_parser, main
from pporpe.cli_flags import field_docs
from pporpe.online.config import TESTBED, OnlineConfig, TrainConfig


def train_help() -> str:
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    return " ".join(sub.choices["train"].format_help().split())  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    ("cls", "skip", "rename"),
    [
        (OnlineConfig, set(), {}),
        (TrainConfig, {"learner"}, {}),
        (BatchConfig, set(), {"total_steps": "steps"}),
    ],
)
def test_every_config_field_is_a_flag_with_its_docstring(
    cls: type, skip: set[str], rename: dict[str, str]
) -> None:
    text = train_help()
    docs = field_docs(cls)
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        flag = "--" + rename.get(f.name, f.name).replace("_", "-")
        assert flag in text, flag
        first_words = " ".join(docs[f.name].replace("``", "").split()[:4])
        assert first_words in text, (f.name, first_words)


def parse(*argv: str) -> object:
    return build_parser().parse_args(["train", "--out", "x", *argv])


def test_given_flags_reach_the_config_and_others_keep_its_defaults() -> None:
    argv = ["--lambdas", "0.4", "0.8", "--policy-gradient", "weighted_score", "--no-compile",
            "--reward-scale", "none", "--seed", "3"]  # fmt: skip
    cfg = _online_config(parse(*argv))
    assert isinstance(cfg, TrainConfig)
    assert cfg.learner.lambdas == (0.4, 0.8) and cfg.learner.policy_gradient == "weighted_score"
    assert cfg.learner.compile is False and cfg.learner.reward_scale is None and cfg.seed == 3
    assert cfg.learner.eps == OnlineConfig().eps and cfg.episodes == 200
    steps = _online_config(parse("--steps", "500"))
    assert isinstance(steps, TrainConfig) and (steps.episodes, steps.steps) == (None, 500)
    batch = _batch_config(parse("--learner", "batch", "--steps", "256", "--gae-lambda", "0.9"))
    assert isinstance(batch, BatchConfig)
    assert (batch.total_steps, batch.gae_lambda, batch.eps) == (256, 0.9, BatchConfig().eps)
    assert batch.eps != OnlineConfig().eps  # each kind's own default


def test_method_spo_reaches_both_learners_and_the_help_lists_it() -> None:
    online = _online_config(parse("--method", "spo", "--eps", "0.2"))
    assert isinstance(online, TrainConfig) and online.learner.method == "spo"
    batch = _batch_config(parse("--learner", "batch", "--method", "spo"))
    assert isinstance(batch, BatchConfig) and batch.method == "spo"
    assert "--method {ppo,rb,rpe,spo}" in train_help()
    assert "Simple Policy Optimization" in train_help()


def test_the_testbed_preset_as_flags() -> None:
    """Every TESTBED setting can be given on the command line."""
    argv: list[str] = []
    for name, value in TESTBED.items():
        flag = "--" + name.replace("_", "-")
        if isinstance(value, bool):
            argv.append(flag if value else "--no-" + name.replace("_", "-"))
        elif isinstance(value, tuple):
            argv += [flag, *map(str, value)]
        else:
            argv += [flag, "none" if value is None else str(value)]
    cfg = _online_config(parse(*argv))
    assert isinstance(cfg, TrainConfig) and cfg.learner == OnlineConfig(**TESTBED)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--n-envs", "2"], "--n-envs applies to the batch PPO only"),
        (["--learner", "batch", "--kappa", "2"], "--kappa applies to the online learner only"),
        (["--learner", "batch", "--episodes", "3"], "--steps"),
        (["--lambdas", "0.5", "2"], "lambdas"),
        (["--min-scale", "0"], "min_scale"),
    ],
)
def test_a_flag_of_the_other_kind_or_a_bad_value_is_refused_before_work(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], message: str
) -> None:
    out = tmp_path / "never"
    assert main(["train", *argv, "--out", str(out)]) == 2
    assert message in capsys.readouterr().err and not out.exists()


def test_shared_flags_have_one_type() -> None:
    flags, groups = _train_flags()
    shared = [f for f, owners in flags.owners.items() if len(owners) > 1]
    assert {"method", "eps", "gamma", "lr", "layers", "steps"} <= set(shared)
    assert set(groups) == {"run", "online", "batch"}
