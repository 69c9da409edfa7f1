"""Command-line interface: ``pporpe <command> ...``.

Every command validates its arguments before it builds an environment or starts work.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Any

from .cli_parser import USAGE_ERROR, OneLineParser, bounded_int, subcommand_parser

__all__ = ["build_parser", "main"]

INTERRUPTED_EXIT = 130
"""Exit status after Ctrl-C (128 + SIGINT), as a shell reports a process SIGINT stopped;
after SIGTERM, 143 (128 + SIGTERM)."""


class _CommandInterrupted(KeyboardInterrupt):
    """A command stopped by Ctrl-C or SIGTERM; its message is the one line that says how far
    it got, ``exit_status`` 128 + the signal."""

    def __init__(self, message: str, signum: int | None = None) -> None:
        super().__init__(message)
        self.exit_status = 128 + signum if signum else INTERRUPTED_EXIT


def _cmd_figures(args: argparse.Namespace) -> int:
    from .experiments.reports.figures import draw_analytic_figures

    for path in draw_analytic_figures(args.out, eps=args.eps, beta=args.beta, eta=args.eta):
        print(path)
    return 0


ONLINE_ONLY_RUN_FLAGS = ("episodes",)
"""Flags of the run's settings (:class:`TrainConfig`) that batch PPO does not take: it
trains for ``--steps``."""


def _train_flags() -> tuple[Any, dict[str, Any]]:
    """The generated flags of ``pporpe train`` and their groups: the run's settings
    (:class:`TrainConfig`), the online learner's (:class:`OnlineConfig`) and batch PPO's
    (:class:`BatchConfig`, whose ``total_steps`` is ``--steps``). Budgets and seeds have
    upper bounds (:data:`~pporpe.config.MAX_STEPS`, ``MAX_EPISODES``, ``MAX_SEED``)."""
    from .batch.config import BatchConfig
    from .cli_flags import ConfigFlags, FlagGroup
    from .config import MAX_EPISODES, MAX_EVAL_EPISODES, MAX_SEED, MAX_STEPS
    from .online.config import OnlineConfig, TrainConfig

    # the same settings of a run; checkpoint_every counts episodes of one, updates of the other
    shared = frozenset({"env", "seed", "eval_episodes"})
    groups = {
        "run": FlagGroup("run", TrainConfig, skip=frozenset({"learner"}), label="online"),
        "online": FlagGroup("online learner", OnlineConfig),
        "batch": FlagGroup("batch PPO", BatchConfig, skip=shared, rename={"total_steps": "steps"}),
    }
    bounds = {"steps": MAX_STEPS, "episodes": MAX_EPISODES, "eval_episodes": MAX_EVAL_EPISODES,
              "seed": MAX_SEED}  # fmt: skip
    return ConfigFlags(list(groups.values()), bounds), groups


def _train_help_sections(flags: Any, groups: dict[str, Any]) -> list[tuple[str, list[str]]]:
    """``pporpe train --help``'s sections: the flags both learner kinds take, then those
    only the online learner takes, then those only batch PPO takes."""
    takers: dict[str, list[str]] = {"common": [], "online": [], "batch": []}
    for flag, owners in flags.owners.items():
        mine = {group for group, _ in owners}
        online = bool(mine & {groups["run"], groups["online"]})
        batch = bool(mine & {groups["run"], groups["batch"]}) and flag not in ONLINE_ONLY_RUN_FLAGS
        takers["common" if online and batch else "online" if online else "batch"].append(flag)
    return [
        ("common settings (both learners)", takers["common"]),
        ("online learner settings (--learner online, the default)", takers["online"]),
        ("batch learner settings (--learner batch: batch PPO)", takers["batch"]),
    ]


def _refuse_other_kinds_flags(args: argparse.Namespace, flags: Any, own: set[Any]) -> None:
    """A flag that no group of this learner kind has is an error naming it."""
    for flag in flags.given(args):
        if not any(group in own for group, _ in flags.owners[flag]):
            kinds = " / ".join(g.name for g, _ in flags.owners[flag])
            raise ValueError(f"--{flag.replace('_', '-')} applies to the {kinds} only")


def _online_config(args: argparse.Namespace) -> object:
    from .cli_flags import values_for
    from .online.config import OnlineConfig, TrainConfig

    flags, groups = _train_flags()
    _refuse_other_kinds_flags(args, flags, {groups["run"], groups["online"]})
    run = values_for(flags, args, groups["run"])
    if "steps" in run and "episodes" not in run:
        run["episodes"] = None  # a budget in steps instead of the default 200 episodes
    learner = OnlineConfig(**values_for(flags, args, groups["online"]))
    return TrainConfig(**run, learner=learner)


def _batch_config(args: argparse.Namespace) -> object:
    from .batch.config import zoo_config
    from .cli_flags import values_for

    flags, groups = _train_flags()
    for flag in ONLINE_ONLY_RUN_FLAGS:
        if hasattr(args, flag):
            raise ValueError(
                f"--learner batch trains for --steps (environment steps), not --{flag}"
            )
    _refuse_other_kinds_flags(args, flags, {groups["run"], groups["batch"]})
    run = values_for(flags, args, groups["run"])
    run.pop("steps", None)
    overrides = {**run, **values_for(flags, args, groups["batch"])}
    # per-task defaults (rl-baselines3-zoo where it has the task), then the given options
    return zoo_config(overrides.pop("env", "pendulum"), **overrides)


_CONFIG_FROM_ARGS = {"online": _online_config, "batch": _batch_config}
"""How ``pporpe train`` options become the run configuration of each learner kind."""


def _cmd_train(args: argparse.Namespace) -> int:
    from .envs import resolve_env_id
    from .evaluation import check_mujoco_gl

    # validate everything before any environment is built
    cfg: Any = _CONFIG_FROM_ARGS[args.learner](args)
    resolve_env_id(cfg.env)
    check_mujoco_gl(cfg.env)
    _check_task(cfg.env)  # before --force removes anything
    if args.force:  # the new run's task builds, then the old run's files go (none via a link)
        from .runs.folder import clear_run_dir

        clear_run_dir(args.out)
    result = _train_until_interrupted(cfg, args.out, progress=not args.quiet)
    if result.already_done:
        print(f"already done: {result.run_dir} holds this run, complete (--force starts over)")
    trained = _trained_line(result, batch=args.learner == "batch")
    if trained:
        print(trained)
    if result.evaluation is not None:
        _print_eval(result.evaluation)
    print(f"run folder: {result.run_dir}")
    return 0


def _check_task(env: str) -> None:
    """Build the task once: one that cannot be built (a removed version such as Hopper-v3,
    a missing package, discrete actions) is refused naming it."""
    from .envs import make_env

    try:
        make_env(env).close()
    except (ValueError, ImportError) as exc:
        if env in str(exc):
            raise
        error = ImportError if isinstance(exc, ImportError) else ValueError
        raise error(f"task {env!r}: {exc}") from None


def _trained_line(result: Any, batch: bool) -> str:
    """What a run trained, in how long; an online run's last return (empty when it
    trained no episode)."""
    from .text import count, fixed

    steps, seconds, episodes = result.total_steps, result.train_time, len(result.records)
    rate = f"{steps / max(seconds, 1e-9):.0f} steps/s"
    if batch:
        return (
            f"trained {count(steps, 'step')} ({count(result.chunks, 'update')}, "
            f"{count(episodes, 'episode')}) in {seconds:.1f} s ({rate})"
        )
    if not result.records:
        return ""
    return (
        f"trained {count(episodes, 'episode')}, {count(steps, 'step')} in {seconds:.1f} s "
        f"({rate}); last return {fixed(result.records[-1].ret, 1)}"
    )


def _train_until_interrupted(cfg: Any, out: str, progress: bool) -> Any:
    """``train``, where Ctrl-C stops the run at its next step with a checkpoint there."""
    from .runs.loop import train
    from .runs.stopping import Interrupted, stop_on_signals

    try:
        with stop_on_signals() as stop:
            return train(cfg, out, progress=progress, stop=stop)
    except Interrupted as exc:
        episodes = max(exc.episodes.values(), default=0)
        raise _CommandInterrupted(
            f"interrupted at episode {episodes} (checkpointed); resume with the same command",
            stop.signum,
        ) from None


def _print_eval(ev: object) -> None:
    from .evaluation import EvalResult
    from .text import count, fixed

    assert isinstance(ev, EvalResult)
    print(
        f"test return over {count(ev.episodes, 'episode')}: median {fixed(ev.median)}, "
        f"mean {fixed(ev.mean)}, IQR {fixed(ev.iqr)} [{fixed(ev.q25)}, {fixed(ev.q75)}]"
    )


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from pathlib import Path

    from .evaluation import (
        EVAL_SEED_OFFSET,
        check_mujoco_gl,
        check_video_support,
        evaluate_policy,
    )
    from .io import atomic_write_json
    from .runs.folder import read_config
    from .runs.links import refuse_links
    from .runs.loop import load_policy
    from .text import count

    if args.video is not None:
        if args.video_episodes > args.episodes:
            raise ValueError(
                f"--video-episodes must be in [1, --episodes={args.episodes}]; "
                f"got {args.video_episodes}"
            )
        check_video_support()  # before any work
        if Path(args.video).exists() and not Path(args.video).is_dir():
            raise ValueError(f"--video must be a folder; {args.video} is a file")
    check_mujoco_gl(read_config(args.run_dir)[1].env)  # before MuJoCo is imported
    refuse_links(args.run_dir, ["evaluation.json"])  # written at the end, never via a link
    policy = load_policy(args.run_dir)  # any learner kind, any pporpe version's folder
    cfg = policy.config
    seed = cfg.seed + EVAL_SEED_OFFSET if args.seed is None else args.seed
    ev = evaluate_policy(
        policy,
        cfg.env,
        args.episodes,
        seed,
        video_dir=args.video,
        video_episodes=args.video_episodes,
        progress=not args.quiet,
    )
    _print_eval(ev)
    out = Path(args.run_dir) / "evaluation.json"
    try:
        atomic_write_json(out, {**ev.to_dict(), "seed": seed})
    except OSError as exc:  # a read-only folder: the returns are printed, not lost
        print("test returns (not saved): " + " ".join(map(repr, ev.returns)))
        unsaved = f"could not save the test returns in {out}: {exc.strerror or exc}"
    else:
        print(f"saved {out}")
        unsaved = ""
    if args.video is not None:
        videos = sorted(Path(args.video).glob("*.mp4"))
        names = ", ".join(v.name for v in videos)
        print(f"recorded {count(len(videos), 'video')} in {args.video}: {names}")
    if unsaved:
        raise ValueError(f"{unsaved} (the returns are printed above)")
    return 0


def _cmd_reproduce(args: argparse.Namespace) -> int:
    from .evaluation import check_mujoco_gl
    from .experiments.grids.spec import load_spec, select_runs
    from .text import count

    spec = load_spec(args.spec)  # every run is validated before any starts
    for env in spec.envs:
        check_mujoco_gl(env)
    whole = spec
    if args.tasks or args.methods or args.seeds:  # one chunk of the grid, or one cell
        spec = select_runs(spec, args.tasks, args.methods, args.seeds)
    seeds = count(len({r.seed for r in spec.runs}), "seed")
    print(
        f"grid {spec.name!r}: {count(len(spec.runs), 'run')} ({', '.join(spec.methods)} x "
        f"{', '.join(spec.envs)} x {seeds}) -> {args.out}"
    )
    outcome = _reproduce_until_interrupted(spec, whole, args)
    were = "was" if len(outcome.skipped) == 1 else "were"
    print(
        f"{count(len(outcome.done), 'run')} done ({len(outcome.skipped)} {were} already "
        f"done), {len(outcome.failed)} failed, in {outcome.wall_time:.1f} s"
    )
    for key, err in outcome.failed.items():
        print(f"FAILED {key}: {err} (traceback in {args.out}/{key}/error.txt)")
    if args.report:
        _report(args.out)
    return 0 if outcome.ok else 1


def _reproduce_until_interrupted(spec: Any, whole: Any, args: argparse.Namespace) -> Any:
    """``reproduce``, where Ctrl-C or SIGTERM stops every running run at its next step with
    a checkpoint there (a second signal stops at once)."""
    from pathlib import Path

    from .experiments.grids.reproduce import (
        DEFAULT_CHECKPOINT_SECONDS,
        DEFAULT_POPULATION,
        reproduce,
    )
    from .runs.stopping import StopRequest, stop_on_signals

    every = args.checkpoint_seconds
    stop = StopRequest()
    try:
        with stop_on_signals() as stop:
            outcome = reproduce(
                spec, args.out, backend=args.backend, workers=args.workers,
                address=args.address, progress=not args.quiet,
                population=args.population or DEFAULT_POPULATION,
                checkpoint_seconds=DEFAULT_CHECKPOINT_SECONDS if every is None else every,
                whole=whole, stop=stop,
            )  # fmt: skip
    except KeyboardInterrupt:
        outcome = None
    if outcome is None or outcome.interrupted:
        done = sum((Path(args.out) / run.key / "done.json").exists() for run in spec.runs)
        raise _CommandInterrupted(
            f"interrupted: {done} of {len(spec.runs)} runs done; resume with the same command",
            stop.signum,
        )
    return outcome


def _report(out: str) -> None:
    from .experiments.reports.report import write_report

    paths = write_report(out)
    print(paths[0].read_text())
    print("wrote " + ", ".join(str(p) for p in paths))


def _cmd_report(args: argparse.Namespace) -> int:
    _report(args.dir)
    return 0


_positive_int = bounded_int(None, low=1)


def _nonneg_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}") from None
    if not (value >= 0.0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0, got {text!r}")
    return value


def _add_figures(sub: Any) -> None:
    """The ``pporpe figures`` subcommand."""
    fig = sub.add_parser(
        "figures", help="draw the paper's analytic figures (relative ratio, negative loss)"
    )
    fig.add_argument(
        "--out",
        default="results/figures",
        help="output folder (PNG and PDF) [default: %(default)s]",
    )
    fig.add_argument(
        "--eps", type=float, default=0.1, help="threshold eps in (0, 1) [default: %(default)s]"
    )
    fig.add_argument(
        "--beta",
        type=float,
        default=0.5,
        help="RPE mixture ratio beta in [0, 1] [default: %(default)s]",
    )
    fig.add_argument(
        "--eta", type=float, default=0.3, help="PPO-RB rollback eta >= 0 [default: %(default)s]"
    )
    fig.set_defaults(func=_cmd_figures)


def _add_train(sub: Any) -> None:
    """The ``pporpe train`` subcommand."""
    tr = sub.add_parser(
        "train",
        help="train on one task: the paper's online learner or batch PPO",
        description="Train one run. Every setting of the run, of the online learner and of "
        "batch PPO is a flag; a flag not given keeps its config's default (for batch PPO, "
        "rl-baselines3-zoo's per-task defaults where it has the task).",
    )
    tr.add_argument(
        "--learner",
        choices=["online", "batch"],
        default="online",
        help="online (the paper's Alg. 1, default) or batch (rollouts + minibatch epochs)",
    )
    tr.add_argument("--out", required=True, help="run folder (resumes if it holds a checkpoint)")
    tr.add_argument(
        "--force",
        action="store_true",
        help="start over: remove a previous run's files from --out first",
    )
    tr.add_argument("--quiet", action="store_true", help="no progress bar")
    flags, groups = _train_flags()
    flags.add_to(tr, _train_help_sections(flags, groups))
    tr.set_defaults(func=_cmd_train)


def _add_evaluate(sub: Any) -> None:
    """The ``pporpe evaluate`` subcommand."""
    from .config import MAX_EVAL_EPISODES, MAX_SEED

    ev = sub.add_parser("evaluate", help="test a trained run: median, mean and IQR of returns")
    ev.add_argument("run_dir", help="run folder written by `pporpe train`")
    ev.add_argument(
        "--episodes",
        type=bounded_int(MAX_EVAL_EPISODES, low=1),
        default=50,
        help="test episodes (default 50)",
    )
    ev.add_argument(
        "--seed",
        type=bounded_int(MAX_SEED, low=0),
        default=None,
        help="environment seed (default: training seed + 1000003)",
    )
    ev.add_argument(
        "--video",
        metavar="DIR",
        default=None,
        help='record test episodes as MP4 into DIR (needs pip install "pporpe[video]"; '
        "default: no video)",
    )
    ev.add_argument(
        "--video-episodes",
        type=_positive_int,
        default=1,
        help="with --video: how many of the first test episodes to record (default 1)",
    )
    ev.add_argument("--quiet", action="store_true", help="no progress bar")
    ev.set_defaults(func=_cmd_evaluate)


def _add_reproduce(sub: Any) -> None:
    """The ``pporpe reproduce`` subcommand."""
    from .config import MAX_SEED
    from .experiments.grids.reproduce import DEFAULT_POPULATION

    rp = sub.add_parser("reproduce", help="run a methods x tasks x seeds grid from a TOML spec")
    rp.add_argument("spec", help="grid spec, e.g. experiments/quick.toml or experiments/paper.toml")
    rp.add_argument("--out", required=True, help="results folder (re-run to resume)")
    rp.add_argument(
        "--backend",
        choices=["local", "ray"],
        default="local",
        help="local process pool (default) or an existing Ray cluster",
    )
    rp.add_argument(
        "--workers",
        type=_positive_int,
        default=None,
        help="local worker processes (default: number of cores)",
    )
    rp.add_argument(
        "--address",
        default=None,
        help="Ray cluster address HOST:PORT (default: RAY_ADDRESS or a local Ray)",
    )
    rp.add_argument(
        "--population",
        type=_positive_int,
        default=None,
        help=(
            f"runs of one task and network shape (online or batch) trained at once by one "
            f"worker (default {DEFAULT_POPULATION}, the fused online engine's best; 30 for "
            f"the torch engine; batch runs gain up to 30 too)"
        ),
    )
    rp.add_argument(
        "--checkpoint-seconds",
        type=_nonneg_float,
        default=None,
        help="least seconds between two checkpoints of a population asked for by the spec's "
        "checkpoint_every (default 60); whatever the count, every run is also checkpointed "
        "30 s into the command, 1 min later, then every 2 min",
    )
    rp.add_argument("--tasks", nargs="+", metavar="TASK", help="only these tasks (default: all)")
    rp.add_argument("--methods", nargs="+", metavar="METHOD", help="only these (default: all)")
    rp.add_argument(
        "--seeds",
        nargs="+",
        type=bounded_int(MAX_SEED, low=0),
        default=None,
        metavar="SEED",
        help="only these seeds (default: all)",
    )
    rp.add_argument("--report", action="store_true", help="write the report when done")
    rp.add_argument("--quiet", action="store_true", help="no progress bar")
    rp.set_defaults(func=_cmd_reproduce)


def _add_report(sub: Any) -> None:
    """The ``pporpe report`` subcommand."""
    rep = sub.add_parser("report", help="summary table and figures of a grid's results")
    rep.add_argument("dir", help="results folder written by `pporpe reproduce`")
    rep.set_defaults(func=_cmd_report)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``pporpe`` command."""
    parser = OneLineParser(
        prog="pporpe",
        description="PPO-RPE, PPO and PPO-RB: train, evaluate and reproduce the paper.",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    _add_figures(sub)
    _add_train(sub)
    _add_evaluate(sub)
    _add_reproduce(sub)
    _add_report(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``pporpe`` console script."""
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra:  # named by the subcommand's parser: "pporpe train: error: ..."
        subcommand_parser(parser, args.command).error(f"unrecognized arguments: {' '.join(extra)}")
    try:
        return int(args.func(args))
    except (ValueError, ImportError) as exc:  # ImportError: an optional extra is missing
        print(f"pporpe {args.command}: error: {exc}", file=sys.stderr)
        return USAGE_ERROR
    except OSError as exc:  # a full disk, a vanished folder: the files written so far stay
        where = f": {exc.filename}" if exc.filename else ""
        print(f"pporpe {args.command}: error: {exc.strerror or exc}{where}", file=sys.stderr)
        return USAGE_ERROR
    except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM: one line, never a traceback
        if isinstance(exc, _CommandInterrupted):
            print(f"pporpe {args.command}: {exc}", file=sys.stderr)
            return exc.exit_status
        print(
            f"pporpe {args.command}: interrupted; the work since the last checkpoint is lost; "
            "resume with the same command",
            file=sys.stderr,
        )
        return INTERRUPTED_EXIT


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
