"""pporpe beside the author's own code (GitHub kbys-t/test_et), seed by seed.

Three subcommands, each resumable (a seed whose result file exists is skipped):

``reference``
    runs the author's test bed, unmodified, from a checkout you name, in its own Python
    environment (gym 0.25.2; ``../shared/anchors/testbed/README.md`` or docs/testbed.md say
    how to install it), one seed after another through ``benchmarks/testbed_worker.py``
    (which checkpoints every 10 episodes, so a killed seed resumes)::

        python benchmarks/testbed.py reference --checkout ~/test_et \\
            --python ~/test_et/.venv/bin/python --task swingup --config testbed --seeds 1 2 3

``pporpe``
    runs pporpe's online learner with the matching preset (``--config testbed``:
    :data:`pporpe.online.TESTBED`; ``--config paper``: the same learner with the paper's
    Table I values) for the same seeds, as one population::

        python benchmarks/testbed.py pporpe --task swingup --config testbed --seeds 1 2 ... 10

``summarize``
    reads every result file and writes ``summary.json`` (the versions, the commands and a
    list ``runs`` of ``{"implementation", "task", "config", "seed", "first50_mean",
    "score"}``; score is the median of the 50 test returns), ``summary.md`` (per task and
    config: first-50 mean and score with bootstrap CIs, P(pporpe > test bed) with its CI)
    and ``curves_<task>_<config>.png`` (the two mean learning curves with 95% bands).

Both implementations follow the same protocol: 200 training episodes (the registered
episode limit, 1000 steps), then 50 test episodes acting with the policy's location.
Result files: ``benchmarks/results/testbed/<implementation>/<config>/<task>/seed<N>.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "testbed"
WORKER = HERE / "testbed_worker.py"
TASKS = {
    "pendulum": "InvertedPendulumBulletEnv-v0",
    "swingup": "InvertedPendulumSwingupBulletEnv-v0",
}
IMPLEMENTATIONS = ("pporpe", "testbed")
SIDE_BY_SIDE = ("testbed", "paper")
"""The settings both implementations run: the test bed's own, and the paper's Table I
values passed through the test bed's constructor (``testbed_worker.CONFIGS``)."""

PAIRS = (
    ("testbed", "testbed"),
    ("testbed+fused", "testbed"),
    ("paper", "paper"),
    ("testbed+joint_head", "testbed"),
)
"""(pporpe's settings, the test bed's) compared side by side: each with its own, pporpe's
fused engine with the test bed's settings, and pporpe with its joint head against the
test bed, what that choice alone changes."""

TOWARD_TABLE_I: dict[str, dict[str, Any]] = {
    "lr": {"lr": 3e-4},
    "width": {"units": 100},
    "target": {"tau": 0.3, "nu": 1.0},
    "traces": {"lambdas": (0.5, 0.95), "kappa": 10.0},
    "weights": {"beta_td": 0.01, "beta_de": 0.01, "reward_scale": None},
    "clip": {"policy_gradient": "surrogate"},
}
"""The groups of values where the test bed departs from the paper's Table I, each as the
OnlineConfig fields that give the paper's value: the learning rate, the width, the
t-soft target network (tau 0.3, nu 1), the traces' lambda_max2 and kappa, 0.01 per
regulariser with the reward scaled by 1 - gamma, and PPO's clip on the objective."""

DIAGNOSTIC: dict[str, dict[str, Any]] = {"joint_head": {"head_tensors": "joint"}}
"""Changes of the test bed's settings toward pporpe's own choices, for diagnosis:
``joint_head``, the policy's output layer as one tensor pair for the t-momentum."""

ENGINE: dict[str, dict[str, Any]] = {"fused": {"engine": "fused"}}
"""The implementation of the step, not a setting of the learner: the configs run by
pporpe's torch engine (the engine of the first runs here) unless ``fused`` is added, the
numba kernel (:mod:`pporpe.online.fused_engine`, 5x faster at 60 members). The two agree to
float rounding, so a config and its ``+fused`` twin are the same learner; the path table
compares each config with the baseline of its own engine (:func:`baseline_of`)."""

GROUPS: dict[str, dict[str, Any]] = {**TOWARD_TABLE_I, **DIAGNOSTIC, **ENGINE}
"""Every group a config name may add to ``testbed``, in the order of folder names."""

PAPER_THROUGH_TESTBED: dict[str, Any] = {
    **TOWARD_TABLE_I["lr"],
    **TOWARD_TABLE_I["width"],
    **TOWARD_TABLE_I["traces"],
    "beta_td": 0.01,
    "beta_de": 0.01,
    "reward_scale": 0.0098,
}
"""pporpe's settings for the test bed's ``paper`` run: TESTBED with Table I's values the
test bed's constructor accepts. It has no target network; its TD error carries the two
regularisers with one weight w and a balance b, as w b^2 and w b (1 - b), and scales the
reward by (1 - gamma)(1 - w b), so the paper's 0.01 per term is w = 0.04 with b = 0.5 and
a reward scale of (1 - gamma)(1 - 0.02) = 0.0098 (the test bed cannot scale by 1 - gamma
with the regularisers on)."""


def settings_for(config: str) -> dict[str, Any]:
    """pporpe's learner settings of a config name: ``testbed``, ``paper``, or ``testbed``
    followed by groups of :data:`GROUPS` joined by ``+`` (``testbed+lr+width``).
    Raises ValueError naming what is allowed."""
    from pporpe.online.config import TESTBED

    base = {**TESTBED, "engine": "torch"}  # the committed runs' engine; +fused changes it
    if config == "paper":
        return {**base, **PAPER_THROUGH_TESTBED}
    head, *groups = config.split("+")
    unknown = [g for g in groups if g not in GROUPS]
    if head != "testbed" or unknown or len(set(groups)) != len(groups):
        raise ValueError(
            f"config must be 'paper', 'testbed' or 'testbed' with distinct groups of "
            f"{sorted(GROUPS)} joined by '+'; got {config!r}"
        )
    out = base
    for g in groups:
        out.update(GROUPS[g])
    return out


def canonical_config(config: str) -> str:
    """A config's groups in :data:`GROUPS`' order (its folder name)."""
    settings_for(config)
    head, *groups = config.split("+")
    order = list(GROUPS)
    return "+".join([head, *sorted(groups, key=order.index)])


def baseline_of(config: str) -> str:
    """The run a config is compared with in the path table: ``testbed`` with the config's
    engine group, if any (``testbed+lr+fused`` -> ``testbed+fused``); a ``testbed`` run
    by another engine with the first one (``testbed+fused`` -> ``testbed``: the engine
    check)."""
    groups = config.split("+")[1:]
    engine = [g for g in groups if g in ENGINE]
    if config == "paper" or len(engine) == len(groups):
        return "testbed"
    return "+".join(["testbed", *engine])


def config_arg(text: str) -> str:
    try:
        return canonical_config(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def result_path(implementation: str, config: str, task: str, seed: int, root: Path) -> Path:
    return root / implementation / config / task / f"seed{seed}.json"


def run_reference(args: argparse.Namespace) -> int:
    """The test bed's seeds one after another, each in its own worker process."""
    if not Path(args.python).exists():
        raise SystemExit(f"--python: {args.python} does not exist")
    failed = 0
    for seed in args.seeds:
        out = result_path("testbed", args.config, args.task, seed, args.root)
        if out.exists():
            print(f"seed {seed}: done already ({out})", flush=True)
            continue
        work = args.work / args.config / args.task / f"seed{seed}"
        cmd = [
            str(args.python), str(WORKER), "--checkout", str(args.checkout),
            "--env", TASKS[args.task], "--seed", str(seed), "--config", args.config,
            "--episodes", str(args.episodes), "--tests", str(args.tests),
            "--work", str(work), "--out", str(out),
        ]  # fmt: skip
        env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
               "PYTHONWARNINGS": "ignore"}  # fmt: skip
        print(f"seed {seed}: {' '.join(cmd)}", flush=True)
        rc = subprocess.call(cmd, env=env)
        if rc != 0:
            print(f"seed {seed}: worker exited with {rc}", flush=True)
            failed += 1
    return 1 if failed else 0


def pporpe_spec(config: str, args: argparse.Namespace) -> Any:
    """The grid spec of pporpe's runs with ``config``'s settings for the seeds."""
    from pporpe.experiments.grids.spec import parse_spec

    settings = settings_for(config)
    method = settings.pop("method")
    return parse_spec(
        {
            "name": f"testbed-{config}",
            "methods": [method],
            "seeds": list(args.seeds),
            "eval_episodes": args.tests,
            "learner": {k: list(v) if isinstance(v, tuple) else v for k, v in settings.items()},
            "tasks": [{"env": args.task, "episodes": args.episodes}],
        },
        f"testbed:{config}",
    )


def pporpe_groups(args: argparse.Namespace) -> list[tuple[list[str], list[tuple[str, Any]]]]:
    """pporpe's runs of every ``args.config``, grouped by network shape (the runs one
    population can train): per group, its configs and ``(run_dir, config.json content)``
    of its runs, each under ``<root>/pporpe_runs/<config>/<task>/<method>/seed<N>``."""
    from pporpe.runs.folder import config_json
    from pporpe.runs.kinds import kind_of

    groups: dict[Any, list[tuple[str, str, Any]]] = {}
    for config in args.config:
        for run in pporpe_spec(config, args).runs:
            kind = kind_of(run.config)
            run_dir = args.root / "pporpe_runs" / config / run.key
            groups.setdefault(kind.pack_key(run.config), []).append(
                (config, str(run_dir), config_json(kind, run.config))
            )
    return [
        (list(dict.fromkeys(c for c, _, _ in members)), [(d, j) for _, d, j in members])
        for members in groups.values()
    ]


def run_pporpe(args: argparse.Namespace) -> int:
    """pporpe's learner with each config's settings for the seeds, then one result file
    per finished seed. Runs of every config that share a network shape train as one
    population of up to ``--population`` members (:func:`pporpe_groups`; the run loop:
    checkpoints every minute, a rerun of the same command resumes), so that ``--config
    testbed+lr testbed+target ...`` costs far less than the configs one after another."""
    from pporpe.experiments.grids.backends import run_job
    from pporpe.experiments.grids.reproduce import DEFAULT_CHECKPOINT_SECONDS

    failed = 0
    for configs, runs in pporpe_groups(args):
        home = args.root / "pporpe_runs" / "populations" / f"{args.task}-{'-'.join(configs)}"
        size = min(args.population, len(runs))
        print(f"{len(runs)} runs of {', '.join(configs)}: population of {size}", flush=True)
        status = run_job(str(home), runs, size, DEFAULT_CHECKPOINT_SECONDS)
        failed += sum(s["status"] != "done" for s in status)
    for config in args.config:
        method = settings_for(config)["method"]
        for seed in args.seeds:
            run_dir = args.root / "pporpe_runs" / config / args.task / method / f"seed{seed}"
            export_pporpe_seed(run_dir, args, config, seed)
    return 1 if failed else 0


def export_pporpe_seed(run_dir: Path, args: argparse.Namespace, config: str, seed: int) -> None:
    """A finished pporpe run folder as a result file in the test bed's format."""
    from pporpe.io import atomic_write_json
    from pporpe.runs.logger import read_records

    if not (run_dir / "done.json").exists():
        print(f"seed {seed}: not finished ({run_dir})", flush=True)
        return
    records = read_records(run_dir / "episodes.csv")
    tests = json.loads((run_dir / "evaluation.json").read_text())["returns"]
    atomic_write_json(
        result_path("pporpe", config, args.task, seed, args.root),
        {
            "implementation": "pporpe",
            "env": TASKS[args.task],
            "seed": seed,
            "config": config,
            "settings": json.loads((run_dir / "config.json").read_text())["learner"],
            "returns": [r.ret for r in records],
            "lengths": [r.length for r in records],
            "test_returns": tests,
            "run_folder": str(run_dir.relative_to(args.root)),
        },
    )


THRESHOLD = {"pendulum": 950.0, "swingup": 800.0}
"""A seed "reaches" the task when its score is at least this (as the ablation counts)."""


def load_results(root: Path) -> list[dict[str, Any]]:
    """Every result file under ``root`` as a record with its curve and score."""
    import numpy as np

    task_of = {env: task for task, env in TASKS.items()}
    records = []
    for impl in IMPLEMENTATIONS:
        for path in sorted((root / impl).glob("*/*/seed*.json")):
            data = json.loads(path.read_text())
            returns = [float(x) for x in data["returns"]]
            records.append(
                {
                    "implementation": impl,
                    "task": task_of[data["env"]],
                    "config": data["config"],
                    "seed": int(data["seed"]),
                    "first50_mean": float(np.mean(returns[:50])),
                    "score": float(np.median(data["test_returns"])),
                    "returns": returns,
                    "versions": data.get("versions"),
                }
            )
    return records


def select(records: list[dict[str, Any]], **where: Any) -> list[dict[str, Any]]:
    return [r for r in records if all(r[k] == v for k, v in where.items())]


def side_by_side(
    records: list[dict[str, Any]], task: str, config: str, reference: str | None = None
) -> dict[str, Any] | None:
    """pporpe with ``config`` beside the test bed with ``reference`` (default: the same
    settings) on one task: CIs and P(pporpe > test bed)."""
    from pporpe.experiments.reports.stats import bootstrap_ci, probability_of_improvement_ci

    reference = config if reference is None else reference
    ours = select(records, implementation="pporpe", task=task, config=config)
    ref = select(records, implementation="testbed", task=task, config=reference)
    if not ours or not ref:
        return None
    label = config if reference == config else f"{config} / {reference}"
    row: dict[str, Any] = {"task": task, "config": label, "seeds": {}}
    for name, group in (("pporpe", ours), ("testbed", ref)):
        row["seeds"][name] = len(group)
        for metric in ("first50_mean", "score"):
            row[f"{name}_{metric}"] = bootstrap_ci([r[metric] for r in group]).as_dict()
    for metric in ("first50_mean", "score"):
        row[f"p_pporpe_better_{metric}"] = probability_of_improvement_ci(
            [r[metric] for r in ours], [r[metric] for r in ref]
        ).as_dict()
    row["bands"] = band_overlap(ours, ref)
    row["curves"] = (config, reference)
    return row


def mean_band(group: list[dict[str, Any]]) -> tuple[Any, Any, Any]:
    """Per-episode mean return over seeds and its 95% t-interval (scipy.stats.t)."""
    import numpy as np
    from scipy import stats

    curves = np.array([r["returns"] for r in group], dtype=np.float64)
    mean = curves.mean(0)
    n = len(curves)
    half = stats.t.ppf(0.975, n - 1) * curves.std(0, ddof=1) / np.sqrt(n) if n > 1 else 0 * mean
    return mean, mean - half, mean + half


def band_overlap(ours: list[dict[str, Any]], ref: list[dict[str, Any]]) -> dict[str, Any]:
    """Episodes where the two 95% bands of the mean curve do not overlap."""
    import numpy as np

    _, lo_a, hi_a = mean_band(ours)
    _, lo_b, hi_b = mean_band(ref)
    n = min(len(lo_a), len(lo_b))
    apart = np.nonzero((lo_a[:n] > hi_b[:n]) | (lo_b[:n] > hi_a[:n]))[0] + 1
    return {"episodes": n, "apart": [int(e) for e in apart]}


def path_rows(records: list[dict[str, Any]], task: str) -> list[dict[str, Any]]:
    """pporpe's configs on one task (the path from TESTBED to Table I): first-50 mean,
    final mean and IQM with CIs, seeds reaching the threshold, P(> testbed)."""
    from pporpe.experiments.reports.stats import bootstrap_ci, iqm, probability_of_improvement_ci

    def scores_of(config: str) -> list[float]:
        return [r["score"] for r in select(records, implementation="pporpe", task=task,
                                           config=config)]  # fmt: skip

    rows = []
    configs = {r["config"] for r in select(records, implementation="pporpe", task=task)}
    for config in sorted(configs, key=lambda c: (c.split("+")[-1] in ENGINE,
                                                  baseline_of(c) != "testbed" or c != "testbed",
                                                  c.count("+"), c)):  # fmt: skip
        group = select(records, implementation="pporpe", task=task, config=config)
        scores, base = scores_of(config), scores_of(baseline_of(config))
        row = {
            "task": task,
            "config": config,
            "seeds": len(group),
            "first50_mean": bootstrap_ci([r["first50_mean"] for r in group]).as_dict(),
            "mean": bootstrap_ci(scores).as_dict(),
            "iqm": bootstrap_ci(scores, iqm).as_dict(),
            "reached": sum(s >= THRESHOLD[task] for s in scores),
        }
        if base and config != baseline_of(config):
            row["baseline"] = baseline_of(config)
            row["p_better_than_testbed"] = probability_of_improvement_ci(scores, base).as_dict()
        rows.append(row)
    return rows


def fmt(ci: dict[str, float], digits: int = 0) -> str:
    return f"{ci['value']:.{digits}f} [{ci['low']:.{digits}f}, {ci['high']:.{digits}f}]"


def markdown(pairs: list[dict[str, Any]], paths: list[dict[str, Any]]) -> str:
    lines = [
        "# pporpe beside the author's test bed",
        "",
        "Generated by `python benchmarks/testbed.py summarize` from the result files under",
        "`benchmarks/results/testbed/`. Score: the median of 50 test episodes; first 50: the",
        "mean training return of episodes 1-50; bootstrap 95% CIs (BCa) over seeds.",
        "",
        "## Side by side",
        "",
        "| task | settings | seeds (pporpe / test bed) | first 50: pporpe | first 50: test bed "
        "| P(pporpe > test bed), first 50 | score: pporpe | score: test bed "
        "| P(pporpe > test bed), score | episodes whose bands are apart |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in pairs:
        apart = r["bands"]["apart"]
        lines.append(
            f"| {r['task']} | {r['config']} | {r['seeds']['pporpe']} / {r['seeds']['testbed']} "
            f"| {fmt(r['pporpe_first50_mean'])} | {fmt(r['testbed_first50_mean'])} "
            f"| {fmt(r['p_pporpe_better_first50_mean'], 2)} | {fmt(r['pporpe_score'])} "
            f"| {fmt(r['testbed_score'])} | {fmt(r['p_pporpe_better_score'], 2)} "
            f"| {len(apart)} of {r['bands']['episodes']} |"
        )
    lines += [
        "",
        "## pporpe from the test bed's settings toward Table I",
        "",
        "P(> baseline): P(a seed of the row scores above a seed of the baseline), the",
        "baseline being `testbed` run by the same engine (`testbed+fused` for the rows run by",
        "the fused engine); `testbed+fused`'s is `testbed`, the engine check.",
        "",
        "| task | settings | seeds | first 50 | score: mean | score: IQM | seeds reaching "
        "| baseline | P(> baseline) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in paths:
        p = fmt(r["p_better_than_testbed"], 2) if "p_better_than_testbed" in r else "-"
        lines.append(
            f"| {r['task']} | {r['config']} | {r['seeds']} | {fmt(r['first50_mean'])} "
            f"| {fmt(r['mean'])} | {fmt(r['iqm'])} | {r['reached']} of {r['seeds']} "
            f"| {r.get('baseline', '-')} | {p} |"
        )
    return "\n".join(lines) + "\n"


def step_table(root: Path) -> list[str]:
    """The update-by-update comparison of ``step.json`` (benchmarks/testbed_step.py)."""
    path = root / "step.json"
    if not path.exists():
        return []
    runs = json.loads(path.read_text())["runs"]
    names = ("policy hidden", "policy output", "value")
    lines = [
        "",
        "## Update by update",
        "",
        "`python benchmarks/testbed_step.py --checkout TEST_ET`: the largest parameter gap after",
        "n updates, relative to the largest move from the start (policy hidden layers / policy",
        "output layer / value network).",
        "",
        "| t-momentum | pporpe's head | n | pporpe against the test bed "
        "| pporpe against itself, 1 ulp away |",
        "| --- | --- | --- | --- | --- |",
    ]
    for r in runs:
        label = "off (k_dof inf)" if r["k_dof"] == float("inf") else f"on (k_dof {r['k_dof']:g})"
        for n, ours, ctl in zip(r["after_updates"], r["testbed"], r["control_one_ulp"],
                                strict=True):  # fmt: skip
            a = " / ".join(f"{ours[k]['relative']:.1e}" for k in names)
            b = " / ".join(f"{ctl[k]['relative']:.1e}" for k in names)
            lines.append(f"| {label} | {r.get('head_tensors', 'joint')} | {n} | {a} | {b} |")
    return lines


def plot_curves(
    records: list[dict[str, Any]], task: str, config: str, reference: str, out: Path
) -> None:
    """The two implementations' mean learning curves with 95% bands, one figure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, ax = plt.subplots(figsize=(7, 4))
    for impl, cfg, colour in (("pporpe", config, "tab:blue"), ("testbed", reference, "tab:orange")):
        group = select(records, implementation=impl, task=task, config=cfg)
        mean, lo, hi = mean_band(group)
        x = np.arange(1, len(mean) + 1)
        label = f"{'pporpe' if impl == 'pporpe' else 'test bed'} '{cfg}' ({len(group)} seeds)"
        ax.plot(x, mean, color=colour, label=label)
        ax.fill_between(x, lo, hi, color=colour, alpha=0.25, linewidth=0)
    ax.set_xlabel("episode")
    ax.set_ylabel("training return")
    ax.set_title(f"{task}: mean training return and its 95% band")
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


def summarize(args: argparse.Namespace) -> int:
    sys.path.insert(0, str(HERE))
    from _common import machine_info

    from pporpe.io import atomic_write_json, atomic_write_text

    records = load_results(args.root)
    tasks = sorted({r["task"] for r in records})
    pairs = [
        row
        for task in tasks
        for config, reference in PAIRS
        if (row := side_by_side(records, task, config, reference)) is not None
    ]
    paths = [row for task in tasks for row in path_rows(records, task)]
    for row in pairs:
        config, reference = row["curves"]
        plot_curves(records, row["task"], config, reference,
                    args.root / f"curves_{row['task']}_{config}.png")  # fmt: skip
    versions = sorted({json.dumps(r["versions"], sort_keys=True) for r in records if r["versions"]})
    atomic_write_json(
        args.root / "summary.json",
        {
            "commands": COMMANDS,
            "machine": machine_info(),
            "testbed_versions": [json.loads(v) for v in versions],
            "runs": [
                {
                    k: r[k]
                    for k in ("implementation", "task", "config", "seed", "first50_mean", "score")
                }
                for r in records
            ],
            "side_by_side": pairs,
            "toward_table_i": paths,
        },
    )
    text = markdown(pairs, paths) + "\n".join(step_table(args.root)) + "\n"
    atomic_write_text(args.root / "summary.md", text)
    print(text)
    return 0


COMMANDS = [
    "python benchmarks/testbed.py reference --checkout TEST_ET --python TEST_ET_PYTHON "
    "--task {swingup,pendulum} --config {testbed,paper} --seeds ...",
    "python benchmarks/testbed.py pporpe --task {swingup,pendulum} --config CONFIG "
    "--seeds 1 ... 10",
    "python benchmarks/testbed.py summarize",
]
"""How the result files were made (the seeds of each are in ``runs``)."""


def positive_seeds(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"a seed must be an int >= 1, got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    ref = sub.add_parser("reference", help="run the author's test bed for some seeds")
    ref.add_argument("--checkout", type=Path, required=True, help="folder of test_et")
    ref.add_argument("--python", type=Path, required=True, help="the test bed's interpreter")
    ref.add_argument(
        "--work",
        type=Path,
        default=Path.home() / ".cache" / "pporpe-testbed",
        help="folder of the workers' checkpoints (outside the repository)",
    )
    ref.add_argument("--config", choices=SIDE_BY_SIDE, default="testbed")
    own = sub.add_parser("pporpe", help="run pporpe's learner with the test bed's settings")
    own.add_argument("--config", type=config_arg, nargs="+", default=["testbed"],
                     help="testbed, paper, or testbed+GROUP+... (groups: "
                     f"{', '.join(GROUPS)}); several share one population")  # fmt: skip
    own.add_argument("--population", type=int, default=10, help="runs trained at once")
    summ = sub.add_parser("summarize", help="tables, figures and summary.json from the files")
    summ.add_argument("--root", type=Path, default=RESULTS, help="folder of the result files")
    for p in (ref, own):
        p.add_argument("--task", choices=sorted(TASKS), required=True)
        p.add_argument("--seeds", type=positive_seeds, nargs="+", required=True)
        p.add_argument("--episodes", type=int, default=200)
        p.add_argument("--tests", type=int, default=50)
        p.add_argument("--root", type=Path, default=RESULTS, help="folder of the result files")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "reference":
        return run_reference(args)
    if args.command == "pporpe":
        return run_pporpe(args)
    if args.command == "summarize":
        return summarize(args)
    raise AssertionError(args.command)


if __name__ == "__main__":
    sys.exit(main())
