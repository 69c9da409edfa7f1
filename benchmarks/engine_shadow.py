"""The torch engine shadowing the fused engine along learning runs: one-step discrepancies.

The unit tests hold the two engines of :class:`pporpe.online.population.PopulationLearner`
to each other over 25 steps from a fresh start. This benchmark asks the question those
tests cannot: do they still compute the same step in the states a long run visits (large
or saturated actions, a collapsed scale, a large divergence, long-accumulated optimiser
statistics)? A population of the fused engine learns a task; every ``--every``-th step
its whole state (noise streams included) is copied into a population of the torch engine,
both take the same transition, and the two results are compared:

* the step's scalars per member (TD error, advantage, ratio, trace divergence, decay):
  the relative difference ``|torch - fused| / max(|fused|, |torch|)`` and, for the
  divergence, the two engines' means (a bias, not rounding, shows there);
* the actions a_{t+1}, relative to their size;
* every state buffer, per member, in units of its size (``max|after|`` of either
  engine): the step's change ``change.<name> = max|d_fused|`` and the engines'
  discrepancy ``state.<name> = max|d_torch - d_fused|`` (d = after - before). Rounding
  reads about 1e-7 (float32); a different rule reads as large as the change itself.
  Rare larger ones come from discontinuities of the rules: the trace's
  ``r <- s max(s c2 r, |e|)`` with ``s = sign(e)`` jumps when rounding flips the sign of
  an ``e`` near 0, and the momentum carries the jump: counted as the elements of ``r``
  apart by more than 1e-3 of its size and those of them whose ``e`` has opposite signs.

Usage::

    python benchmarks/engine_shadow.py --task swingup --config testbed --seeds 1 2 3 4 \\
        --episodes 200 --every 53

writes ``benchmarks/results/engine_shadow.json`` (quantiles per quantity and per window of
episodes, the machine and the command) and prints the table.
"""

from __future__ import annotations

import argparse
import itertools
import resource
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import write_json
from lockstep import EngineRun, population
from testbed import TASKS, config_arg, positive_seeds

OUT = Path(__file__).resolve().parent / "results" / "engine_shadow.json"
STATS = ("delta", "adv", "ratio", "divergence", "trace_decay")
TINY = 1e-30
QUANTILES = (0.5, 0.99, 1.0)


def member_axis(name: str) -> int:
    """The member axis of a :meth:`PopulationState.state_dict` entry."""
    stacked = ("params", "trace_e", "trace_r", "opt_v", "opt_vmax", "opt_m", "opt_weight")
    return 1 if name in stacked else 0


def member_rows(x: torch.Tensor, name: str) -> torch.Tensor:
    """A state buffer as float64 ``[K, elements]``, one row per member."""
    axis = member_axis(name)
    return x.double().movedim(axis, 0).reshape(x.shape[axis], -1)


def change_discrepancy(
    before: dict[str, torch.Tensor], fused: dict[str, torch.Tensor], torch_: dict[str, torch.Tensor]
) -> dict[str, np.ndarray]:
    """Per buffer, per member, in units of the buffer's size (``max|after|`` of either
    engine): row 0 the step's change ``max|d_fused|``, row 1 the discrepancy
    ``max|d_torch - d_fused|``."""
    out = {}
    for name, b in before.items():
        if not torch.is_floating_point(b) or b.numel() == 0:
            continue
        start = member_rows(b, name)
        after_f, after_t = member_rows(fused[name], name), member_rows(torch_[name], name)
        df, dt = after_f - start, after_t - start
        size = torch.maximum(after_f.abs().amax(1), after_t.abs().amax(1)).clamp_min(TINY)
        out[name] = torch.stack([df.abs().amax(1) / size, (dt - df).abs().amax(1) / size]).numpy()
    return out


def sign_flips(
    fused: dict[str, torch.Tensor], torch_: dict[str, torch.Tensor], tol: float = 1e-3
) -> np.ndarray:
    """Per member: ``[elements of trace_r whose values differ by more than tol of its
    size, those of them whose trace_e has opposite signs in the two engines]``."""
    ef, et = member_rows(fused["trace_e"], "trace_e"), member_rows(torch_["trace_e"], "trace_e")
    rf, rt = member_rows(fused["trace_r"], "trace_r"), member_rows(torch_["trace_r"], "trace_r")
    size = torch.maximum(rf.abs().amax(1), rt.abs().amax(1)).clamp_min(TINY).unsqueeze(1)
    apart = (rt - rf).abs() / size > tol
    flipped = apart & (torch.sign(ef) != torch.sign(et))
    return torch.stack([apart.sum(1), flipped.sum(1)]).numpy()


class Shadowed:
    """A fused population that learns and a torch population that shadows single steps."""

    def __init__(self, task: str, config: str, seeds: list[int], compile_update: bool) -> None:
        self.lead = EngineRun.start("fused", task, config, seeds)
        self.shadow = population(
            "torch", self.lead.envs[0], config, seeds, compile_update=compile_update
        )
        self.returns: list[list[float]] = [[] for _ in seeds]
        self._ret = np.zeros(len(seeds))

    @property
    def episode(self) -> np.ndarray:
        """Episodes every member of the lead has finished ``[K]``."""
        return self.lead.episodes

    def step(self, compare: bool) -> dict[str, Any] | None:
        """One learning step of the lead; with ``compare``, the shadow's from the same
        state too, and the record of their discrepancies."""
        rew, obs, term, trunc = self.lead.transition()
        record = None
        if compare:
            before = self.lead.learner.state_dict()
            self.shadow.load_state_dict(before)
            st_t, act_t = self.shadow.step(rew, obs, term, trunc)
        st_f = self.lead.learn(rew, obs, term, trunc)
        if compare:
            after_f, after_t = self.lead.learner.state_dict(), self.shadow.state_dict()
            size = np.maximum(np.abs(self.lead.actions).max(1), TINY)
            record = {
                "fused": np.stack([getattr(st_f, n).double().numpy() for n in STATS]),
                "torch": np.stack([getattr(st_t, n).double().numpy() for n in STATS]),
                "action": np.abs(act_t - self.lead.actions).max(1) / size,
                "buffers": change_discrepancy(before["state"], after_f["state"], after_t["state"]),
                "flips": sign_flips(after_f["state"], after_t["state"]),
                "episode": self.episode.copy(),
            }
        self._ret += rew
        self._note_returns(term | trunc)
        self.lead.end_episodes(term | trunc)
        return record

    def _note_returns(self, ended: np.ndarray) -> None:
        for k in np.nonzero(ended)[0]:
            self.returns[k].append(float(self._ret[k]))
            self._ret[k] = 0.0

    def close(self) -> None:
        """Close the lead's environments."""
        self.lead.close()


def fix_mmap_threshold() -> None:
    """Keep glibc from moving large blocks onto the heap: every compared step allocates
    and frees a few states of megabytes while small records accumulate, and glibc's
    adaptive mmap threshold then lets the heap grow without bound (measured: 4 MB per
    step, 20 GB after 5000 steps of 4 members). A fixed threshold of 128 kB keeps the
    large blocks mmapped; elsewhere than glibc this does nothing."""
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.mallopt(-3, 1 << 17)  # M_MMAP_THRESHOLD
    except (OSError, AttributeError):
        pass


def quantiles(x: np.ndarray) -> dict[str, float]:
    x = np.asarray(x, dtype=np.float64).ravel()
    return {f"q{int(q * 100)}": float(np.quantile(x, q)) for q in QUANTILES}


def summarise(records: list[dict[str, Any]], windows: int, episodes: int) -> dict[str, Any]:
    """Quantiles of every discrepancy over all compared steps and per window of episodes."""
    edges = np.linspace(0, episodes, windows + 1)
    rows = []
    for lo, hi in [(0, episodes), *itertools.pairwise(edges)]:
        sel = [(r, k) for r in records for k in range(len(r["episode"]))
               if lo <= r["episode"][k] < hi]  # fmt: skip
        if not sel:
            continue
        f = np.array([r["fused"][:, k] for r, k in sel])
        t = np.array([r["torch"][:, k] for r, k in sel])
        rel = np.abs(t - f) / np.maximum(np.maximum(np.abs(f), np.abs(t)), TINY)
        row: dict[str, Any] = {"episodes": [int(lo), int(hi)], "compared": len(sel)}
        for i, name in enumerate(STATS):
            row[name] = quantiles(rel[:, i])
        div_f, div_t = f[:, STATS.index("divergence")], t[:, STATS.index("divergence")]
        row["divergence_mean"] = {"fused": float(div_f.mean()), "torch": float(div_t.mean())}
        row["action"] = quantiles(np.array([r["action"][k] for r, k in sel]))
        for name in records[0]["buffers"]:
            both = np.array([r["buffers"][name][:, k] for r, k in sel])
            row[f"change.{name}"] = quantiles(both[:, 0])
            row[f"state.{name}"] = quantiles(both[:, 1])
        flips = np.array([r["flips"][:, k] for r, k in sel]).sum(0)
        row["trace_r_apart"], row["trace_r_apart_sign_flipped"] = int(flips[0]), int(flips[1])
        rows.append(row)
    return {"windows": rows}


def table(summary: dict[str, Any]) -> str:
    """Markdown: per quantity, the median / 99% / max relative discrepancy per window."""
    rows = summary["windows"]
    names = [k for k in rows[0] if isinstance(rows[0][k], dict) and "q50" in rows[0][k]]
    head = ["quantity"] + [f"ep {r['episodes'][0]}-{r['episodes'][1]}" for r in rows]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for n in names:
        cells = [f"{r[n]['q50']:.1e} / {r[n]['q99']:.1e} / {r[n]['q100']:.1e}" for r in rows]
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    means = [f"{r['divergence_mean']['fused']:.3g} / {r['divergence_mean']['torch']:.3g}"
             for r in rows]  # fmt: skip
    lines.append("| mean divergence fused / torch | " + " | ".join(means) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", choices=sorted(TASKS), default="swingup")
    p.add_argument(
        "--config", type=config_arg, default="testbed", help="a benchmarks/testbed.py config name"
    )
    p.add_argument("--seeds", type=positive_seeds, nargs="+", default=[1, 2, 3, 4])
    p.add_argument("--episodes", type=int, default=100, help="episodes of every member")
    p.add_argument(
        "--every",
        type=int,
        default=53,
        help="compare every N-th step (prime to the episode length: every phase)",
    )
    p.add_argument("--windows", type=int, default=4, help="windows of episodes in the table")
    p.add_argument("--no-compile", action="store_true", help="the torch engine's eager update")
    p.add_argument("--out", type=Path, default=OUT)
    args = p.parse_args(argv)
    if args.episodes < 1 or args.every < 1 or args.windows < 1:
        p.error("--episodes, --every and --windows must be >= 1")
    torch.set_num_threads(1)
    fix_mmap_threshold()
    run = Shadowed(args.task, args.config, args.seeds, not args.no_compile)
    records, n = [], 0
    while run.episode.min() < args.episodes:
        rec = run.step(compare=n % args.every == 0)
        n += 1
        if rec is not None and (run.episode < args.episodes).all():
            records.append(rec)
        if n % 10000 == 0:
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024
            print(f"step {n}: episodes {run.episode.tolist()}, {rss} MB", flush=True)
    summary = summarise(records, args.windows, args.episodes)
    summary["returns_first50_mean"] = [float(np.mean(r[:50])) for r in run.returns]
    summary["settings"] = {"task": args.task, "config": args.config, "seeds": args.seeds,
                           "episodes": args.episodes, "every": args.every,
                           "compile": not args.no_compile}  # fmt: skip
    write_json(args.out, summary)
    print(table(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
