"""The two engines from the same seeds, in lockstep, each with its own environments: where
and how their runs part.

:mod:`engine_shadow` holds the engines to each other one step at a time (the torch
engine restarted from the fused engine's state every step), so it sees each step's
rounding but not what the rounding becomes over a run. Here each engine runs a whole
population of its own from the same seeds, with its own environments, as two runs of
``benchmarks/testbed.py`` do, and nothing is copied between them. Beside them runs the
control: the fused engine again, its initial parameters one float32 ulp away (a
difference of one rounding and no rule). Per step and member, each twin against the fused
engine:

* ``gap``: the parameters' distance, ``max|theta_torch - theta_fused| / max|theta_fused|``
  over the policy and value networks;
* ``action``: ``max|a_torch - a_fused|`` over the action's components, in units of the
  action range;
* the discrete events of a step, in each engine: the PPO clip passed (the ratio outside
  ``[1 - eps, 1 + eps]``) and the episode's end (terminated or truncated).

What the benchmark reports, per seed: the first step at which the gap passes each of
1e-6 ... 1e-1, the first step at which the two engines' discrete events differ and the gap
just before it, and the growth of the gap, ``log10`` per 1000 steps, fitted while it lies
between 1e-5 and 1e-2, and the largest one-step jump of the gap while it is below 1e-3.
Two engines that agree to rounding part by amplification: a gap that starts at float32's
rounding (about 1e-7) and grows as the control's does, with no discrete event that
differs while the gap is still small. A rule that differs shows as a gap that outgrows
the control's, or as a discrete event that differs while the gap is still at rounding.

Usage::

    python benchmarks/engine_divergence.py --task swingup --config testbed \\
        --seeds 3 9 8 33 36 11 29 14 --episodes 20

writes ``benchmarks/results/engine_divergence.json`` (the machine, the command, per twin
the per-seed table and the gap every ``--record-every`` steps), draws the gaps into
``engine_divergence.png`` beside it, and prints the tables.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import write_json
from lockstep import EngineRun
from testbed import TASKS, config_arg, positive_seeds, settings_for

OUT = Path(__file__).resolve().parent / "results" / "engine_divergence.json"
LEVELS = (1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 1e-1)
ACTION_LEVELS = (1e-3, 1e-1)
FIT_RANGE = (1e-5, 1e-2)
TINY = 1e-30
TWINS = {
    "torch": "the torch engine",
    "fused-ulp": "the fused engine with every initial parameter one float32 ulp away",
}
"""The fused engine's twins: the engine under test, and the control, whose difference from
the fused engine is one rounding at the start and no rule at all."""


@dataclass
class SeedTrace:
    """What one seed's pair of runs did, step by step."""

    seed: int
    gap: list[float] = field(default_factory=list)
    action: list[float] = field(default_factory=list)
    first_event: dict[str, Any] | None = None

    def summary(self, record_every: int) -> dict[str, Any]:
        """The seed's row: first crossings, first differing event, growth rate, and the
        gap every ``record_every`` steps."""
        gap = np.asarray(self.gap)
        action = np.asarray(self.action)
        crossings = {f"{lv:g}": first_index(gap > lv) for lv in LEVELS}
        action_crossings = {f"{lv:g}": first_index(action > lv) for lv in ACTION_LEVELS}
        return {
            "seed": self.seed,
            "steps": len(gap),
            "first_step_gap_above": crossings,
            "first_step_action_above": action_crossings,
            "first_differing_event": self.first_event,
            "growth_log10_per_1000_steps": growth_rate(gap),
            "largest_one_step_jump_below_1e-3": largest_jump(gap),
            "final_gap": float(gap[-1]),
            "final_action_gap": float(self.action[-1]),
            "gap_every": [float(g) for g in gap[::record_every]],
            "action_every": [float(a) for a in action[::record_every]],
        }


def first_index(mask: np.ndarray) -> int | None:
    """The first index where ``mask`` holds (1-based step), or None."""
    hits = np.nonzero(mask)[0]
    return int(hits[0]) + 1 if len(hits) else None


def growth_rate(gap: np.ndarray) -> float | None:
    """Least-squares slope of ``log10(gap)`` per 1000 steps over the steps where the gap
    first lies inside :data:`FIT_RANGE` (from its first entry to its first exit above)."""
    lo, hi = first_index(gap > FIT_RANGE[0]), first_index(gap > FIT_RANGE[1])
    if lo is None or hi is None or hi - lo < 10:
        return None
    t = np.arange(lo, hi)
    return float(np.polyfit(t, np.log10(gap[lo - 1 : hi - 1]), 1)[0] * 1000)


def largest_jump(gap: np.ndarray) -> dict[str, float] | None:
    """The largest one-step growth factor of the gap while it is still below 1e-3 (above
    1e-7, float32's rounding): a differing rule shows as a jump of orders of magnitude."""
    g = np.maximum(gap, TINY)
    ratio = g[1:] / g[:-1]
    ok = (g[:-1] > 1e-7) & (g[1:] < 1e-3)
    if not ok.any():
        return None
    i = int(np.argmax(np.where(ok, ratio, 0.0)))
    return {"step": i + 2, "factor": float(ratio[i]), "gap_before": float(g[i])}


def compare(
    fused: EngineRun,
    pf: np.ndarray,
    twin: EngineRun,
    traces: list[SeedTrace],
    t: int,
    eps: float,
    events: tuple[np.ndarray, ...],
) -> None:
    """Append step ``t``'s gaps to each seed's trace (``pf``: the fused engine's
    :meth:`EngineRun.params`, read once per step for every twin); note its first differing
    event."""
    pt = twin.params()
    gap = np.abs(pt - pf).max(1) / np.maximum(np.abs(pf).max(1), TINY)
    span = np.asarray(fused.learner.action_map.high - fused.learner.action_map.low)
    act = (np.abs(twin.actions - fused.actions) / np.maximum(span, TINY)).max(1)
    ratio_f, ended_f, ratio_t, ended_t = events
    clip_f, clip_t = np.abs(ratio_f - 1) > eps, np.abs(ratio_t - 1) > eps
    for k, tr in enumerate(traces):
        previous = tr.gap[-1] if tr.gap else 0.0
        tr.gap.append(float(gap[k]))
        tr.action.append(float(act[k]))
        if tr.first_event is None and (clip_f[k] != clip_t[k] or ended_f[k] != ended_t[k]):
            tr.first_event = {
                "step": t,
                "kind": "clip" if clip_f[k] != clip_t[k] else "episode end",
                "ratio_fused": float(ratio_f[k]),
                "ratio_twin": float(ratio_t[k]),
                "gap_before": previous,
            }


def start_twin(name: str, args: argparse.Namespace) -> EngineRun:
    """The fused engine's twin of :data:`TWINS` ``name``."""
    if name == "torch":
        return EngineRun.start("torch", args.task, args.config, args.seeds)
    twin = EngineRun.start("fused", args.task, args.config, args.seeds)
    twin.nudge(0)
    return twin


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The fused engine and each twin over ``args.episodes`` episodes of every member of
    the fused engine, all in lockstep."""
    eps = settings_for(args.config)["eps"]
    fused = EngineRun.start("fused", args.task, args.config, args.seeds)
    twins = {name: start_twin(name, args) for name in args.against}
    traces = {name: [SeedTrace(s) for s in args.seeds] for name in twins}
    t = 0
    while fused.episodes.min() < args.episodes:
        t += 1
        lead = fused.step()
        pf = fused.params()
        for name, twin in twins.items():
            compare(fused, pf, twin, traces[name], t, eps, (*lead, *twin.step()))
    return {
        "task": args.task,
        "config": args.config,
        "episodes": args.episodes,
        "record_every": args.record_every,
        "twins": {name: TWINS[name] for name in twins},
        "pairs": {
            name: [tr.summary(args.record_every) for tr in rows] for name, rows in traces.items()
        },
    }


def table(rows: list[dict[str, Any]]) -> str:
    """One pair's per-seed table, markdown."""
    head = ["seed", *(f"gap>{lv:g}" for lv in LEVELS),
            *(f"action>{lv:g}" for lv in ACTION_LEVELS), "first differing event",
            "gap before it", "log10/1000 steps", "largest jump below 1e-3"]  # fmt: skip
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for r in rows:
        ev = r["first_differing_event"]
        jump = r["largest_one_step_jump_below_1e-3"]
        cells = [
            str(r["seed"]),
            *(str(r["first_step_gap_above"][f"{lv:g}"] or "-") for lv in LEVELS),
            *(str(r["first_step_action_above"][f"{lv:g}"] or "-") for lv in ACTION_LEVELS),
            f"{ev['kind']} at step {ev['step']}" if ev else "-",
            f"{ev['gap_before']:.1e}" if ev else "-",
            f"{r['growth_log10_per_1000_steps']:.2f}"
            if r["growth_log10_per_1000_steps"] is not None
            else "-",
            f"x{jump['factor']:.1f} at step {jump['step']}" if jump else "-",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(result: dict[str, Any], path: Path) -> None:
    """The gap along the runs, one panel per twin, one line per seed (log scale)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pporpe.io import atomic_savefig

    pairs = result["pairs"]
    fig, axes = plt.subplots(1, len(pairs), figsize=(5 * len(pairs), 3.6), sharey=True,
                             squeeze=False)  # fmt: skip
    for ax, (name, rows) in zip(axes[0], pairs.items(), strict=True):
        for r in rows:
            gap = np.maximum(np.asarray(r["gap_every"]), 1e-9)
            ax.plot(np.arange(len(gap)) * result["record_every"], gap, lw=1, label=r["seed"])
        ax.set(yscale="log", xlabel="step", title=f"fused engine vs {name}", ylim=(1e-9, 10))
    axes[0][0].set_ylabel("max|theta_twin - theta_fused| / max|theta_fused|")
    axes[0][-1].legend(title="seed", fontsize=7, ncol=2)
    fig.tight_layout()
    atomic_savefig(fig, path)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", choices=sorted(TASKS), default="swingup")
    p.add_argument("--config", type=config_arg, default="testbed",
                   help="the learner's settings, a config of benchmarks/testbed.py")  # fmt: skip
    p.add_argument("--seeds", type=positive_seeds, nargs="+", default=[3, 9, 8, 33, 36, 11, 29, 14])
    p.add_argument("--episodes", type=int, default=20, help="episodes of every member")
    p.add_argument("--against", choices=sorted(TWINS), nargs="+", default=sorted(TWINS),
                   help="the fused engine's twins, run beside it (TWINS)")  # fmt: skip
    p.add_argument("--record-every", type=int, default=100, help="steps between kept gaps")
    p.add_argument("--out", type=Path, default=OUT)
    p.add_argument("--draw", action="store_true",
                   help="only draw the figure of the results already in --out")  # fmt: skip
    args = p.parse_args(argv)
    if args.draw:
        plot(json.loads(args.out.read_text(encoding="utf-8")), args.out.with_suffix(".png"))
        return 0
    if args.episodes < 1 or args.record_every < 1:
        p.error("--episodes and --record-every must be at least 1")
    import torch

    torch.set_num_threads(1)
    result = run(args)
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))
    for name, rows in result["pairs"].items():
        print(f"fused engine against {TWINS[name]}:\n{table(rows)}\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
