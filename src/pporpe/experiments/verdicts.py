"""The paper's claims against a grid's data: a probability of improvement and a verdict.

One per claim (final score, early learning, regularisation), task and rival.
"""

from __future__ import annotations

import math

from .figures import METHOD_LABELS
from .results import Cell
from .summary import Statistics, improvement_rows
from .tables import fmt_ci

__all__ = ["CLAIMS", "claims_markdown", "verdict"]

CLAIMS = (
    ("score", "final performance: PPO-RPE scores as well as or better than", None),
    (
        "first50",
        "early learning: PPO-RPE learns faster from the early stage than",
        ("pendulum", "swingup"),
    ),
    ("reg", "regularisation: PPO-RPE regularises more strongly than", None),
)
"""The paper's claims checked by the report: the statistic, the claim, the tasks it is
made for (None: all)."""


def verdict(low: float, high: float, n: tuple[int, int]) -> str:
    """What a probability-of-improvement CI says: ahead, behind, or cannot tell."""
    if math.isnan(low):
        return "no data"
    if low > 0.5:
        return "supported (PPO-RPE ahead)"
    if high < 0.5:
        return "contradicted (PPO-RPE behind)"
    return f"cannot tell at {min(n)} seeds (the CI contains 0.5)"


def claims_markdown(cells: list[Cell], stats: Statistics | None = None) -> str:
    """One line per claim, task and rival: the probability of improvement and the verdict."""
    rows = improvement_rows(cells) if stats is None else stats.improvements
    lines = ["| claim | task | rival | P(PPO-RPE > rival) [95% CI] | verdict |",
             "| --- | --- | --- | :---: | --- |"]  # fmt: skip
    for stat, claim, tasks in CLAIMS:
        for r in rows:
            if tasks is not None and r["task"] not in tasks:
                continue
            lines.append(
                f"| {claim.split(':')[0]} | {r['task']} | "
                f"{METHOD_LABELS.get(r['rival'], r['rival'])} | {fmt_ci(r, stat, 2)} | "
                f"{verdict(r[f'{stat}_low'], r[f'{stat}_high'], r[f'{stat}_n'])} |"
            )
    legend = "\n".join(
        f"- **{c.split(':')[0]}**:{c.split(':', 1)[1]} the rival"
        + ("" if tasks is None else f" (claimed for {', '.join(tasks)})")
        for _, c, tasks in CLAIMS
    )
    return "\n".join(lines) + "\n\n" + legend + "\n"
