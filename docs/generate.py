"""Write the documentation's generated pages from the committed results.

Every table of the results pages (``docs/results/*.md``) and the README's results table
comes from a committed result file, never from a hand-copied number:

* ``docs/results/reproduction.md``: ``results/paper/REPORT.md`` (``pporpe report``, from the
  committed run folders) with its figures;
* ``docs/results/ablation.md``: ``benchmarks/results/ablation.md`` and ``ablation.json``
  (``benchmarks/ablation.py --summarize``, from the committed run folders) and
  ``pendulum_behaviour*.json``;
* ``docs/results/throughput.md``: ``benchmarks/results/throughput*.json``;
* ``docs/results/vs-sb3.md``: ``benchmarks/results/vs_sb3.json``;
* ``docs/results/engines.md``: ``benchmarks/results/engine_shadow.json`` and
  ``engine_divergence.json``;
* ``docs/results/batch-mujoco.md``: ``results/batch-mujoco/REPORT.md`` once that grid's
  results are committed (until then a page that says it has not run yet);
* the block of ``README.md`` between the ``results`` markers: per task the most conclusive
  committed grid's ``REPORT.md`` and ``summary.csv`` (:data:`HEADLINE_GRIDS`), and the
  batch grid's once committed.

The README's headline figure (``results/headline.png``) is drawn from the same grids by
``experiments/headline.py``, which needs the package; ``--check`` names it while the
sources it recorded (``results/headline.json``) are not today's.

    python docs/generate.py           # rewrite the pages that changed
    python docs/generate.py --check   # exit 1 naming the pages that are not up to date

``make docs`` runs the check before it builds; ``make docs-pages`` rewrites. Only the
standard library is used, so this runs before anything is installed.
"""

from __future__ import annotations

import argparse
import ast
import csv
import json
import re
import statistics
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
TASKS = {
    "pendulum": "InvertedPendulum",
    "swingup": "Swingup",
    "halfcheetah": "HalfCheetah",
    "ant": "Ant",
}
METHODS = {"ppo": "PPO", "rb": "PPO-RB", "rpe": "PPO-RPE"}
README_START = (
    "<!-- results: written by python docs/generate.py from the committed grids' REPORT.md "
    "and summary.csv -->"
)
README_END = "<!-- end of results -->"

Row = list[str]


def banner(*sources: str) -> str:
    """The first line of a generated page: where it comes from, and not to edit it."""
    names = ", ".join(f"`{s}`" for s in sources)
    return f"<!-- Written by python docs/generate.py from {names}; edit the script, not here. -->"


def table(head: Row, rows: list[Row], align: Row | None = None) -> list[str]:
    """A Markdown table; ``align`` holds one separator cell per column (default ``---``)."""
    sep = align or ["---"] * len(head)
    return ["| " + " | ".join(r) + " |" for r in (head, sep, *rows)]


def md_tables(text: str) -> list[list[Row]]:
    """The Markdown tables of a text, in order: each a list of rows of stripped cells, its
    header first and its separator row dropped."""
    tables: list[list[Row]] = []
    current: list[Row] = []
    for line in [*text.splitlines(), ""]:
        if line.strip().startswith("|"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if not all(set(c) <= set(":- ") for c in cells):
                current.append(cells)
        elif current:
            tables.append(current)
            current = []
    return tables


def find_table(text: str, first_column: str, source: str) -> list[Row]:
    """The first table of ``text`` whose header row includes ``first_column``."""
    for rows in md_tables(text):
        if first_column in rows[0]:
            return rows
    raise ValueError(f"{source} has no table with a {first_column!r} column")


def read_json(root: Path, path: str) -> Any:
    return json.loads((root / path).read_text(encoding="utf-8"))


def fmt_p(p: dict[str, float]) -> str:
    """A probability with its CI, as benchmarks/ablation.py writes it: ``0.58 [0.42, 0.72]``."""
    return f"{p['value']:.2f} [{p['low']:.2f}, {p['high']:.2f}]"


def machine_line(machine: dict[str, Any], command: str) -> str:
    """Where and how a benchmark ran, from its JSON's ``machine`` and ``command``."""
    threads = machine.get("torch_threads", "?")
    return (
        f"Measured by `{command}` on {machine.get('cpu', '?')} ({machine.get('cores', '?')} "
        f"cores), torch {machine.get('torch', '?')} with {threads} "
        f"thread{'' if threads == 1 else 's'}, at {machine.get('time', '?')}."
    )


# --- The paper's comparison -------------------------------------------------------------


HEADLINE_GRIDS: dict[str, tuple[str, ...]] = {
    "pendulum": ("results/paper-50seeds", "results/paper"),
    "swingup": ("results/paper-50seeds", "results/paper"),
    "halfcheetah": ("results/paper-full", "results/paper"),
    "ant": ("results/paper-full", "results/paper"),
}
"""Per task, the grids of the paper's comparison (Table I as printed) the README's headline
may come from, most conclusive first: the 50-seed grid (``experiments/paper-50seeds.toml``)
for the pendulum tasks, the full-length grid (``experiments/paper-full.toml``, 2000
episodes) for the locomotion tasks, then the first reproduction (``experiments/paper.toml``,
10 seeds, 200 episodes), which stays in the docs."""
HEADLINE_MIN_SEEDS = 10
"""A grid is the headline's source for a task once every method has this many finished
seeds there (the project's floor for a learning-quality verdict); before that the next
grid of :data:`HEADLINE_GRIDS` is."""
WHAT_RAN = re.compile(r"^- (\w+): (\d+) training episodes per run, (\d+)/(\d+) runs finished")


def paper_means(root: Path, grid: str = "results/paper") -> dict[tuple[str, str], float]:
    """Mean score per (task, method name) from a grid's ``summary.csv``."""
    with open(root / grid / "summary.csv", encoding="utf-8") as f:
        return {(r["task"], r["method"]): float(r["mean_score"]) for r in csv.DictReader(f)}


def grid_seeds(root: Path, grid: str, mean_column: str = "mean_score") -> dict[str, int]:
    """Per task of a grid's ``summary.csv``, the fewest finished seeds of any method with a
    finite ``mean_column``."""
    seeds: dict[str, int] = {}
    with open(root / grid / "summary.csv", encoding="utf-8") as f:
        for r in csv.DictReader(f):
            n = int(r["seeds"]) if r[mean_column] not in ("", "nan") else 0
            seeds[r["task"]] = min(seeds.get(r["task"], n), n)
    return seeds


def training_length(root: Path, grid: str) -> dict[str, int]:
    """Per task of an online grid, its training episodes per run, from REPORT.md's
    "What ran"."""
    text = (root / grid / "REPORT.md").read_text(encoding="utf-8")
    return {m[1]: int(m[2]) for m in map(WHAT_RAN.match, text.splitlines()) if m}


def paper_claims(
    root: Path, grid: str = "results/paper"
) -> dict[tuple[str, str, str], tuple[str, str]]:
    """(claim, task, rival) -> (P(PPO-RPE > rival) [CI], verdict), from a grid's REPORT.md
    claims table."""
    rows = find_table((root / grid / "REPORT.md").read_text(), "claim", f"{grid}/REPORT.md")
    return claims_of(rows)


def claims_of(rows: list[Row]) -> dict[tuple[str, str, str], tuple[str, str]]:
    """(claim, task, rival) -> (P(PPO-RPE > rival) [CI], verdict) of a claims table's rows
    (its header first)."""
    head = rows[0]
    i = {name: head.index(name) for name in ("claim", "task", "rival", "verdict")}
    p = next(k for k, name in enumerate(head) if name.startswith("P(PPO-RPE"))
    return {(r[i["claim"]], r[i["task"]], r[i["rival"]]): (r[p], r[i["verdict"]]) for r in rows[1:]}


RIVALS = ("PPO", "PPO-RB")
"""The methods PPO-RPE is compared with, in the order of a row's verdicts."""


def short_verdict(verdicts: list[str]) -> str:
    """One verdict for a row (one per rival of :data:`RIVALS`): the shared one, shortened,
    or each one with its rival."""
    short = [v.split(" (")[0].split(", on the")[0] for v in verdicts]
    if len(set(short)) == 1:
        return short[0]
    return ", ".join(f"{v} against {rival}" for v, rival in zip(short, RIVALS, strict=True))


def headline_grid(root: Path, task: str) -> str | None:
    """The grid the README's row of ``task`` comes from (:data:`HEADLINE_GRIDS`): the first
    with a committed report where every method has :data:`HEADLINE_MIN_SEEDS` seeds of the
    task, else the last one committed with the task; None if none is."""
    seeds = {g: grid_seeds(root, g).get(task, 0) for g in HEADLINE_GRIDS[task]
             if (root / g / "REPORT.md").exists()}  # fmt: skip
    committed = [g for g, n in seeds.items() if n > 0]
    for grid in committed:
        if seeds[grid] >= HEADLINE_MIN_SEEDS:
            return grid
    return committed[-1] if committed else None


HEADLINE_FIGURE = "results/headline.png"
"""The README's headline figure: per task, the learning curves of its headline grid."""
HEADLINE_SOURCES = "results/headline.json"
"""What :data:`HEADLINE_FIGURE` was drawn from (:func:`headline_sources`), written with it
by ``experiments/headline.py``; ``--check`` compares it with today's."""
HEADLINE_COMMAND = "python experiments/headline.py"


def method_seeds(root: Path, grid: str, task: str) -> dict[str, int]:
    """Finished seeds per method of ``task`` in a grid's ``summary.csv`` (those of the
    result that stands, :func:`standing_result`, while its pre-registered verdict is
    pending)."""
    standing = standing_result(root, grid).get(task)
    if standing:
        return dict(standing["seeds"])
    with open(root / grid / "summary.csv", encoding="utf-8") as f:
        return {r["method"]: int(r["seeds"]) for r in csv.DictReader(f) if r["task"] == task}


def headline_sources(root: Path) -> dict[str, dict[str, Any]]:
    """Per task with a committed grid, what the headline figure draws: its headline grid
    (:func:`headline_grid`, the README table's), the training episodes per run there and
    the finished seeds per method."""
    out: dict[str, dict[str, Any]] = {}
    for task in TASKS:
        grid = headline_grid(root, task)
        if grid is not None:
            out[task] = {
                "grid": grid,
                "episodes": training_length(root, grid)[task],
                "seeds": method_seeds(root, grid, task),
            }
    return out


def headline_figure_stale(root: Path) -> bool:
    """Whether :data:`HEADLINE_SOURCES` (so the figure) is not what the committed grids give."""
    path = root / HEADLINE_SOURCES
    if not path.exists():
        return True
    return bool(json.loads(path.read_text(encoding="utf-8")) != headline_sources(root))


STANDING_HEADING = "## The result that stands until the pre-registered verdict"
"""The section of a REPORT.md (``pporpe report``) that holds, for each task whose
pre-registered verdict is pending, the result of its seeds finished before the
pre-registration: the README keeps that result until the verdict is read."""


def standing_result(root: Path, grid: str) -> dict[str, dict[str, Any]]:
    """Per task of a grid's pending pre-registration (:data:`STANDING_HEADING`): its mean
    scores per method name, the fewest seeds of a method, and its claims ((claim, task,
    rival) -> (P [CI], verdict)), from that section of REPORT.md; empty if it has none."""
    text = (root / grid / "REPORT.md").read_text(encoding="utf-8")
    if STANDING_HEADING not in text:
        return {}
    section = text.split(STANDING_HEADING, 1)[1].split("\n## ", 1)[0]
    scores = find_table(section, "mean score [95% CI]", f"{grid}/REPORT.md")
    claims = find_table(section, "claim", f"{grid}/REPORT.md")
    i = {name: scores[0].index(name) for name in ("task", "method", "seeds")}
    mean = scores[0].index("mean score [95% CI]")
    out: dict[str, dict[str, Any]] = {}
    for r in scores[1:]:
        task = out.setdefault(r[i["task"]], {"means": {}, "seeds": {}, "claims": {}})
        task["means"][(r[i["task"]], r[i["method"]])] = float(r[mean].split()[0])
        task["seeds"][r[i["method"]]] = int(r[i["seeds"]])
    for key, value in claims_of(claims).items():
        out[key[1]]["claims"][key] = value
    return out


def readme_row(root: Path, grid: str, task: str) -> Row:
    """One task of an online grid: the task linked to the grid's report, its training
    episodes, seeds, the mean scores, P(PPO-RPE > rival) of the final score and the
    verdicts of the paper's claims of final score, early learning and regularisation ("-"
    where the paper makes no early-learning claim)."""
    standing = standing_result(root, grid).get(task)
    if standing:  # a pre-registered verdict pending: the result that stands until then
        means, claims = standing["means"], standing["claims"]
        n_seeds = min(standing["seeds"].values())
    else:
        means, claims = paper_means(root, grid), paper_claims(root, grid)
        n_seeds = grid_seeds(root, grid)[task]
    scores = " / ".join(f"{means[(task, m)]:.0f}" for m in METHODS.values())
    final = [claims[("final performance", task, rival)] for rival in RIVALS]
    early = [claims.get(("early learning", task, rival)) for rival in RIVALS]
    reg = [claims[("regularisation", task, rival)] for rival in RIVALS]
    verdicts = [
        short_verdict([v for _, v in final]),
        short_verdict([e[1] for e in early if e]) if all(early) else "-",
        short_verdict([v for _, v in reg]),
    ]
    name = f"[{TASKS[task]}]({grid}/REPORT.md)"
    length = f"{training_length(root, grid)[task]} episodes"
    seeds = str(n_seeds)
    return [name, length, seeds, scores, final[0][0], final[1][0], *verdicts]


BATCH_GRID = "results/batch-mujoco"
"""The batch study's grid (``experiments/batch-mujoco.toml``): its page and README rows
appear once its REPORT.md is committed."""
BATCH_SCORE = "score_mean_value"
"""The batch grid's ``summary.csv`` column of the mean test score."""


def batch_readme_rows(root: Path, grid: str = BATCH_GRID) -> list[Row]:
    """Per task of a batch grid (``pporpe report``'s batch REPORT.md and summary.csv), and
    pooled over its tasks: the mean test scores (pooled: the IQM of the normalised scores),
    P(PPO-RPE > rival) of the test score and its verdict ("-" for the online grids' claims
    of early learning and regularisation); the pooled row once two tasks have one."""
    report = (root / grid / "REPORT.md").read_text(encoding="utf-8")
    with open(root / grid / "summary.csv", encoding="utf-8") as f:
        means = {(r["task"], r["method"]): float(r[BATCH_SCORE]) for r in csv.DictReader(f)}
    seeds = grid_seeds(root, grid, BATCH_SCORE)
    tables = md_tables(report)
    per_task = next(t for t in tables if t[0][:3] == ["claim", "task", "rival"])
    pooled = next(t for t in tables if t[0][:2] == ["claim", "rival"])
    iqms = next(t for t in tables if t[0][:2] == ["claim", "method"])
    rows = []
    for task in dict.fromkeys(t for t, _ in means):
        got = {r[2]: (r[3], r[5]) for r in per_task[1:] if r[:2] == ["test score", task]}
        if not {"PPO", "PPO-RB"} <= set(got) or not seeds.get(task):
            continue
        scores = " / ".join(f"{means[(task, m)]:.0f}" for m in METHODS.values())
        verdict = short_verdict([got[r][1] for r in RIVALS])
        rows.append([f"[{task}]({grid}/REPORT.md)", BATCH_LENGTH, str(seeds[task]), scores,
                     got["PPO"][0], got["PPO-RB"][0], verdict, "-", "-"])  # fmt: skip
    p = {r[1]: (r[3], r[4]) for r in pooled[1:] if r[0] == "test score"}
    iqm = {r[1]: r[4].split(" [")[0] for r in iqms[1:] if r[0] == "test score"}
    if len(rows) > 1 and {"PPO", "PPO-RB"} <= set(p) and set(METHODS.values()) <= set(iqm):
        scores = " / ".join(iqm[m] for m in METHODS.values()) + " (IQM, normalised)"
        verdict = short_verdict([p[r][1] for r in RIVALS])
        n = str(min(int(r[2]) for r in rows))
        rows.append([f"[{len(rows)} tasks, pooled]({grid}/REPORT.md)", BATCH_LENGTH, n, scores,
                     p["PPO"][0], p["PPO-RB"][0], verdict, "-", "-"])  # fmt: skip
    return rows


BATCH_LENGTH = "batch PPO"
"""The training column of the batch grid's README rows (the steps are in the sentence
above the table)."""
README_HEAD = ["task", "training", "seeds", "mean score: PPO / PPO-RB / PPO-RPE",
               "P(PPO-RPE > PPO)", "P(PPO-RPE > PPO-RB)", "final score", "early learning",
               "stronger regularisation"]  # fmt: skip


def verdict_sentence(claim: str, rows: list[Row], column: int) -> str:
    """``claim``, then the tasks grouped by their verdict in ``column``, in order."""
    groups: dict[str, list[str]] = {}
    for r in rows:
        if r[column] != "-":
            groups.setdefault(r[column], []).append(r[0].split("](")[0].lstrip("["))
    parts = [f"{v} on {', '.join(tasks)}" for v, tasks in groups.items()]
    return f"- {claim}: {'; '.join(parts)}." if parts else ""


def batch_sentence(rows: list[Row]) -> str:
    """The batch grid's verdicts in words: per task, then pooled (the last row, when it is
    the pooled one)."""
    tasks = [r for r in rows if "pooled" not in r[0]]
    text = verdict_sentence("In batch PPO, its test score against PPO and PPO-RB", tasks, 6)
    pooled = [r for r in rows if "pooled" in r[0]]
    if text and pooled:
        text = f"{text[:-1]}; pooled over the {len(tasks)} tasks, {pooled[0][6]}."
    link = rows[0][0].split("](")[-1].rstrip(")") if rows else ""
    return f"{text[:-1]} ([the study]({link}))." if text else ""


def readme_results(root: Path) -> list[str]:
    """The README's headline: per task the row of its most conclusive committed grid
    (:func:`headline_grid`), then the batch grid's (:func:`batch_readme_rows`) once
    committed; below the table, the verdicts of each claim in words."""
    online = [readme_row(root, grid, task) for task in TASKS
              if (grid := headline_grid(root, task))]  # fmt: skip
    batch = batch_readme_rows(root) if (root / BATCH_GRID / "REPORT.md").exists() else []
    lines = table(README_HEAD, online + batch, [":---", ":---", "---:", *[":---:"] * 3,
                                                ":---", ":---", ":---"])  # fmt: skip
    words = [
        verdict_sentence("PPO-RPE's final score against PPO and PPO-RB, online", online, 6),
        verdict_sentence("Its early learning", online, 7),
        verdict_sentence("Its stronger regularisation", online, 8),
        batch_sentence(batch),
    ]
    return [*lines, "", *[w for w in words if w]]


def rewrite_blocks(text: str, start: str, end: str, blocks: list[list[str]], where: str) -> str:
    """``text`` with its k-th block between the markers ``start`` ... ``end`` replaced by
    the lines ``blocks[k]`` (the markers kept); a ValueError naming ``where`` unless the
    markers enclose exactly ``len(blocks)`` blocks."""
    head, *rest = text.split(start)
    if len(rest) != len(blocks) or any(end not in after for after in rest):
        raise ValueError(
            f"{where} lacks {len(blocks)} block(s) between the markers {start!r} ... {end!r}"
        )
    out = [head]
    for block, after in zip(blocks, rest, strict=True):
        out.append("\n".join([start, *block, end]) + after[after.index(end) + len(end) :])
    return "".join(out)


def with_readme_results(root: Path) -> str:
    """README.md with the block between the results markers rewritten."""
    text = (root / "README.md").read_text(encoding="utf-8")
    return rewrite_blocks(text, README_START, README_END, [readme_results(root)], "README.md")


def report_page(root: Path, grid: str, title: str, lead: str) -> str:
    """A grid's REPORT.md as a docs page, its figures linked from the page's folder."""
    report = (root / grid / "REPORT.md").read_text(encoding="utf-8")
    body = report.split("\n", 1)[1].lstrip("\n")  # drop the report's title
    body = re.sub(r"\]\((fig_[\w.]+)\)", rf"](../../{grid}/\1)", body)
    head = [f"# {title}", "", banner(f"{grid}/REPORT.md"), "", lead, ""]
    return "\n".join(head) + body.rstrip("\n") + "\n"


def reproduction_page(root: Path) -> str:
    """The report of the committed grid with the paper's Table I."""
    return report_page(
        root, "results/paper", "The paper's comparison, reproduced",
        "`experiments/paper.toml` run by `make reproduce-paper` into `results/paper/`, whose "
        "small per-run files are committed; `pporpe report results/paper` writes the report "
        "below from them (the same text as `results/paper/REPORT.md`, with the per-seed "
        "table in `results/paper/summary.csv`).",
    )  # fmt: skip


def reproduction_testbed_page(root: Path) -> str:
    """The report of the committed grid with the author's test bed settings."""
    return report_page(
        root, "results/paper-testbed", "The paper's comparison with the test bed's settings",
        "`experiments/paper-testbed.toml` (the paper's two pendulum tasks, 10 seeds per "
        "method, with `pporpe.online.TESTBED`, the settings of the author's public test bed, "
        "for all three methods) run by `pporpe reproduce experiments/paper-testbed.toml --out "
        "results/paper-testbed --report` into `results/paper-testbed/`, whose small per-run "
        "files are committed. Beside it: [the same comparison with Table I](reproduction.md), "
        "and [pporpe beside the test bed](../testbed.md).",
    )  # fmt: skip


def reproduction_50seeds_page(root: Path) -> str:
    """The report of the pendulum tasks at 50 seeds (committed run by run while it runs)."""
    return report_page(
        root, "results/paper-50seeds", "The pendulum tasks at 50 seeds",
        "`experiments/paper-50seeds.toml`: the paper's two pendulum tasks with Table I (the "
        "learner of [the first reproduction](reproduction.md), by the fused engine), 50 seeds "
        "per method, where a confidence interval of P(PPO-RPE > rival) is narrow enough to "
        "say *equivalent*. The grid runs outside the repository (`pporpe reproduce "
        "experiments/paper-50seeds.toml --out DIR`); `python experiments/collect.py DIR "
        "results/paper-50seeds` commits each finished run, and `pporpe report "
        "results/paper-50seeds` writes the report below from those committed. *What ran* "
        "says how many runs it covers: until every run is done, its verdicts are those of "
        "the seeds finished.",
    )  # fmt: skip


def batch_mujoco_page(root: Path) -> str:
    """The report of the batch study (``experiments/batch-mujoco.toml``), or a page that
    says it has not run yet while ``results/batch-mujoco/REPORT.md`` is not committed."""
    title = "Batch PPO on MuJoCo: PPO, PPO-RB and PPO-RPE with CleanRL's settings"
    lead = (
        "`experiments/batch-mujoco.toml`: batch PPO (rollouts, then minibatch epochs) with "
        "CleanRL's `ppo_continuous_action.py` settings for every run, PPO, PPO-RB and "
        "PPO-RPE on HalfCheetah-v4, Hopper-v4, Walker2d-v4 and Ant-v4, 10 seeds, 1M steps "
        "per run. `pporpe reproduce experiments/batch-mujoco.toml --out DIR` trains it; "
        "`python experiments/collect.py DIR results/batch-mujoco` commits the finished runs "
        "and `pporpe report results/batch-mujoco` writes the report below from them: per "
        "task and pooled over the tasks (rliable's IQM of normalised scores and average "
        "probability of improvement), by environment steps."
    )
    return report_or_pending(root, BATCH_GRID, "experiments/batch-mujoco.toml", title, lead)


def report_or_pending(root: Path, grid: str, spec: str, title: str, lead: str) -> str:
    """:func:`report_page` of ``grid`` once its REPORT.md is committed; until then a page
    that says so (generated from the spec ``spec``)."""
    if (root / grid / "REPORT.md").exists():
        return report_page(root, grid, title, lead)
    head = [f"# {title}", "", banner(spec), "", lead, ""]
    return "\n".join([*head, "Not run yet: no results of this grid are committed "
                      f"(`{grid}/REPORT.md` does not exist).", ""])  # fmt: skip


def reproduction_full_page(root: Path) -> str:
    """The report of the paper's grid at full length (committed run by run while it runs),
    or a page that says it has not run yet."""
    return report_or_pending(
        root, "results/paper-full", "experiments/paper-full.toml",
        "The paper's comparison at full length",
        "`experiments/paper-full.toml`: the paper's four tasks with Table I (the learner of "
        "[the first reproduction](reproduction.md)), 10 seeds per method, HalfCheetah and Ant "
        "at the 2000 training episodes of the author's test bed (a tenth of that in the "
        "first reproduction), the pendulum tasks at 200, 50 test episodes per run. The grid "
        "runs outside the repository (`pporpe reproduce experiments/paper-full.toml --out "
        "DIR`, resumable); `python experiments/collect.py DIR results/paper-full` commits "
        "each finished run, and `pporpe report results/paper-full` writes the report below "
        "from those committed. *What ran* says how many runs it covers: until every run is "
        "done, its verdicts are those of the seeds finished.",
    )  # fmt: skip


# --- The learner ablation ---------------------------------------------------------------


def ablation_comparisons(data: dict[str, Any]) -> dict[tuple[str, str], dict[str, float]]:
    """(variant, reference) -> P(variant > reference) averaged over both tasks."""
    return {
        (v["variant"], ref): v["p_above"]
        for ref, entries in data["versus_both_tasks"].items()
        for v in entries
    }


def effect(p: dict[str, float]) -> str:
    """Better or worse when the CI excludes 0.5, else neutral."""
    if p["low"] > 0.5:
        return "better"
    return "worse" if p["high"] < 0.5 else "neutral"


def ablation_verdict(data: dict[str, Any]) -> list[str]:
    """The conclusions, each number read from ablation.json."""
    both = ablation_comparisons(data)
    named = {"baseline", "all", "all_but_entropy"}
    singles = [v for v in data["variants"] if "+" not in v and v not in named]
    rows = [
        [f"`{v}`", fmt_p(both[(v, "baseline")]), effect(both[(v, "baseline")])]
        for v in singles
        if (v, "baseline") in both
    ]
    lines = [
        "Each of the author's choices alone, on top of pporpe 0.2's (the baseline), averaged "
        "over both tasks; *better* or *worse* where the CI excludes 0.5:",
        "",
        *table(["change alone", "P(> baseline), both tasks", "effect"], rows),
        "",
    ]
    defaults = "td_units+amsgrad+layer_norm+trace_kl"
    refs = [r for r in ("baseline", "all", "amsgrad") if (defaults, r) in both]
    if refs:
        against = ", ".join(f"P(> {r}) {fmt_p(both[(defaults, r)])}" for r in refs)
        lines += [
            f"pporpe's defaults since 0.4 (`{defaults}`, `pporpe.online.DEFAULT_CHOICES`) keep "
            "the author's choices that are not worse alone and drop those that are. Over both "
            f"tasks: {against}.",
            "",
        ]
    return lines


def p_task(data: dict[str, Any], variant: str, reference: str, task: str) -> str:
    """P(variant > reference) on one task, or ``"not run"``."""
    for v in data["versus"].get(reference, []):
        if v["variant"] == variant and v["task"] == task:
            return fmt_p(v["p_above"])
    return "not run"


def best_mean(data: dict[str, Any], task: str) -> str:
    """The variant and method with the highest mean score on a task, with its CI."""
    r = max((r for r in data["rows"] if r["task"] == task), key=lambda r: r["mean"]["value"])
    m = r["mean"]
    return (
        f"`{r['variant']}` with {METHODS[r['method']]}, {m['value']:.0f} "
        f"[{m['low']:.0f}, {m['high']:.0f}]"
    )


def ablation_findings(data: dict[str, Any]) -> list[str]:
    """What else the runs say, each number read from ablation.json."""
    both = ablation_comparisons(data)
    defaults, weights = "td_units+amsgrad+layer_norm+trace_kl", "+weights"
    lines = [
        f"- All six together (`all`) help on InvertedPendulum (P(> baseline) "
        f"{p_task(data, 'all', 'baseline', 'pendulum')}) and not on Swingup "
        f"({p_task(data, 'all', 'baseline', 'swingup')}), where their policies drive the "
        "cart at the action bounds (the last table).",
        f"- The best Swingup mean is {best_mean(data, 'swingup')}; on InvertedPendulum "
        f"{best_mean(data, 'pendulum')}.",
    ]
    for v in data["variants"]:
        if v == defaults + weights and (v, defaults) in both:
            lines.append(
                f"- The test bed's regulariser weights on top of the defaults (`{v}`), "
                f"against the defaults: InvertedPendulum "
                f"{p_task(data, v, defaults, 'pendulum')}, Swingup "
                f"{p_task(data, v, defaults, 'swingup')}, both tasks "
                f"{fmt_p(both[(v, defaults)])}; the defaults keep the paper's weights."
            )
    return [*lines, ""]


def behaviour_table(root: Path) -> list[str]:
    """What the trained Swingup and InvertedPendulum policies do, from pendulum_behaviour*.json."""
    rows = []
    for name in ("pendulum_behaviour_pendulum.json", "pendulum_behaviour.json"):
        data = read_json(root, f"benchmarks/results/{name}")
        for g in data["groups"]:
            *_, variant, task, method = g["group"].split("/")
            name = [TASKS.get(task, task), f"`{variant}`", METHODS.get(method, method)]
            upright, saturated = f"{100 * g['upright']:.0f}%", f"{100 * g['saturated']:.0f}%"
            rows.append([*name, upright, f"{g['mean_abs_action']:.2f}", saturated,
                         f"{g['turns']:.1f}"])  # fmt: skip
    head = ["task", "variant", "method", "upright", "mean abs(a)", "saturated", "net turns"]
    return table(head, rows, ["---", "---", "---", "---:", "---:", "---:", "---:"])


def ablation_page(root: Path) -> str:
    data = read_json(root, "benchmarks/results/ablation.json")
    tables = (root / "benchmarks/results/ablation.md").read_text(encoding="utf-8")
    tables = "\n".join(ln for ln in tables.splitlines() if not ln.startswith("<!--")).strip()
    lines = [
        "# The learner ablation",
        "",
        banner("benchmarks/results/ablation.md", "ablation.json", "pendulum_behaviour*.json"),
        "",
        "Where the paper is silent, the author's public test bed made six choices that "
        "pporpe 0.2 did not ([the choices](../online-learner.md)). `benchmarks/ablation.py` "
        "trains each alone on top of pporpe 0.2's choices (`baseline`), all six together "
        "(`all`, pporpe 0.3's defaults) and combinations joined with `+`, each variant with "
        "PPO, PPO-RB and PPO-RPE on InvertedPendulum and Swingup: 10 seeds, the paper's 200 "
        "episodes, a run's score the median of 50 test episodes. P(> reference) is the "
        "probability that a run of the variant scores above a run of the reference, the "
        "three methods' 30 runs of a task pooled (a choice is the same for the three), with "
        "its bootstrap 95% CI; *both tasks* averages the two tasks. `+weights` adds the test "
        "bed's regulariser weights and reward scale, which the paper states otherwise: a "
        "diagnosis, never a default.",
        "",
        "## Verdict",
        "",
        *ablation_verdict(data),
        *ablation_findings(data),
        "## Scores",
        "",
        f"`{data['command']}` writes these tables from the committed run folders "
        "(`benchmarks/results/ablation/`); a cell is a mean over 10 seeds (with its bootstrap "
        "95% CI below) and the seeds at 950 (InvertedPendulum) or 800 (Swingup).",
        "",
        tables,
        "",
        "## What the policies do",
        "",
        "`benchmarks/pendulum_behaviour.py` replays trained policies (3 deterministic test "
        "episodes a run, the second half of each): the share of steps with the pole upright, "
        "the mean action magnitude, the share of steps at the action bounds (abs(a) > 0.95) "
        "and the net turns of the pole.",
        "",
        *behaviour_table(root),
    ]
    return "\n".join(lines) + "\n"


# --- Throughput and the batch trainer ---------------------------------------------------


def throughput_table(data: dict[str, Any]) -> list[str]:
    """Learner µs per member-step by task, engine and K, with its ratio to the env step."""
    ks = sorted({r["K"] for r in data["rows"]})
    cells: dict[tuple[str, str], dict[int, dict[str, Any]]] = {}
    for r in data["rows"]:
        cells.setdefault((r["task"], r["engine"]), {})[r["K"]] = r
    head = ["task", "engine", *[f"K = {k}" for k in ks], "env step"]
    rows = []
    for (task, engine), got in cells.items():
        env_us = 1e6 / data["env_steps_per_s"][task]
        values = [
            f"{got[k]['learner_us_per_member_step']:.0f} ({got[k]['learner_over_env_step']:.2f}x)"
            if k in got else "-"
            for k in ks
        ]  # fmt: skip
        rows.append([TASKS.get(task, task), engine, *values, f"{env_us:.0f}"])
    return table(head, rows, ["---", "---", *["---:"] * (len(head) - 2)])


def speedup_line(data: dict[str, Any]) -> str:
    """The fused engine against the torch engine at K = 1, per task measured with both."""
    parts = [
        f"{TASKS.get(r['task'], r['task'])} {r['speedup_vs_torch_k1']:.1f}x"
        for r in data["rows"]
        if r["engine"] == "fused" and r["K"] == 1 and r["speedup_vs_torch_k1"]
    ]
    return (
        "A single run (K = 1) by the fused engine against the torch engine, same run: "
        + ", ".join(parts)
        + "."
    )


def startup_line(data: dict[str, Any]) -> str:
    start = data["startup"]
    return (
        f"Start-up of `{start['command']}` (its wall time minus its training time: the "
        f"imports, building the task and the learner, and loading or compiling the fused "
        f"kernels): {start['cold']['startup_s']:.1f} s with an empty numba cache (the "
        f"kernels compile, once per machine and version), {start['warm']['startup_s']:.1f} s "
        f"with the cache that left."
    )


def estimate_lines(data: dict[str, Any]) -> list[str]:
    est, ref = data["paper_grid_estimate"], data["paper_grid_estimate_reference_step"]
    per_task = ", ".join(
        f"{TASKS.get(t, t)} {v['cpu_hours']:.1f}" for t, v in est["per_task"].items()
    )
    return [
        f"The best population size in this measurement is K = {data['best_k']} (the "
        f"cheapest member-step at HalfCheetah's size; `pporpe reproduce --population` sets "
        f"K). From its "
        f"rates, the estimate for the paper's full grid (`experiments/paper-full.toml`): "
        f"{est['wall_hours']:.1f} hours on 2 workers, {est['cpu_hours']:.1f} CPU hours "
        f"({per_task}); with pybullet_envs_gymnasium's step instead of pporpe's, "
        f"{ref['wall_hours']:.1f} hours ({ref['cpu_hours']:.1f} CPU hours). "
        f"Formula: {est['formula']}.",
    ]


def env_step_table(data: dict[str, Any]) -> list[str]:
    """Per task the µs of a step by pporpe's batched step, by pybullet_envs_gymnasium's
    own, and of the physics alone, with the ratios."""
    rows = [
        [TASKS.get(task, task), f"{e['batched_us']:.0f}", f"{e['reference_us']:.0f}",
         f"{e['physics_us']:.0f}", f"{e['batched_over_reference']:.2f}x",
         f"{e['batched_over_physics']:.2f}x"]
        for task, e in data["env_step"].items()
    ]  # fmt: skip
    head = ["task", "pporpe's step", "reference step", "physics alone", "pporpe / reference",
            "pporpe / physics"]  # fmt: skip
    return table(head, rows, ["---", *["---:"] * 5])


def throughput_page(root: Path) -> str:
    data = read_json(root, "benchmarks/results/throughput.json")
    lines = [
        "# Throughput of the online learner",
        "",
        banner("benchmarks/results/throughput.json"),
        "",
        "Microseconds of learner work per member-step of a population of K online runs "
        "(`pporpe.online.PopulationLearner`; every member its own config, seed and "
        "environment), by the fused engine (the default: one numba kernel per step) and "
        "the torch engine (the reference), and in brackets as a multiple of the task's "
        "environment step (*env step*, µs, measured in the same run); medians of "
        "alternating rounds. Lower is better.",
        "",
        machine_line(data["machine"], data["command"]),
        "",
        *throughput_table(data),
        "",
        speedup_line(data),
        "",
        startup_line(data),
        "",
        *estimate_lines(data),
        "",
        "## The environment step",
        "",
        "Microseconds per step of each Bullet task (random actions, resets included; "
        "medians of the same alternating rounds): pporpe's step (`pporpe.envs.bullet`, the "
        "default of `pporpe.envs.make_env`, the same numbers bit for bit, "
        "[see getting started](../getting-started.md)), pybullet_envs_gymnasium's own "
        '(`bullet_step="reference"`), and PyBullet\'s `stepSimulation` alone, the floor '
        "of any step. The *env step* above is pporpe's.",
        "",
        *env_step_table(data),
    ]
    return "\n".join(lines) + "\n"


def vs_sb3_rows(data: dict[str, Any]) -> list[Row]:
    def num(x: float | None, spec: str) -> str:
        return "-" if x is None else format(x, spec)

    rows = []
    for r in data["rows"]:
        name = "SB3 PPO" if r["trainer"] == "sb3" else f"pporpe {METHODS[r['trainer']]}"
        speed = [f"{r['steps_per_s']:.0f}", num(r.get("sps_ratio_vs_sb3"), ".2f")]
        time_to = [num(r["time_to_threshold"], ".1f"), num(r.get("time_ratio_vs_sb3"), ".2f")]
        task = TASKS.get(r["env"], r["env"])
        rows.append([task, name, *speed, f"{r['final_median']:.0f}", *time_to, r["reached"]])
    return rows


def vs_sb3_page(root: Path) -> str:
    data = read_json(root, "benchmarks/results/vs_sb3.json")
    budgets = "; ".join(
        f"{TASKS.get(t, t)} {b['steps']:,} steps" for t, b in data["budgets"].items()
    )
    head = ["task", "trainer", "steps/s", "over SB3", "final median test return",
            f"time to {data['threshold']:.0f} (s)", "over SB3", "seeds reaching it"]  # fmt: skip
    lines = [
        "# The batch trainer against Stable-Baselines3",
        "",
        banner("benchmarks/results/vs_sb3.json"),
        "",
        "`pporpe.batch` (`pporpe train --learner batch`) against Stable-Baselines3's PPO "
        f"{data['stable_baselines3']} on the same rl-baselines3-zoo settings, "
        f"{data['seeds']} seeds, {budgets}: training steps per second, the final median test "
        f"return and the training time until a test return of {data['threshold']:.0f} (a "
        "ratio below 1 is faster than SB3). Medians over seeds. `make bench-sb3` reruns it.",
        "",
        machine_line(data["machine"], data["command"]),
        "",
        *table(head, vs_sb3_rows(data), ["---", "---", *["---:"] * 6]),
    ]
    return "\n".join(lines) + "\n"


CLEANRL_PUBLISHED = {"HalfCheetah-v4": "1442.64 ± 46.03", "Hopper-v4": "2382.86 ± 271.74",
                     "Walker2d-v4": "2287.95 ± 571.78"}  # fmt: skip
"""CleanRL's published last-100 means of ``ppo_continuous_action.py`` (v4, 1M steps, 3
seeds; vwxyzjn/cleanrl ``docs/benchmark/ppo_continuous_action.md``): context, not yardstick."""


def ci_text(ci: dict[str, float]) -> str:
    return f"{ci['value']:.0f} [{ci['low']:.0f}, {ci['high']:.0f}]"


def p_text(p: dict[str, float] | None) -> str:
    return "-" if p is None else f"{p['value']:.2f} [{p['low']:.2f}, {p['high']:.2f}]"


def cleanrl_rows(data: dict[str, Any]) -> list[Row]:
    """Per task of benchmarks/results/cleanrl/summary.json: seeds, the last-100 means with
    their CIs, P(pporpe > CleanRL), SB3's mean and P(pporpe > SB3) where it ran, and the
    median steps per CPU second of the runs that recorded their CPU time."""
    impls = ("pporpe", "cleanrl", "sb3")
    rows = []
    for r in data["tasks"]:
        rows.append([
            r["task"], " / ".join(str(r["seeds"].get(i, 0)) for i in impls),
            ci_text(r["pporpe"]), ci_text(r["cleanrl"]) if "cleanrl" in r else "-",
            p_text(r.get("p_pporpe_better")),
            ci_text(r["sb3"]) if "sb3" in r else "-", p_text(r.get("p_pporpe_better_sb3")),
            " / ".join(f"{r[f'{i}_steps_per_cpu_s']:.0f}" if f"{i}_steps_per_cpu_s" in r
                       else "-" for i in impls),
            CLEANRL_PUBLISHED.get(r["task"], "-"),
        ])  # fmt: skip
    return rows


def cleanrl_throughput_lines(root: Path) -> list[str]:
    """The side-by-side throughput of each task measured (``benchmarks/cleanrl.py
    throughput``: CleanRL's script and ``pporpe train --learner batch``, A B A B)."""
    files = sorted((root / "benchmarks/results/cleanrl").glob("throughput_*.json"))
    if not files:
        return []
    rows = []
    for f in files:
        d = json.loads(f.read_text())
        rows.append([d["task"], f"{d['steps']:,}", str(len(d["rounds"]["pporpe"])),
                     f"{d['median']['pporpe']:.0f}", f"{d['median']['cleanrl']:.0f}",
                     f"{d['pporpe_over_cleanrl']:.2f}x"])  # fmt: skip
    d = json.loads(files[0].read_text())
    head = ["task", "steps per round", "rounds", "pporpe steps/s", "CleanRL steps/s",
            "pporpe / CleanRL"]  # fmt: skip
    return [
        "Throughput, one run per process and one thread each (CleanRL with OMP_NUM_THREADS=1, "
        "pporpe's run loop sets torch to 1), side by side in the same command (medians of the "
        "rounds, each implementation's own clock):", "",
        machine_line(d["machine"], d["command"].replace(d["task"], "TASK")), "",
        *table(head, rows, ["---", *["---:"] * 5]), "",
    ]  # fmt: skip


CPU_RATE_NOTE = (
    "Steps per CPU second: a run's environment steps over the CPU seconds it used (CleanRL's "
    "script: its process's, from the operating system; SB3: its `learn`; pporpe: the run's "
    "share of its process's, from `done.json`: the study trains 30 runs per process), the "
    "median over the runs that recorded it, \"-\" where none did. Unlike steps per wall "
    "second, it does not depend on what else shared the cores."
)
"""Below the CleanRL side-by-side table: what its throughput column is."""


def vs_cleanrl_page(root: Path) -> str:
    """pporpe's batch PPO beside CleanRL's script (and SB3's PPO) seed by seed, from
    benchmarks/results/cleanrl/summary.json, or a page that says it has not run yet."""
    path = "benchmarks/results/cleanrl/summary.json"
    lines = [
        "# pporpe's PPO beside CleanRL's", "", banner(path), "",
        "Is pporpe's batch PPO the field's PPO? The PPO runs of [the batch study](batch-mujoco.md) "
        "(`experiments/batch-mujoco.toml`, CleanRL's settings) beside CleanRL's "
        "`ppo_continuous_action.py` run unmodified from its own checkout and environment "
        "(gymnasium 0.29.1, mujoco 2.3.3), and Stable-Baselines3's PPO with the same settings, "
        "by `benchmarks/cleanrl.py` (its docstring has the commands). The metric is CleanRL's: "
        "the mean return of the last 100 training episodes of a 1M-step run; 95% CIs by "
        "bootstrap over seeds; P(pporpe > rival) whose CI contains 0.5 means the two cannot be "
        "told apart at these seeds. CleanRL's own published means (3 seeds) are context: "
        "HalfCheetah's outcomes are bimodal across seeds.", "",
    ]  # fmt: skip
    lines += cleanrl_throughput_lines(root)
    if not (root / path).exists():
        return "\n".join([*lines, f"Learning: not run yet (`{path}` does not exist).", ""])
    data = read_json(root, path)
    head = ["task", "seeds (pporpe / CleanRL / SB3)", "pporpe", "CleanRL",
            "P(pporpe > CleanRL)", "SB3", "P(pporpe > SB3)",
            "steps per CPU second (pporpe / CleanRL / SB3)", "CleanRL published"]  # fmt: skip
    figures = [f"![{t}](../../benchmarks/results/cleanrl/curves_{t}.png)"
               for t in sorted({r["task"] for r in data["runs"]})]  # fmt: skip
    lines += [machine_line(data["machine"], data["command"]), "",
              *table(head, cleanrl_rows(data), ["---", "---", *["---:"] * 7]), "",
              CPU_RATE_NOTE, "", *figures]  # fmt: skip
    return "\n".join(lines) + "\n"


SHADOW_SCALARS = {
    "delta": "TD error delta",
    "adv": "advantage A",
    "ratio": "ratio rho",
    "divergence": "trace divergence d",
    "trace_decay": "trace decay",
    "action": "next action",
}
"""The step's scalars of benchmarks/engine_shadow.py and their names in the table."""


def shadow_rows(window: dict[str, Any]) -> list[Row]:
    """One row per quantity of a window of benchmarks/results/engine_shadow.json."""

    def q(d: dict[str, float]) -> list[str]:
        return [f"{d[k]:.1e}" for k in ("q50", "q99", "q100")]

    rows = [[name, "-", *q(window[key])] for key, name in SHADOW_SCALARS.items()]
    for key in window:
        if key.startswith("state."):
            name = key.removeprefix("state.")
            change = f"{window['change.' + name]['q50']:.1e}"
            rows.append([f"`{name}`", change, *q(window[key])])
    return rows


def divergence_line(data: dict[str, Any]) -> str:
    """The two engines' mean trace divergence per window of episodes."""
    parts = [
        f"episodes {w['episodes'][0]}-{w['episodes'][1] - 1}: "
        f"{w['divergence_mean']['fused']:.3g} / {w['divergence_mean']['torch']:.3g}"
        for w in data["windows"][1:]
    ]
    return "Mean trace divergence per step, fused / torch: " + "; ".join(parts) + "."


def flips_lines(whole: dict[str, Any]) -> list[str]:
    """How many of the trace's large discrepancies are sign flips of ``e`` near 0."""
    if "trace_r_apart" not in whole:
        return []
    return [
        "",
        f"Elements of the trace `r` that the two engines left apart by more than 1e-3 of "
        f"its size: {whole['trace_r_apart']:,} in all compared steps; in "
        f"{whole['trace_r_apart_sign_flipped']:,} of them the trace `e` has opposite signs "
        "in the two engines (`r <- s max(s c2 r, |e|)`, `s = sign(e)`, jumps when rounding "
        "flips the sign of an `e` near 0).",
    ]


DIVERGENCE = "benchmarks/results/engine_divergence.json"
DIVERGENCE_FIGURE = "benchmarks/results/engine_divergence.png"


def divergence_cells(row: dict[str, Any]) -> Row:
    """One seed of one pair of benchmarks/results/engine_divergence.json, as table cells."""
    gap, act = row["first_step_gap_above"], row["first_step_action_above"]
    ev, jump = row["first_differing_event"], row["largest_one_step_jump_below_1e-3"]
    rate = row["growth_log10_per_1000_steps"]
    return [
        str(row["seed"]),
        *(f"{gap[lv]:,}" if gap[lv] else "-" for lv in ("1e-06", "0.0001", "0.01")),
        f"{row['final_gap']:.2f}",
        *(f"{act[lv]:,}" if act[lv] else "-" for lv in ("0.001", "0.1")),
        f"{ev['kind']} at {ev['step']:,} (gap {ev['gap_before']:.0e})" if ev else "-",
        f"{rate:.2f}" if rate is not None else "-",
        f"x{jump['factor']:.0f} at {jump['step']:,}" if jump else "-",
    ]


def divergence_median(rows: list[dict[str, Any]], key: str, level: str) -> str:
    """The median over seeds of a first-crossing step (a seed that never crossed counts as
    later than all), or ``-`` when half the seeds never crossed."""
    steps = sorted(r[key][level] or float("inf") for r in rows)
    mid = statistics.median(steps)
    return f"{mid:,.0f}" if mid != float("inf") else "-"


def divergence_section(root: Path) -> list[str]:
    """The engines page's second part: where two runs from the same seed part."""
    data = read_json(root, DIVERGENCE)
    task = TASKS.get(data["task"], data["task"])
    head = ["seed", "gap > 1e-6", "> 1e-4", "> 1e-2", "gap at the end", "action > 1e-3", "> 1e-1",
            "first discrete event that differs", "log10 gap / 1000 steps",
            "largest one-step jump (gap < 1e-3)"]  # fmt: skip
    lines = [
        "## Where two runs from one seed part",
        "",
        f"`{DIVERGENCE}`: the fused engine and its twins learn {task} with the "
        f"`{data['config']}` settings, each twin a population of its "
        f"own with its own environments, from the same seeds ({data['episodes']} episodes "
        "of every member, nothing copied between them). The twins: "
        + "; ".join(f"**{name}**, {what}" for name, what in data["twins"].items())
        + ". The seeds are those whose 200-episode scores lie furthest apart between the "
        "engines. Per step: the gap, max|theta_twin - theta_fused| / max|theta_fused| over "
        "both networks, and the actions' difference in units of the action range; the "
        "tables give the first step at which each passes a level, the first step at which "
        "a discrete event (the clip passed, an episode's end) differs, with the gap just "
        "before it, the gap's growth while between 1e-5 and 1e-2, and its largest one-step "
        "jump while below 1e-3.",
        "",
        machine_line(data["machine"], data["command"]),
        "",
    ]
    for name, rows in data["pairs"].items():
        lines += [f"The fused engine against {data['twins'][name]} (`{name}`):", "",
                  *table(head, [divergence_cells(r) for r in rows]), ""]  # fmt: skip
    gap, act = "first_step_gap_above", "first_step_action_above"
    medians = [
        f"`{name}`: gap above 1e-4 at step {divergence_median(rows, gap, '0.0001')}, above "
        f"1e-2 at {divergence_median(rows, gap, '0.01')}, actions apart by 1e-1 at "
        f"{divergence_median(rows, act, '0.1')}"
        for name, rows in data["pairs"].items()
    ]
    lines += ["Medians over the seeds: " + "; ".join(medians) + ".", ""]
    if (root / DIVERGENCE_FIGURE).exists():
        lines += [f"![The gap along the runs, per seed and twin](../../{DIVERGENCE_FIGURE})", ""]
    return lines


def engines_page(root: Path) -> str:
    data = read_json(root, "benchmarks/results/engine_shadow.json")
    st, whole = data["settings"], data["windows"][0]
    head = ["quantity", "size of the step's change (median)", "discrepancy: median",
            "99%", "max"]  # fmt: skip
    lines = [
        "# The two engines along learning runs",
        "",
        banner("benchmarks/results/engine_shadow.json"),
        "",
        f"A population of the fused engine learns {TASKS.get(st['task'], st['task'])} with "
        f"the `{st['config']}` settings of `benchmarks/testbed.py` ({len(st['seeds'])} "
        f"members, {st['episodes']} episodes each); every N-th step (N = {st['every']}) its "
        "whole state is copied into a population of the torch engine (compiled update: "
        f"{'yes' if st['compile'] else 'no'}) and both take the same transition "
        f"({whole['compared']} member-steps compared). The step's scalars: relative "
        "difference |torch - fused| / max(|torch|, |fused|). Every state buffer, per "
        "member: the step's change max|after - before| and the engines' discrepancy "
        "max|change_torch - change_fused|, both in units of the buffer's size "
        "max|after| (of either engine). Float32 rounding reads about 1e-7 of the size; "
        "a rule that differs reads as large as the change.",
        "",
        machine_line(data["machine"], data["command"]),
        "",
        *table(head, shadow_rows(whole), ["---", *["---:"] * 4]),
        "",
        divergence_line(data),
        *flips_lines(whole),
        "",
        *divergence_section(root),
    ]
    return "\n".join(lines).rstrip("\n") + "\n"


# --- The columns of episodes.csv (docs/run-folders.md) -----------------------------------

COLUMNS_START = (
    "<!-- columns: written by python docs/generate.py from pporpe.runs.logger.COLUMNS and "
    "the fields' docstrings; edit those, not here -->"
)
COLUMNS_END = "<!-- end of columns -->"


def field_docs(path: Path, classes: tuple[str, ...]) -> dict[str, str]:
    """The docstring under each annotated field of ``classes`` in the module at ``path``
    (read with ``ast``: nothing is imported)."""
    docs: dict[str, str] = {}
    for node in ast.parse(path.read_text(encoding="utf-8")).body:
        if not isinstance(node, ast.ClassDef) or node.name not in classes:
            continue
        for field, doc in zip(node.body, node.body[1:], strict=False):
            if isinstance(field, ast.AnnAssign) and isinstance(field.target, ast.Name):
                if isinstance(doc, ast.Expr) and isinstance(doc.value, ast.Constant):
                    docs[field.target.id] = " ".join(str(doc.value.value).split())
    return docs


def column_names(path: Path) -> list[str]:
    """``COLUMNS`` of the module at ``path`` (``pporpe.runs.logger``), read with ``ast``."""
    for node in ast.parse(path.read_text(encoding="utf-8")).body:
        if isinstance(node, ast.AnnAssign) and getattr(node.target, "id", "") == "COLUMNS":
            return list(ast.literal_eval(node.value))  # type: ignore[arg-type]
    raise ValueError(f"{path} defines no COLUMNS")


def with_run_folder_columns(root: Path) -> str:
    """docs/run-folders.md with the table of episodes.csv's columns rewritten."""
    runs = root / "src" / "pporpe" / "runs"
    docs = {**field_docs(runs / "kinds.py", ("SurrogateDiagnostics",)),
            **field_docs(runs / "logger.py", ("EpisodeRecord",))}  # fmt: skip
    names = column_names(runs / "logger.py")
    rows = [[f"`{name}`", docs[name].replace("|", "\\|")] for name in names]
    text = (root / "docs" / "run-folders.md").read_text(encoding="utf-8")
    block = table(["column", "what it holds"], rows)
    return rewrite_blocks(text, COLUMNS_START, COLUMNS_END, [block], "docs/run-folders.md")


# --- The batch population's measurements (docs/batch.md) --------------------------------

POPULATION_START = (
    "<!-- population: written by python docs/generate.py from "
    "benchmarks/results/batch_population.json; edit the script, not here -->"
)
POPULATION_END = "<!-- end of population -->"
OPTION_NAMES = {
    "separate": "K runs one after another",
    "vmap": "`torch.func` vmap(grad)",
    "stacked": "stacked (the population)",
    "stacked-bmm": "stacked, every layer `baddbmm`",
}


def population_option_table(data: dict[str, Any]) -> list[str]:
    """µs per member of one minibatch step, by option (columns) and K (rows)."""
    cost = {(o["option"], o["K"]): o["us_per_member_step"] for o in data["options"]}
    options = [o for o in OPTION_NAMES if any(key[0] == o for key in cost)]
    rows = [[str(k), *(f"{cost[(o, k)]:.0f}" if (o, k) in cost else "-" for o in options)]
            for k in sorted({k for _, k in cost})]  # fmt: skip
    same = data["equal_to_runs_alone"]
    rows.append(["the bits of a run alone", *("yes" if same.get(o) else "no" for o in options)])
    return table(["K", *(OPTION_NAMES[o] for o in options)], rows)


def population_run_table(data: dict[str, Any]) -> list[str]:
    """Whole runs: member-steps/s, the ratio to a run alone (its range over rounds) and
    the rollout and update costs."""
    names = {"alone": "a run alone", "envs": "the environments alone"}
    rows = []
    for r in data["runs"]:
        name = names.get(r["variant"], r["variant"].replace("=", " = "))
        if r["variant"] == "envs":
            name += f" (K = {r['members']})"
        spread = r["rounds_ratio_to_alone"]
        ratio = f"{r['ratio_to_alone']:.2f}".rstrip("0").rstrip(".")
        if spread:
            ratio += f" ({min(spread):.2f}-{max(spread):.2f})"
        cost = f"{r['rollout_us_per_member_step']:.0f}"
        if r["update_us_per_member_step"]:
            cost += f" + {r['update_us_per_member_step']:.0f}"
        rows.append([name, f"{r['member_steps_per_s']:.0f}", ratio, cost])
    head = ["", "member-steps/s", "against a run alone (rounds)",
            "rollout + update, µs per member-step"]  # fmt: skip
    return [*table(head, rows), "", *population_cost_lines(data)]


def population_cost_lines(data: dict[str, Any]) -> list[str]:
    """Where the K of the environments' row spends a member-step, and what the 3x target
    (K = 10 against a run alone) would take."""
    runs = {r["variant"]: r for r in data["runs"]}
    envs = runs["envs"]
    pop, alone = runs[f"K={envs['members']}"], runs["alone"]
    total = pop["us_per_member_step"]
    env, rollout = envs["us_per_member_step"], pop["rollout_us_per_member_step"]
    lines = [
        f"Of K = {envs['members']}'s {total:.0f} µs per member-step, {env:.0f} are the "
        f"environments' own step (the last row), {rollout - env:.0f} the rest of the rollout "
        "(some 130 small operations per step, 2K of them member by member: the noise draws "
        "from each member's own generator and the two small output layers, which no batched "
        f"form computes with a run alone's bits) and {pop['update_us_per_member_step']:.0f} "
        "the update."
    ]
    if envs["members"] == 10 and pop["ratio_to_alone"] < 3:
        need = total - alone["us_per_member_step"] / 3
        lines[0] += (
            f" K = 10 at 3x a run alone would need {need:.0f} µs less per member-step "
            "from the population's own work."
        )
    return lines


def with_population_tables(root: Path) -> str:
    """docs/batch.md with the two tables of the batch population's benchmark rewritten
    (the first pair of markers: where it ran and the options; the second: whole runs), and
    the table of the MuJoCo step's benchmark."""
    data = read_json(root, "benchmarks/results/batch_population.json")
    text = (root / "docs" / "batch.md").read_text(encoding="utf-8")
    options = [*measured_lines(data), "", *population_option_table(data)]
    blocks = [options, population_run_table(data)]
    text = rewrite_blocks(text, POPULATION_START, POPULATION_END, blocks, "docs/batch.md")
    step = read_json(root, "benchmarks/results/mujoco_step.json")
    step_block = [*measured_lines(step), "", *mujoco_step_table(step)]
    return rewrite_blocks(text, MUJOCO_STEP_START, MUJOCO_STEP_END, [step_block],
                          "docs/batch.md")  # fmt: skip


def measured_lines(data: dict[str, Any]) -> list[str]:
    """Where and how a benchmark ran (its command without the ``--note``), and its note on
    what shared the cores when it has one."""
    lines = [machine_line(data["machine"], data["command"].split(" --note")[0])]
    if data.get("note"):
        lines.append(f"What shared the cores: {data['note']}.")
    return lines


MUJOCO_STEP_START = (
    "<!-- mujoco step: written by python docs/generate.py from "
    "benchmarks/results/mujoco_step.json; edit the script, not here -->"
)
MUJOCO_STEP_END = "<!-- end of mujoco step -->"


def mujoco_step_table(data: dict[str, Any]) -> list[str]:
    """Per -v4 task: µs per step by pporpe's step, Gymnasium's and the MuJoCo calls alone,
    the Python around the physics in each, and whether the identity held."""
    rows = [
        [task, f"{r['lean_us']:.0f}", f"{r['reference_us']:.0f}", f"{r['physics_us']:.0f}",
         f"{r['lean_over_reference']:.2f}",
         f"{r['python_us_lean']:.0f} / {r['python_us_reference']:.0f}",
         f"{'yes' if r['identical'] else 'NO'} ({r['steps']:,} steps, {r['resets']:,} resets)"]
        for task, r in data["tasks"].items()
    ]  # fmt: skip
    head = ["task", "pporpe's step", "Gymnasium's step", "MuJoCo calls alone",
            "pporpe / Gymnasium", "Python around them, pporpe / Gymnasium",
            "the same bit for bit"]  # fmt: skip
    return table(head, rows, ["---", *["---:"] * 5, "---"])


PAGES: dict[str, Callable[[Path], str]] = {
    "docs/results/reproduction.md": reproduction_page,
    "docs/results/reproduction-testbed.md": reproduction_testbed_page,
    "docs/results/reproduction-50seeds.md": reproduction_50seeds_page,
    "docs/results/reproduction-full.md": reproduction_full_page,
    "docs/results/batch-mujoco.md": batch_mujoco_page,
    "docs/results/ablation.md": ablation_page,
    "docs/results/throughput.md": throughput_page,
    "docs/results/vs-sb3.md": vs_sb3_page,
    "docs/results/vs-cleanrl.md": vs_cleanrl_page,
    "docs/results/engines.md": engines_page,
    "README.md": with_readme_results,
    "docs/run-folders.md": with_run_folder_columns,
    "docs/batch.md": with_population_tables,
}
"""Each generated file (relative to the repository root) and the function that writes it."""


def expected(root: Path = ROOT) -> dict[str, str]:
    """Every generated file's text as the committed results give it today."""
    return {path: page(root) for path, page in PAGES.items()}


def stale(root: Path = ROOT) -> list[str]:
    """The generated files whose text on disk is not what :func:`expected` writes, and the
    headline figure if it was drawn from other results (:func:`headline_figure_stale`)."""
    out = []
    for path, text in expected(root).items():
        target = root / path
        if not target.exists() or target.read_text(encoding="utf-8") != text:
            out.append(path)
    if headline_figure_stale(root):
        out.append(HEADLINE_FIGURE)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="only report stale pages")
    parser.add_argument("--root", type=Path, default=ROOT, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.check:
        bad = stale(args.root)
        for path in bad:
            command = HEADLINE_COMMAND if path == HEADLINE_FIGURE else "python docs/generate.py"
            print(f"{path} is not what the committed results give: run {command}")
        return 1 if bad else 0
    for path, text in expected(args.root).items():
        target = args.root / path
        if not target.exists() or target.read_text(encoding="utf-8") != text:
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_text(text, encoding="utf-8")
            print(f"wrote {path}")
    if headline_figure_stale(args.root):
        print(f"{HEADLINE_FIGURE} is not what the committed results give: run {HEADLINE_COMMAND}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
