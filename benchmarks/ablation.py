"""Ablation of the learner choices where pporpe 0.2 and the author's test bed differ.

Each *variant* is the baseline (pporpe 0.2's choices, ``BASELINE_CHOICES``) with one change,
or all changes together (``AUTHOR_CHOICES``, pporpe 0.3's defaults), or all but the
entropy density (``all_but_entropy``), or any combination of the changes named with ``+``
(``amsgrad+td_units``: pporpe 0.2's choices with those two changes;
``td_units+amsgrad+layer_norm+trace_kl`` is ``DEFAULT_CHOICES``, pporpe's defaults since
0.4). Two more changes, ``weights`` and ``lr_width`` (:data:`TESTBED`), are the test bed's
values where the paper states others, for diagnosis only; they run in combinations, not
alone (``td_units+amsgrad+layer_norm+trace_kl+weights``: the defaults with the test bed's
regulariser weights and reward scale, the test bed's signal only with the unscaled TD
units). Every variant runs the paper's comparison (PPO,
PPO-RB, PPO-RPE) on InvertedPendulum and Swingup at the paper's 200 episodes with 10
seeds, through the grid machinery (populations, checkpoints, resume). It prints, per
variant, task and method:

* the mean and the interquartile mean (IQM) of the per-seed score (median of the test
  episodes), each with a bootstrap 95% CI (scipy.stats.bootstrap, BCa, 10,000 resamples);
* the mean return of the first 50 training episodes (early learning), with its CI;
* the number of seeds whose score reaches 950 (pendulum) or 800 (swingup);
* per variant and task, the probability that a run of the variant scores above a run of
  the baseline, P(variant > baseline), above a run of all six changes together,
  P(variant > all), above a run of the optimiser change alone, P(variant > amsgrad), and
  above a run of the 0.4 defaults (``--versus`` names other references), over the three
  methods' 30 runs pooled (a choice is the same for the three methods), with a bootstrap
  95% CI (Agarwal et al. 2021); and the same averaged over the two tasks.

The compute is large (Swingup's episodes are always 1000 steps), so the benchmark runs in
chunks: choose them with ``--variants`` and ``--tasks``; finished runs are skipped when
started again with the same ``--out``, and ``--summarize`` only reads what is on disk.
The printout shows the chosen variants and tasks; the JSON (and the comparisons) always
cover every variant and task with finished runs under ``--out``.

    python benchmarks/ablation.py [--variants baseline critic ...] [--tasks pendulum]
                                  [--seeds 10] [--out DIR] [--json FILE] [--summarize]
                                  [--versus baseline all amsgrad ...]
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import payload_command, write_json

from pporpe.evaluation import load_evaluation
from pporpe.experiments.grids.reproduce import reproduce
from pporpe.experiments.grids.spec import parse_spec
from pporpe.experiments.reports.stats import (
    average_probability_of_improvement_ci,
    bootstrap_ci,
    iqm,
    probability_of_improvement_ci,
)
from pporpe.io import atomic_write_text
from pporpe.online.config import AUTHOR_CHOICES, BASELINE_CHOICES, DEFAULT_CHOICES, TESTBED_WEIGHTS
from pporpe.runs.logger import read_records

AUTHOR: dict[str, dict[str, Any]] = {
    "critic": {"critic_signal": "actor"},
    "td_units": {"td_units": "unscaled"},
    "entropy": {"entropy_density": "pre_squash"},
    "amsgrad": {"amsgrad_max": "raw", "amsgrad_decay": 0.99999},
    "layer_norm": {"layer_norm_affine": False},
    "trace_kl": {"trace_divergence": "analytic"},
}
"""Each difference, as the OnlineConfig fields that give the author's choice."""

TESTBED: dict[str, dict[str, Any]] = {
    "weights": dict(TESTBED_WEIGHTS),
    "lr_width": {"lr": 1e-4, "units": 128},
}
"""Where the author's test bed departs from a value the paper states (so never a default,
the paper wins), for diagnosis only: "weights", its regulariser weight 0.1 and balance 0.5,
which make 0.1 * 0.5 * 0.5 = 0.025 per term (the paper: beta_TD = beta_DE = 0.01) and a
reward scale of (1 - gamma)(1 - 0.1 * 0.5) = 0.0095; "lr_width", its lr 1e-4 and 128 units
a layer (the paper: 3e-4 and 100)."""

CHANGES: dict[str, dict[str, Any]] = {**AUTHOR, **TESTBED}
"""Every change a variant may combine, in the order of the tables and folder names."""


def combined(names: Any) -> dict[str, Any]:
    """pporpe 0.2's choices with the named changes of :data:`CHANGES` on top."""
    return {**BASELINE_CHOICES, **{k: v for name in names for k, v in CHANGES[name].items()}}


VARIANTS: dict[str, dict[str, Any]] = {
    "baseline": dict(BASELINE_CHOICES),
    **{name: combined([name]) for name in AUTHOR},
    "all": combined(AUTHOR),
    "all_but_entropy": combined(name for name in AUTHOR if name != "entropy"),
}
"""Each variant's learner settings, every choice explicit (pporpe 0.3's defaults are
"all"; 0.4's are the combination ``td_units+amsgrad+layer_norm+trace_kl``).
"all_but_entropy" is all changes except the pre-squash entropy density, the one that alone
makes Swingup worse (docs/online-learner.md)."""
assert VARIANTS["all"] == dict(AUTHOR_CHOICES)

DEFAULTS = "td_units+amsgrad+layer_norm+trace_kl"
"""pporpe's defaults since 0.4 (``DEFAULT_CHOICES``), as a variant name."""
assert combined(DEFAULTS.split("+")) == dict(DEFAULT_CHOICES)

REFERENCES = ("baseline", "all", "amsgrad", DEFAULTS)
"""The variants every other is compared with by default (``--versus``): pporpe 0.2's
choices, the author's six, the optimiser change alone, the one the rule for pporpe 0.4's
defaults measured the chosen set against (docs/online-learner.md, *The defaults*), and
the 0.4 defaults themselves. The Markdown tables show the first two."""


def variant_settings(name: str) -> dict[str, Any]:
    """A variant's learner settings: a name of :data:`VARIANTS`, or a combination of the
    changes of :data:`CHANGES` joined by ``+`` (``amsgrad+td_units``: pporpe 0.2's choices
    with those changes on top). Raises ValueError naming what is allowed."""
    if name in VARIANTS:
        return dict(VARIANTS[name])
    parts = name.split("+")
    unknown = [p for p in parts if p not in CHANGES]
    if len(parts) < 2 or unknown or len(set(parts)) != len(parts):
        raise ValueError(
            f"variant must be one of {sorted(VARIANTS)} or two or more distinct changes of "
            f"{sorted(CHANGES)} joined by '+'; got {name!r}"
        )
    return combined(parts)


def canonical(name: str) -> str:
    """A combination's changes in :data:`CHANGES`'s order (its folder name), so that
    ``trace_kl+amsgrad`` and ``amsgrad+trace_kl`` are one variant; other names unchanged."""
    variant_settings(name)
    if name in VARIANTS:
        return name
    order = list(CHANGES)
    return "+".join(sorted(name.split("+"), key=order.index))


def variant_arg(name: str) -> str:
    """argparse type for ``--variants``: the :func:`canonical` name, checked."""
    try:
        return canonical(name)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def variants_on_disk(out: Path) -> list[str]:
    """The variants of :data:`VARIANTS`, then the combinations with a folder under ``out``."""
    combos = sorted(
        p.name for p in out.glob("*+*") if p.is_dir() and p.name not in VARIANTS and _valid(p.name)
    )
    return [*VARIANTS, *combos]


def _valid(name: str) -> bool:
    try:
        return canonical(name) == name
    except ValueError:
        return False


THRESHOLD = {"pendulum": 950.0, "swingup": 800.0}
METHODS = ("ppo", "rb", "rpe")


def with_ci(values: list[float], statistic: Any) -> dict[str, float]:
    """The statistic and its bootstrap 95% CI (pporpe.experiments.reports.stats: scipy's BCa)."""
    return bootstrap_ci(values, statistic).as_dict()


def spec_for(variant: str, tasks: list[str], seeds: int, eval_episodes: int, episodes: int) -> Any:
    return parse_spec(
        {
            "name": f"ablation-{variant}",
            "methods": list(METHODS),
            "seeds": seeds,
            "eval_episodes": eval_episodes,
            # its committed runs were trained by the torch engine: a rerun resumes them
            "learner": {**variant_settings(variant), "engine": "torch"},
            "tasks": [{"env": t, "episodes": episodes} for t in tasks],
        },
        f"ablation:{variant}",
    )


def summarize(out: Path, variants: list[str], tasks: list[str]) -> list[dict[str, Any]]:
    rows = []
    for variant in variants:
        for task in tasks:
            for method in METHODS:
                runs = sorted((out / variant / task / method).glob("seed*"))
                done = [r for r in runs if (r / "done.json").exists()]
                if not done:
                    continue
                scores = [ev.median for r in done if (ev := load_evaluation(r)) is not None]
                early = [
                    float(np.mean([rec.ret for rec in read_records(r / "episodes.csv")[:50]]))
                    for r in done
                ]
                rows.append(
                    {
                        "variant": variant,
                        "task": task,
                        "method": method,
                        "seeds": len(done),
                        "mean": with_ci(scores, np.mean),
                        "iqm": with_ci(scores, iqm),
                        "first50_mean_return": with_ci(early, np.mean),
                        "seeds_reaching": int(sum(s >= THRESHOLD[task] for s in scores)),
                        "threshold": THRESHOLD[task],
                        "scores": scores,
                    }
                )
    return rows


def pool_methods(
    rows: list[dict[str, Any]],
) -> tuple[dict[tuple[str, str], list[float]], dict[tuple[str, str], set[str]]]:
    """Per (variant, task): the scores of its methods' runs pooled, and which methods."""
    pooled: dict[tuple[str, str], list[float]] = {}
    methods: dict[tuple[str, str], set[str]] = {}
    for r in rows:
        key = (r["variant"], r["task"])
        pooled.setdefault(key, []).extend(r["scores"])
        methods.setdefault(key, set()).add(r["method"])
    return pooled, methods


def versus(rows: list[dict[str, Any]], reference: str) -> list[dict[str, Any]]:
    """P(variant > reference) per variant and task, the methods' runs pooled, with its CI.

    Only where the variant and the reference each have finished runs of all three methods
    on the task; the pooled run counts are part of each entry (30 when every seed is done).
    """
    pooled, methods = pool_methods(rows)
    out = []
    for (variant, task), scores in pooled.items():
        ref = (reference, task)
        if variant == reference or ref not in pooled:
            continue
        if methods[(variant, task)] != set(METHODS) or methods[ref] != set(METHODS):
            continue
        p = probability_of_improvement_ci(scores, pooled[ref])
        out.append(
            {
                "variant": variant,
                "reference": reference,
                "task": task,
                "runs": len(scores),
                "reference_runs": len(pooled[ref]),
                "p_above": p.as_dict(),
            }
        )
    return out


def versus_both(rows: list[dict[str, Any]], reference: str) -> list[dict[str, Any]]:
    """P(variant > reference) averaged over the tasks, each task's three methods pooled,
    with a bootstrap CI (``average_probability_of_improvement_ci``): a choice is made once
    for every task. Only variants with finished runs of all three methods on every task
    of :data:`THRESHOLD`, as has the reference; the pooled run counts per task are part
    of each entry (30 when every seed is done)."""
    pooled, methods = pool_methods(rows)

    def complete(variant: str) -> bool:
        return all(methods.get((variant, t)) == set(METHODS) for t in THRESHOLD)

    out: list[dict[str, Any]] = []
    if not complete(reference):
        return out
    for variant in dict.fromkeys(r["variant"] for r in rows):
        if variant == reference or not complete(variant):
            continue
        pairs = [(pooled[(variant, t)], pooled[(reference, t)]) for t in THRESHOLD]
        p = average_probability_of_improvement_ci(pairs)
        out.append(
            {
                "variant": variant,
                "reference": reference,
                "tasks": list(THRESHOLD),
                "runs": [len(x) for x, _ in pairs],
                "reference_runs": [len(y) for _, y in pairs],
                "p_above": p.as_dict(),
            }
        )
    return out


def fmt(ci: dict[str, float]) -> str:
    return f"{ci['value']:7.1f} [{ci['low']:7.1f}, {ci['high']:7.1f}]"


def fmt_p(p: dict[str, float]) -> str:
    """A probability with its CI, two decimals: ``0.58 [0.42, 0.72]``."""
    return f"{p['value']:.2f} [{p['low']:.2f}, {p['high']:.2f}]"


TASK_NAMES = {"pendulum": "InvertedPendulum", "swingup": "Swingup"}


def summary_table(rows: list[dict[str, Any]], probs: dict[tuple[str, str, str], str]) -> list[str]:
    """One line per variant, both tasks: the three methods' mean scores, PPO / PPO-RB /
    PPO-RPE, with their seeds at the threshold, and P(> baseline) pooled [95% CI]; then
    P(> baseline) and P(> all) averaged over the two tasks (``probs[("both", ...)]``)."""
    means: dict[tuple[str, str], dict[str, dict[str, Any]]] = {}
    for r in rows:
        means.setdefault((r["variant"], r["task"]), {})[r["method"]] = r
    variants = list(dict.fromkeys(r["variant"] for r in rows))
    head = ["variant"]
    for task in THRESHOLD:
        head += [
            f"{TASK_NAMES[task]}: PPO / PPO-RB / PPO-RPE (seeds >= {THRESHOLD[task]:.0f})",
            "P(> baseline)",
        ]
    head += ["P(> baseline), both tasks", "P(> all), both tasks"]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for v in variants:
        row = [v]
        for task in THRESHOLD:
            got = means.get((v, task), {})
            if not got:
                row += ["not run", ""]
                continue
            score = " / ".join(
                f"{got[m]['mean']['value']:.0f}" if m in got else "-" for m in METHODS
            )
            reach = ", ".join(
                f"{got[m]['seeds_reaching']}/{got[m]['seeds']}" if m in got else "-"
                for m in METHODS
            )
            row += [f"{score} ({reach})", probs.get((task, v, "baseline"), "")]
        row += [probs.get(("both", v, ref), "") for ref in ("baseline", "all")]
        lines.append("| " + " | ".join(row) + " |")
    return lines


def markdown(
    rows: list[dict[str, Any]],
    comparisons: dict[str, list[dict[str, Any]]],
    both: dict[str, list[dict[str, Any]]] | None = None,
) -> str:
    """The tables of benchmarks/results/ablation.md (docs/results/ablation.md shows them):
    :func:`summary_table`, then per task one line per variant with each method's mean
    score [95% CI] and seeds at the threshold, then P(> baseline) and P(> all) pooled over
    the methods [95% CI]."""
    cells: dict[tuple[str, str], dict[str, str]] = {}
    for r in rows:
        m, n = r["mean"], r["seeds"]
        cells.setdefault((r["task"], r["variant"]), {})[r["method"]] = (
            f"{m['value']:.0f} [{m['low']:.0f}, {m['high']:.0f}], {r['seeds_reaching']}/{n}"
        )
    probs: dict[tuple[str, str, str], str] = {}
    for ref, table in comparisons.items():
        for entry in table:
            probs[(entry["task"], entry["variant"], ref)] = fmt_p(entry["p_above"])
    for ref, table in (both or {}).items():
        for entry in table:
            probs[("both", entry["variant"], ref)] = fmt_p(entry["p_above"])
    lines = [*summary_table(rows, probs), ""]
    for task in THRESHOLD:
        variants = [v for (t, v) in cells if t == task]
        if not variants:
            continue
        lines += [
            f"{TASK_NAMES[task]} (mean score [95% CI], seeds >= {THRESHOLD[task]:.0f}):",
            "",
            "| variant | PPO | PPO-RB | PPO-RPE | P(> baseline) | P(> all) |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        for v in variants:
            row = [cells[(task, v)].get(m, "not run") for m in METHODS]
            row += [probs.get((task, v, ref), "") for ref in ("baseline", "all")]
            lines.append(f"| {v} | " + " | ".join(row) + " |")
        lines.append("")
    return "\n".join(lines).rstrip("\n") + "\n"


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--variants",
        nargs="+",
        default=list(VARIANTS),
        type=variant_arg,
        metavar="VARIANT",
        help=f"{', '.join(VARIANTS)}, or two or more of {', '.join(CHANGES)} joined by '+' "
        "(e.g. amsgrad+td_units)",
    )
    parser.add_argument("--tasks", nargs="+", default=["pendulum", "swingup"])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--eval-episodes", type=int, default=50)
    parser.add_argument("--episodes", type=int, default=200, help="training episodes (paper: 200)")
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument(
        "--out",
        default="benchmarks/results/ablation",
        help="run folders (their checkpoints and TensorBoard logs are not committed)",
    )
    parser.add_argument("--json", default="benchmarks/results/ablation.json")
    parser.add_argument(
        "--markdown",
        default="benchmarks/results/ablation.md",
        help="the same summary as Markdown tables (every variant on disk)",
    )
    parser.add_argument("--summarize", action="store_true", help="only read finished runs")
    parser.add_argument(
        "--versus",
        nargs="+",
        default=list(REFERENCES),
        type=variant_arg,
        metavar="VARIANT",
        help="the variants to compare every other with, P(variant > it) "
        f"(default: {' '.join(REFERENCES)})",
    )
    return parser.parse_args()


def train(args: argparse.Namespace, out: Path) -> None:
    """Train (or resume) the chosen variants' runs on the chosen tasks, each into out/VARIANT."""
    for variant in args.variants:
        spec = spec_for(variant, args.tasks, args.seeds, args.eval_episodes, args.episodes)
        settings = variant_settings(variant)
        changed = {k: v for k, v in settings.items() if BASELINE_CHOICES.get(k) != v}
        print(f"variant {variant}: {changed or 'pporpe 0.2 choices'}", flush=True)
        outcome = reproduce(spec, out / variant, workers=args.workers)
        print(f"  {len(outcome.done)} done, {len(outcome.failed)} failed, "
              f"{outcome.wall_time:.0f} s", flush=True)  # fmt: skip


@dataclass(frozen=True)
class Summary:
    """Every variant and task with finished runs under ``--out``: the JSON's content."""

    names: list[str]
    """The variants on disk (:func:`variants_on_disk`)."""
    rows: list[dict[str, Any]]
    """:func:`summarize`'s rows, every task of :data:`THRESHOLD`."""
    versus: dict[str, list[dict[str, Any]]]
    """Per reference, :func:`versus`'s comparisons."""
    both: dict[str, list[dict[str, Any]]]
    """Per reference, :func:`versus_both`'s comparisons."""

    @classmethod
    def of(cls, out: Path, references: list[str]) -> Summary:
        names = variants_on_disk(out)
        rows = summarize(out, names, list(THRESHOLD))
        return cls(
            names=names,
            rows=rows,
            versus={ref: versus(rows, ref) for ref in references},
            both={ref: versus_both(rows, ref) for ref in references},
        )


@dataclass(frozen=True)
class Shown:
    """What the printout shows: the chosen variants on the chosen tasks."""

    variants: list[str]
    pairs: set[tuple[str, str]]
    """Every (variant, task) chosen."""
    width: int
    """The width of the variant column."""


def print_rows(rows: list[dict[str, Any]], shown: Shown) -> None:
    """One line per chosen variant, task and method: scores with their CIs."""
    w = shown.width
    header = (
        f"{'variant':{w}s} {'task':9s} {'method':6s} {'n':>3s} {'mean score [95% CI]':>27s} "
        f"{'IQM [95% CI]':>27s} {'first-50 mean [95% CI]':>27s} {'>= thr':>7s}"
    )
    print(header)
    print("-" * len(header))
    for r in rows:
        if (r["variant"], r["task"]) not in shown.pairs:
            continue
        print(
            f"{r['variant']:{w}s} {r['task']:9s} {r['method']:6s} {r['seeds']:3d} "
            f"{fmt(r['mean']):>27s} {fmt(r['iqm']):>27s} {fmt(r['first50_mean_return']):>27s} "
            f"{r['seeds_reaching']:3d}/{r['seeds']:<3d}"
        )


def print_versus(summary: Summary, shown: Shown) -> None:
    """The chosen variants' comparisons with each reference, per task then over both."""
    w = shown.width
    for ref, table in summary.versus.items():
        per_task = [v for v in table if (v["variant"], v["task"]) in shown.pairs]
        if not per_task:
            continue
        print(f"\nP(variant > {ref}), the three methods' runs pooled [95% CI]:")
        for v in per_task:
            ci = fmt_p(v["p_above"])
            runs = f"({v['runs']} vs {v['reference_runs']} runs)"
            print(f"{v['variant']:{w}s} {v['task']:9s} {ci}  {runs}")
    for ref, table in summary.both.items():
        averaged = [v for v in table if v["variant"] in shown.variants]
        if not averaged:
            continue
        print(f"\nP(variant > {ref}), mean over both tasks [95% CI]:")
        for v in averaged:
            print(f"{v['variant']:{w}s} {fmt_p(v['p_above'])}")


def write_outputs(summary: Summary, json_path: str, markdown_path: str) -> None:
    """The JSON (with the variants' settings) and the Markdown tables."""
    payload = {
        "variants": {n: variant_settings(n) for n in summary.names},
        "rows": summary.rows,
        "versus": summary.versus,
        "versus_both_tasks": summary.both,
    }
    path = write_json(json_path, payload)
    print(f"wrote {path}")
    header = f"<!-- written by: {payload_command()} -->\n\n"
    md = atomic_write_text(
        markdown_path, header + markdown(summary.rows, summary.versus, summary.both)
    )
    print(f"wrote {md}")


def main() -> None:
    args = parse_args()
    out = Path(args.out)
    if not args.summarize:
        train(args, out)
    # The JSON and the comparisons cover every variant and task on disk, so that a chunk's
    # command never overwrites the file with a subset; the printout is the chosen ones.
    summary = Summary.of(out, list(dict.fromkeys(args.versus)))
    pairs = {(v, t) for v in args.variants for t in args.tasks}
    shown = Shown(args.variants, pairs, width=max(map(len, summary.names)))
    print_rows(summary.rows, shown)
    print_versus(summary, shown)
    write_outputs(summary, args.json, args.markdown)


if __name__ == "__main__":
    main()
