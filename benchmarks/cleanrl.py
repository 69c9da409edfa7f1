"""pporpe's batch PPO beside CleanRL's ``ppo_continuous_action.py``, seed by seed: is
pporpe's PPO the field's PPO?

CleanRL's script runs unmodified, from a checkout you name (never copied into this
repository), in its own Python environment: CleanRL pins gymnasium 0.29.1 and mujoco 2.3.3;
it runs with torch 2.13 CPU, numpy < 2, tyro, tensorboard and imageio < 3::

    git clone https://github.com/vwxyzjn/cleanrl ~/cleanrl && cd ~/cleanrl
    python3 -m venv .venv && .venv/bin/pip install torch==2.13.0 "numpy<2" \\
        gymnasium==0.29.1 mujoco==2.3.3 tyro tensorboard "imageio<3"

Five subcommands, each resumable (a seed whose result file exists is skipped):

``cleanrl``
    CleanRL's script for the seeds, one after another (``--no-cuda``, its defaults
    otherwise: 1M steps, 2048 steps per rollout, 32 minibatches, 10 epochs, ...); the
    episodic returns it prints are the result::

        python benchmarks/cleanrl.py cleanrl --checkout ~/cleanrl \\
            --python ~/cleanrl/.venv/bin/python --task Hopper-v4 --seeds 1 2 3 4 5

``pporpe``
    the PPO runs of the batch study (``experiments/batch-mujoco.toml``, CleanRL's settings;
    ``pporpe reproduce ... --out results/batch-mujoco``) as result files in the same form.

``sb3``
    Stable-Baselines3's PPO with CleanRL's settings (the same networks, initialisation,
    normalisation, schedule and losses, as SB3's options allow: ``VecNormalize`` clipping
    at 10, ``clip_range_vf`` 0.2, a linear learning rate, Adam's eps 1e-5), in pporpe's
    environment, the returns of its ``Monitor``::

        python benchmarks/cleanrl.py sb3 --task Hopper-v4 --seeds 1 2 3

``throughput``
    steps/s of both side by side in one run, alternating A B A B: CleanRL's script and
    ``pporpe train --learner batch`` with the study's settings, each for ``--steps``.

``summarize``
    ``summary.json`` (the versions, the commands and a list ``runs`` of ``{"implementation":
    "pporpe" | "cleanrl" | "sb3", "task", "seed", "last100_mean", "steps_per_s",
    "steps_per_cpu_s"}``: steps per second of the run's wall clock, and per CPU second where
    its result file records ``cpu_s``), ``summary.md`` (per task: the last-100 mean with
    bootstrap CIs, P(pporpe > CleanRL) with its CI, P(pporpe > SB3) where SB3 ran, and the
    median steps per CPU second) and ``curves_<task>.png`` (the mean learning
    curves over steps, 95% bands).

The metric is CleanRL's: the mean return of the last 100 training episodes. Result files:
``benchmarks/results/cleanrl/<implementation>/<task>/seed<N>.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "cleanrl"
SCRIPT = Path("cleanrl") / "ppo_continuous_action.py"
TASKS = ("HalfCheetah-v4", "Hopper-v4", "Walker2d-v4", "Ant-v4")
IMPLEMENTATIONS = ("pporpe", "cleanrl", "sb3")
EPISODE_LINE = re.compile(r"global_step=(\d+), episodic_return=\[?([-+0-9.eE]+)\]?")
SPS_LINE = re.compile(r"^SPS: (\d+)", re.M)
LAST = 100
"""CleanRL's metric: the mean return of the last this many training episodes."""


def result_path(root: Path, implementation: str, task: str, seed: int) -> Path:
    return root / implementation / task / f"seed{seed}.json"


def parse_cleanrl_output(text: str) -> dict[str, Any]:
    """The episodes (step at its end, return) and the last steps/s CleanRL's script
    printed."""
    episodes = [(int(s), float(r)) for s, r in EPISODE_LINE.findall(text)]
    sps = [int(x) for x in SPS_LINE.findall(text)]
    return {
        "episode_steps": [s for s, _ in episodes],
        "returns": [r for _, r in episodes],
        "steps_per_s": float(sps[-1]) if sps else None,
    }


def last_mean(returns: list[float], last: int = LAST) -> float:
    """Mean of the last ``last`` returns (all of them when there are fewer)."""
    if not returns:
        raise ValueError("no episodes")
    return float(np.mean(returns[-last:]))


def cleanrl_command(args: argparse.Namespace, seed: int, steps: int) -> list[str]:
    return [str(args.python), str(args.checkout / SCRIPT), "--env-id", args.task,
            "--seed", str(seed), "--total-timesteps", str(steps), "--no-cuda"]  # fmt: skip


def child_cpu_seconds() -> float:
    """CPU seconds (user + system) of this process's finished children so far."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def run_cleanrl_once(args: argparse.Namespace, seed: int, steps: int, work: Path) -> str:
    """CleanRL's script in ``work`` (its runs/ folder lands there); its standard output."""
    work.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
           "PYTHONWARNINGS": "ignore"}  # fmt: skip
    done = subprocess.run(cleanrl_command(args, seed, steps), cwd=work, env=env,
                          capture_output=True, text=True)  # fmt: skip
    if done.returncode != 0:
        raise SystemExit(f"CleanRL's script exited {done.returncode}:\n{done.stderr[-2000:]}")
    return done.stdout


def run_cleanrl(args: argparse.Namespace) -> int:
    """CleanRL's script for each seed, one result file per seed."""
    from _common import write_json

    if not (args.checkout / SCRIPT).is_file() or not args.python.exists():
        raise SystemExit(f"--checkout needs {SCRIPT} and --python an interpreter")
    for seed in args.seeds:
        out = result_path(args.root, "cleanrl", args.task, seed)
        if out.exists():
            print(f"seed {seed}: done already ({out})", flush=True)
            continue
        t0, cpu0 = time.perf_counter(), child_cpu_seconds()
        text = run_cleanrl_once(args, seed, args.steps, args.work / args.task / f"seed{seed}")
        parsed = parse_cleanrl_output(text)
        write_json(out, {"implementation": "cleanrl", "task": args.task, "seed": seed,
                         "total_steps": args.steps, "wall_s": time.perf_counter() - t0,
                         "cpu_s": child_cpu_seconds() - cpu0,
                         "cleanrl_commit": git_commit(args.checkout),
                         "cleanrl_versions": versions_of(args.python),
                         "cleanrl_command": " ".join(cleanrl_command(args, seed, args.steps)),
                         **parsed})  # fmt: skip
        print(f"seed {seed}: last-{LAST} mean {last_mean(parsed['returns']):.1f}", flush=True)
    return 0


def versions_of(python: Path) -> dict[str, str]:
    """The versions of what CleanRL's script runs on, in its own environment."""
    code = ("import json, importlib.metadata as m; print(json.dumps({p: m.version(p) for p in "
            "('torch', 'numpy', 'gymnasium', 'mujoco', 'tyro')}))")  # fmt: skip
    done = subprocess.run([str(python), "-c", code], capture_output=True, text=True)
    return json.loads(done.stdout) if done.returncode == 0 else {}


def git_commit(checkout: Path) -> str | None:
    done = subprocess.run(["git", "-C", str(checkout), "rev-parse", "HEAD"],
                          capture_output=True, text=True)  # fmt: skip
    return done.stdout.strip() or None


def sb3_model(task: str, seed: int) -> Any:
    """Stable-Baselines3's PPO set as CleanRL's ``ppo_continuous_action.py``: one
    environment, 2048 steps per rollout, minibatches of 64, 10 epochs, lr 3e-4 annealed
    linearly to 0, gamma 0.99, GAE lambda 0.95, clip 0.2 for the ratio and the value, no
    entropy bonus, value coefficient 0.5, gradient norm 0.5, advantages normalised per
    minibatch, observations and rewards normalised and clipped at 10, separate 2 x 64 tanh
    networks, orthogonal initialisation (SB3's gains: sqrt 2, 0.01 for the mean, 1 for the
    value), a state-independent log std from 0, Adam's eps 1e-5 (SB3's default)."""
    import gymnasium as gym
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    monitored = DummyVecEnv([lambda: Monitor(gym.make(task))])
    venv = VecNormalize(monitored, gamma=0.99, clip_obs=10.0, clip_reward=10.0)
    policy_kwargs = {"net_arch": {"pi": [64, 64], "vf": [64, 64]},
                     "activation_fn": torch.nn.Tanh, "ortho_init": True, "log_std_init": 0.0}
    return PPO("MlpPolicy", venv, learning_rate=lambda left: 3e-4 * left, n_steps=2048,
               batch_size=64, n_epochs=10, gamma=0.99, gae_lambda=0.95, clip_range=0.2,
               clip_range_vf=0.2, ent_coef=0.0, vf_coef=0.5, max_grad_norm=0.5,
               normalize_advantage=True, policy_kwargs=policy_kwargs, seed=seed,
               device="cpu")  # fmt: skip


def run_sb3(args: argparse.Namespace) -> int:
    """Stable-Baselines3's PPO (:func:`sb3_model`) for each seed, one result file per seed:
    the returns and lengths its ``Monitor`` recorded, steps/s of ``learn``."""
    import stable_baselines3
    import torch
    from _common import write_json

    torch.set_num_threads(1)
    for seed in args.seeds:
        out = result_path(args.root, "sb3", args.task, seed)
        if out.exists():
            print(f"seed {seed}: done already ({out})", flush=True)
            continue
        model = sb3_model(args.task, seed)
        t0, cpu0 = time.perf_counter(), time.process_time()
        model.learn(total_timesteps=args.steps)
        wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
        monitor = model.get_env().venv.envs[0]
        returns = [float(r) for r in monitor.get_episode_rewards()]
        steps = np.cumsum(monitor.get_episode_lengths()).tolist()
        write_json(out, {"implementation": "sb3", "task": args.task, "seed": seed,
                         "total_steps": int(model.num_timesteps), "wall_s": wall,
                         "cpu_s": cpu,
                         "sb3_version": stable_baselines3.__version__,
                         "episode_steps": [int(x) for x in steps], "returns": returns,
                         "steps_per_s": model.num_timesteps / wall})  # fmt: skip
        print(f"seed {seed}: last-{LAST} mean {last_mean(returns):.1f}", flush=True)
    return 0


def repo_relative(path: Path) -> str:
    """``path`` relative to the repository where it lies inside it, else as given."""
    try:
        return str(path.resolve().relative_to(HERE.parent.resolve()))
    except ValueError:
        return str(path)


def export_pporpe(args: argparse.Namespace) -> int:
    """The batch study's finished PPO runs of a task as result files."""
    from _common import write_json

    from pporpe.runs.logger import read_records

    found = 0
    for run in sorted((args.study / args.task / "ppo").glob("seed*")):
        if not (run / "done.json").exists():
            continue
        seed = int(run.name.removeprefix("seed"))
        records = read_records(run / "episodes.csv")
        done = json.loads((run / "done.json").read_text())
        whole = "cpu_time" in done and not done.get("cpu_time_since", 0)
        cpu = {"cpu_s": done["cpu_time"]} if whole else {}
        write_json(result_path(args.root, "pporpe", args.task, seed),
                   {"implementation": "pporpe", "task": args.task, "seed": seed,
                    "total_steps": done["total_steps"], "run_folder": repo_relative(run),
                    "episode_steps": [r.total_steps for r in records],
                    "returns": [r.ret for r in records],
                    "steps_per_s": done["total_steps"] / done["train_time"], **cpu})  # fmt: skip
        found += 1
    print(f"{found} finished PPO runs of {args.task} exported from {args.study}")
    return 0


def pporpe_command(args: argparse.Namespace, seed: int, steps: int, out: Path) -> list[str]:
    """``pporpe train`` with the batch study's settings for the task (its spec's run)."""
    from pporpe.experiments.grids.spec import load_spec

    spec = load_spec(HERE.parent / "experiments" / "batch-mujoco.toml")
    (run,) = [r for r in spec.runs if r.env == args.task and r.config.method == "ppo"
              and r.config.seed == 0]  # fmt: skip
    flags = []
    for name, value in vars(run.config).items():
        if name in ("env", "method", "seed", "total_steps", "eval_episodes", "kind"):
            continue
        flag = "--" + name.replace("_", "-")
        if isinstance(value, bool):
            flags.append(flag if value else "--no-" + name.replace("_", "-"))
        elif value is not None:
            flags += [flag, str(value)]
    pporpe = Path(sys.executable).with_name("pporpe")
    return [str(pporpe), "train", "--learner", "batch", "--env", args.task, "--method", "ppo",
            "--seed", str(seed), "--steps", str(steps), "--eval-episodes", "0", "--quiet",
            "--force", "--out", str(out), *flags]  # fmt: skip


def throughput(args: argparse.Namespace) -> int:
    """Both implementations A B A B for ``--steps`` each; steps/s from their own clocks
    (CleanRL's last SPS line, pporpe's closing line)."""
    from _common import write_json

    rates: dict[str, list[float]] = {"cleanrl": [], "pporpe": []}
    for r in range(args.rounds):
        text = run_cleanrl_once(args, 1, args.steps, args.work / "throughput")
        rates["cleanrl"].append(parse_cleanrl_output(text)["steps_per_s"])
        out = subprocess.run(pporpe_command(args, 1, args.steps, args.work / "pporpe"),
                             capture_output=True, text=True, check=True).stdout  # fmt: skip
        found = re.search(r"\(([0-9.]+) steps/s\)", out)
        rates["pporpe"].append(float(found.group(1)) if found else float("nan"))
        print(f"round {r + 1}: cleanrl {rates['cleanrl'][-1]:.0f}, pporpe "
              f"{rates['pporpe'][-1]:.0f} steps/s", flush=True)  # fmt: skip
    medians = {k: float(np.median(v)) for k, v in rates.items()}
    payload = {"task": args.task, "steps": args.steps, "rounds": rates, "median": medians,
               "pporpe_over_cleanrl": medians["pporpe"] / medians["cleanrl"]}  # fmt: skip
    print(f"wrote {write_json(args.root / f'throughput_{args.task}.json', payload)}")
    return 0


def load_runs(root: Path) -> list[dict[str, Any]]:
    """Every result file as a record ``{"implementation", "task", "seed", "last100_mean",
    "steps_per_s", "episode_steps", "returns"}``."""
    runs = []
    for impl in IMPLEMENTATIONS:
        for path in sorted((root / impl).glob("*/seed*.json")):
            data = json.loads(path.read_text())
            cpu = data.get("cpu_s")
            runs.append({"implementation": impl, "task": data["task"], "seed": data["seed"],
                         "last100_mean": last_mean(data["returns"]),
                         "steps_per_s": data["steps_per_s"],
                         "steps_per_cpu_s": data["total_steps"] / cpu if cpu else None,
                         "episode_steps": data["episode_steps"],
                         "returns": data["returns"]})  # fmt: skip
    return runs


def curve(run: dict[str, Any], grid: np.ndarray) -> np.ndarray:
    """A run's return against steps on ``grid``: the mean of the last 100 episodes ended
    by each step (CleanRL's metric along the run), NaN before the first episode ends."""
    steps, returns = np.asarray(run["episode_steps"]), np.asarray(run["returns"])
    out = np.full(len(grid), np.nan)
    for i, g in enumerate(grid):
        n = int(np.searchsorted(steps, g, side="right"))
        if n:
            out[i] = returns[max(0, n - LAST) : n].mean()
    return out


MIN_COMPARED = 2
"""Seeds each side needs before P(pporpe > rival) is given (one seed has no spread)."""


def task_row(runs: list[dict[str, Any]], task: str) -> dict[str, Any] | None:
    """One task's side by side: the last-100 means with CIs and P(pporpe > CleanRL) (where
    CleanRL ran: a task of the study without CleanRL's runs has pporpe's mean alone, beside
    CleanRL's published one on the docs page); None without pporpe's runs."""
    from pporpe.experiments.reports.stats import bootstrap_ci, probability_of_improvement_ci

    groups = {i: [r for r in runs if r["task"] == task and r["implementation"] == i]
              for i in IMPLEMENTATIONS}  # fmt: skip
    groups = {i: g for i, g in groups.items() if g}
    if "pporpe" not in groups:
        return None
    row: dict[str, Any] = {"task": task, "seeds": {i: len(g) for i, g in groups.items()}}
    for impl, group in groups.items():
        row[impl] = bootstrap_ci([r["last100_mean"] for r in group]).as_dict()
        rates = [r["steps_per_cpu_s"] for r in group if r["steps_per_cpu_s"] is not None]
        if rates:
            row[f"{impl}_steps_per_cpu_s"] = float(np.median(rates))
    mine = [r["last100_mean"] for r in groups["pporpe"]]
    for rival, key in (("cleanrl", "p_pporpe_better"), ("sb3", "p_pporpe_better_sb3")):
        if rival in groups and min(len(groups[rival]), len(mine)) >= MIN_COMPARED:
            theirs = [r["last100_mean"] for r in groups[rival]]
            row[key] = probability_of_improvement_ci(mine, theirs).as_dict()
    return row


def plot(runs: list[dict[str, Any]], task: str, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy import stats

    top = max(r["episode_steps"][-1] for r in runs if r["task"] == task)
    grid = np.linspace(top / 50, top, 50)
    fig, ax = plt.subplots(figsize=(6, 4))
    for impl in IMPLEMENTATIONS:
        curves = np.array([curve(r, grid) for r in runs
                           if r["task"] == task and r["implementation"] == impl])  # fmt: skip
        if not len(curves):
            continue
        mean, n = np.nanmean(curves, 0), len(curves)
        half = stats.t.ppf(0.975, n - 1) * np.nanstd(curves, 0, ddof=1) / np.sqrt(n) if n > 1 \
            else 0 * mean  # fmt: skip
        ax.plot(grid, mean, label=f"{impl} ({n} seeds)")
        ax.fill_between(grid, mean - half, mean + half, alpha=0.25)
    ax.set(xlabel="environment steps", ylabel=f"mean return, last {LAST} episodes", title=task)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


def provenance(root: Path) -> dict[str, Any]:
    """What produced the result files: CleanRL's commit, versions and an example command,
    SB3's version, and the commands that make each kind of file."""
    found: dict[str, Any] = {}
    for path in sorted(root.glob("*/*/seed*.json")):
        data = json.loads(path.read_text())
        for key in ("cleanrl_commit", "cleanrl_versions", "cleanrl_command", "sb3_version"):
            if key in data:
                found.setdefault(key, data[key])
    found["commands"] = {
        "cleanrl": "python benchmarks/cleanrl.py cleanrl --checkout CLEANRL --python "
                   "CLEANRL/.venv/bin/python --task TASK --seeds 1 2 3 4 5",
        "pporpe": "pporpe reproduce experiments/batch-mujoco.toml --out DIR; "
                  "python benchmarks/cleanrl.py pporpe --task TASK --study DIR",
        "sb3": "python benchmarks/cleanrl.py sb3 --task TASK --seeds 1 2 3",
        "summary": "python benchmarks/cleanrl.py summarize",
    }  # fmt: skip
    return found


def summarize(args: argparse.Namespace) -> int:
    from _common import write_json

    runs = load_runs(args.root)
    rows = [row for task in TASKS if (row := task_row(runs, task)) is not None]
    for task in {r["task"] for r in runs}:
        plot(runs, task, args.root / f"curves_{task}.png")
    keys = ("implementation", "task", "seed", "last100_mean", "steps_per_s", "steps_per_cpu_s")
    slim = [{k: r[k] for k in keys} for r in runs]
    write_json(args.root / "summary.json", {**provenance(args.root), "runs": slim, "tasks": rows})
    lines = summary_lines(rows)
    (args.root / "summary.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


def summary_lines(rows: list[dict[str, Any]]) -> list[str]:
    """The side-by-side table: per task the last-100 means, P(pporpe > CleanRL), and SB3's
    mean and P(pporpe > SB3) where it ran ("-" where not)."""
    lines = ["| task | seeds (pporpe / CleanRL / SB3) | pporpe last-100 mean | "
             "CleanRL last-100 mean | P(pporpe > CleanRL) | SB3 last-100 mean | "
             "P(pporpe > SB3) | steps per CPU second (pporpe / CleanRL / SB3) |",
             "| --- | --- | ---: | ---: | :---: | ---: | :---: | ---: |"]  # fmt: skip
    for row in rows:
        seeds = " / ".join(str(row["seeds"].get(i, 0)) for i in IMPLEMENTATIONS)
        rates = " / ".join(f"{row[f'{i}_steps_per_cpu_s']:.0f}"
                           if f"{i}_steps_per_cpu_s" in row else "-"
                           for i in IMPLEMENTATIONS)  # fmt: skip
        means = [fmt(row[i]) if i in row else "-" for i in IMPLEMENTATIONS]
        p = [fmt_p(row[k]) if k in row else "-" for k in ("p_pporpe_better", "p_pporpe_better_sb3")]
        lines.append(
            f"| {row['task']} | {seeds} | {means[0]} | {means[1]} | {p[0]} | {means[2]} | "
            f"{p[1]} | {rates} |"
        )
    return lines


def fmt_p(p: dict[str, float]) -> str:
    return f"{p['value']:.2f} [{p['low']:.2f}, {p['high']:.2f}]"


def fmt(ci: dict[str, float]) -> str:
    return f"{ci['value']:.0f} [{ci['low']:.0f}, {ci['high']:.0f}]"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    ref = sub.add_parser("cleanrl", help="CleanRL's script for the seeds")
    put = sub.add_parser("throughput", help="steps/s of both, side by side")
    own = sub.add_parser("pporpe", help="the batch study's PPO runs as result files")
    sb3 = sub.add_parser("sb3", help="Stable-Baselines3's PPO with CleanRL's settings")
    summ = sub.add_parser("summarize", help="summary.json, summary.md and the curves")
    for p in (ref, put):
        p.add_argument("--checkout", type=Path, required=True, help="a clone of CleanRL")
        p.add_argument("--python", type=Path, required=True, help="CleanRL's interpreter")
        p.add_argument("--work", type=Path, default=Path("/tmp/pporpe-cleanrl"),
                       help="where CleanRL's runs/ folders go")  # fmt: skip
    for p in (ref, put, own, sb3):
        p.add_argument("--task", choices=TASKS, required=True)
    for p in (ref, sb3):
        p.add_argument("--seeds", type=int, nargs="+", required=True)
        p.add_argument("--steps", type=positive, default=1_000_000, help="steps per run")
    put.add_argument("--steps", type=positive, default=20_480, help="steps per measurement")
    put.add_argument("--rounds", type=positive, default=3)
    own.add_argument("--study", type=Path, default=HERE.parent / "results" / "batch-mujoco")
    for p in (ref, put, own, summ, sb3):
        p.add_argument("--root", type=Path, default=RESULTS, help="folder of the result files")
    return parser


def positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, not {value}")
    return value


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    commands = {"cleanrl": run_cleanrl, "pporpe": export_pporpe, "throughput": throughput,
                "summarize": summarize, "sb3": run_sb3}  # fmt: skip
    return commands[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
