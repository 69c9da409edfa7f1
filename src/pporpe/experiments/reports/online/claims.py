"""The online report's claims table: each claim of the paper against a grid's data, with a
probability of improvement, the difference of the means and a verdict (:mod:`..verdicts`)."""

from __future__ import annotations

from collections.abc import Mapping

from ..figures import METHOD_LABELS
from ..results import Cell
from ..tables import fmt_ci
from ..verdicts import EQUIVALENCE_BOUNDS, MIN_SEEDS, SETTLE_LEGEND, settle_text, verdict
from .summary import Statistics, improvement_rows

__all__ = ["CLAIMS", "DIFF_DIGITS", "claims_markdown"]

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

DIFF_DIGITS = {"score": 1, "first50": 1, "reg": 4}
"""Decimals of each statistic's mean difference in the claims table."""


def claims_markdown(
    cells: list[Cell], stats: Statistics | None = None, pending: Mapping[str, str] | None = None
) -> str:
    """One line per claim, task and rival: the probability of improvement, the difference of
    the means, the verdict and, where it cannot tell, the seeds that would settle it
    (:func:`settle_text`). A task of ``pending`` (task -> ``36 of 75 runs``, from
    :func:`..preregistration.pending_tasks`) has a pre-registered verdict not yet read: its
    verdicts say so before the interim one, and no seeds are projected (they are fixed)."""
    pending = pending or {}
    rows = improvement_rows(cells) if stats is None else stats.improvements
    lines = ["| claim | task | rival | P(PPO-RPE > rival) [95% CI] "
             "| mean difference, PPO-RPE - rival [95% CI] | verdict | seeds to settle it |",
             "| --- | --- | --- | :---: | :---: | --- | --- |"]  # fmt: skip
    for stat, claim, tasks in CLAIMS:
        for r in rows:
            if tasks is not None and r["task"] not in tasks:
                continue
            said = verdict(r[f"{stat}_low"], r[f"{stat}_high"], r[f"{stat}_n"],
                           r[f"{stat}_left_out"])  # fmt: skip
            settle = settle_text(r[f"{stat}_value"], r[f"{stat}_low"], r[f"{stat}_high"],
                                 min(r[f"{stat}_n"]))  # fmt: skip
            if r["task"] in pending:
                said = f"pending (pre-registered; {pending[r['task']]} in); interim: {said}"
                settle = "- (pre-registered)"
            lines.append(
                f"| {claim.split(':')[0]} | {r['task']} | "
                f"{METHOD_LABELS.get(r['rival'], r['rival'])} | {fmt_ci(r, stat, 2)} | "
                f"{fmt_ci(r, f'{stat}_diff', DIFF_DIGITS[stat])} | {said} | {settle} |"
            )
    return "\n".join(lines) + "\n\n" + _legend() + "\n"


def _legend() -> str:
    """The claims, then how to read the verdicts."""
    claims = "\n".join(
        f"- **{c.split(':')[0]}**:{c.split(':', 1)[1]} the rival"
        + ("" if tasks is None else f" (claimed for {', '.join(tasks)})")
        for _, c, tasks in CLAIMS
    )
    lo_bound, hi_bound = EQUIVALENCE_BOUNDS
    return (
        claims + "\n\n"
        "Verdicts, from the 95% CI of P(PPO-RPE > rival): **supported** when it lies above "
        "0.5, **contradicted** when below, **equivalent** when it lies strictly inside "
        f"{lo_bound}-{hi_bound} (Vargha and Delaney's bounds of a medium effect: no difference "
        "of medium size or more), otherwise **cannot tell**. A CI that touches 0.5 or a bound "
        "is not past it. No verdict where a method has fewer than "
        f"{MIN_SEEDS} seeds. The two methods are compared on the seeds both finished (a grid "
        "still running, a failed run: the verdict says how many were left out). Mean "
        "difference: of the claim's statistic (score, first-50 return, regularisation "
        "amount), with a bootstrap CI resampling both methods' seeds. "
        + SETTLE_LEGEND + "\n"
    )
