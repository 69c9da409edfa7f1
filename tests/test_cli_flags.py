"""``pporpe train``'s flags are generated from the config dataclasses: every field is a
flag whose help is its docstring and whose value reaches the config; a flag not given keeps
the config's default, which differs between the learner kinds."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import warm_process

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


# -- issue 56: one line, every time; help by who takes a flag; bounded budgets -------------
HINT = "({} --help for the options)"


@pytest.mark.parametrize(
    ("argv", "line"),
    [
        (["train", "--method", "trpo", "--out", "x"],
         "pporpe train: error: argument --method: invalid choice 'trpo' (choose from ppo, rb, "
         "rpe, spo)"),
        (["reproduce", "spec.toml", "--out", "x", "--workers", "0"],
         "pporpe reproduce: error: argument --workers: must be an int >= 1; got 0"),
        (["reproduce", "spec.toml", "--out", "x", "--backend", "mars"],
         "pporpe reproduce: error: argument --backend: invalid choice 'mars' (choose from "
         "local, ray)"),
        (["evaluate"], "pporpe evaluate: error: the following arguments are required: run_dir"),
        (["evaluate", "r", "--episodes", "x"],
         "pporpe evaluate: error: argument --episodes: expected an int, got 'x'"),
        (["figures", "--eps", "x"], "pporpe figures: error: argument --eps: invalid float value: "
         "'x'"),
        (["report"], "pporpe report: error: the following arguments are required: dir"),
        (["train", "--out", "x", "--bogus", "1"],
         "pporpe train: error: unrecognized arguments: --bogus 1"),
        ([], "pporpe: error: the following arguments are required: command"),
        (["trpo"], "pporpe: error: argument command: invalid choice 'trpo' (choose from figures, "
         "train, evaluate, reproduce, report)"),
        # budgets far beyond any real use, and seeds past the bound, name the flag and bound
        (["train", "--out", "x", "--steps", str(10**20)],
         "pporpe train: error: argument --steps: must be at most 1,000,000,000; got "
         "100000000000000000000"),
        (["train", "--out", "x", "--learner", "batch", "--steps", str(10**12)],
         "pporpe train: error: argument --steps: must be at most 1,000,000,000; got "
         "1000000000000"),
        (["train", "--out", "x", "--episodes", str(10**9)],
         "pporpe train: error: argument --episodes: must be at most 1,000,000; got "
         "1000000000"),
        (["train", "--out", "x", "--eval-episodes", str(10**9)],
         "pporpe train: error: argument --eval-episodes: must be at most 10,000; got "
         "1000000000"),
        (["train", "--out", "x", "--seed", str(10**30)],
         "pporpe train: error: argument --seed: must be at most 4,294,967,295; got "
         "100000000000... (31 characters)"),
        (["evaluate", "r", "--episodes", str(10**20)],
         "pporpe evaluate: error: argument --episodes: must be at most 10,000; got "
         "100000000000000000000"),
        (["evaluate", "r", "--seed", "-1"],
         "pporpe evaluate: error: argument --seed: must be an int >= 0; got -1"),
        (["reproduce", "s", "--out", "o", "--seeds", "1", str(2**32)],
         "pporpe reproduce: error: argument --seeds: must be at most 4,294,967,295; got "
         "4294967296"),
    ],
)  # fmt: skip
def test_a_refused_command_line_is_one_line_and_a_hint(
    capsys: pytest.CaptureFixture[str], argv: list[str], line: str
) -> None:
    with pytest.raises(SystemExit) as stopped:
        main(argv)
    prog = line.split(": error: ")[0]
    assert stopped.value.code == 2
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [line, HINT.format(prog)] and captured.out == ""


def test_the_console_command_prints_no_usage_block(tmp_path: Path) -> None:
    """What a user sees: argparse printed 40 lines of usage for a wrong --method."""
    proc = warm_process.run(["train", "--method", "trpo", "--out", str(tmp_path / "x")],
                            timeout=120)  # fmt: skip
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.splitlines() == [
        "pporpe train: error: argument --method: invalid choice 'trpo' "
        "(choose from ppo, rb, rpe, spo)",
        "(pporpe train --help for the options)",
    ]
    assert not (tmp_path / "x").exists()


def test_budgets_at_the_bound_are_taken() -> None:
    from pporpe.config import MAX_EPISODES, MAX_SEED, MAX_STEPS

    args = parse("--steps", str(MAX_STEPS), "--seed", str(MAX_SEED))
    assert (args.steps, args.seed) == (MAX_STEPS, MAX_SEED)  # type: ignore[attr-defined]
    assert parse("--episodes", str(MAX_EPISODES)).episodes == MAX_EPISODES  # type: ignore[attr-defined]
    assert parse("--steps", "none").steps is None  # type: ignore[attr-defined]


def help_sections(command: str) -> dict[str, str]:
    """Title -> the text of each section of ``pporpe <command> --help``."""
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    text = sub.choices[command].format_help()  # type: ignore[attr-defined]
    sections: dict[str, str] = {}
    title = ""
    for line in text.splitlines():
        if line and not line.startswith(" ") and line.endswith(":"):
            title = line[:-1]
            sections[title] = ""
        elif title:
            sections[title] += line + "\n"
    return sections


def flags_in(section: str) -> set[str]:
    """The flags a help section defines (the first word of the lines that start one)."""
    return {line.split()[0].rstrip(",") for line in section.splitlines()
            if line.startswith("  --")}  # fmt: skip


def test_train_help_groups_the_flags_by_the_learners_that_take_them() -> None:
    """--method, --eps, --lr and --layers were under "online learner settings", though
    batch PPO takes them too. Each section's flags are what the learner kinds accept."""
    sections = help_sections("train")
    common = flags_in(sections["common settings (both learners)"])
    online = flags_in(sections["online learner settings (--learner online, the default)"])
    batch = flags_in(sections["batch learner settings (--learner batch: batch PPO)"])
    assert {"--method", "--eps", "--lr", "--layers", "--units", "--steps", "--seed"} <= common
    assert {"--episodes", "--kappa", "--lambdas"} <= online and "--eps" not in online
    assert {"--n-envs", "--gae-lambda", "--target-kl"} <= batch
    flags, _ = _train_flags()
    assert len(common) + len(online) + len(batch) == len(flags.owners)
    assert common | online | batch == {"--" + f.replace("_", "-") for f in flags.owners}
    for section, refused_by in ((online, "batch"), (batch, "online"), (common, None)):
        for flag in section:
            for learner in ("online", "batch"):
                args = parse("--learner", learner)
                setattr(args, flag[2:].replace("-", "_"), object())  # given, of no use
                build = _online_config if learner == "online" else _batch_config
                try:
                    build(args)
                    message = ""
                except Exception as exc:  # the value, of no use, may be refused anyhow
                    message = str(exc)
                about_kind = "applies to the" in message or "not --episodes" in message
                assert about_kind == (learner == refused_by), (flag, learner, message)


@pytest.mark.parametrize("command", ["train", "figures", "evaluate", "reproduce"])
def test_every_option_shows_its_default(command: str) -> None:
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    for action in sub.choices[command]._actions:  # type: ignore[attr-defined]
        if not action.option_strings or action.required or action.nargs == 0:
            continue  # positional, required (--out), a switch (--force, --quiet), --help
        text = action.help or ""
        assert "default" in text, (command, action.option_strings, text)
    shown = " ".join(help_sections("figures")["options"].split())
    assert "[default: results/figures]" in shown and "[default: 0.1]" in shown
