"""The paper's claims against a grid's data: a probability of improvement, the difference
of the means, and a verdict.

One per claim (final score, early learning, regularisation), task and rival. The verdict
reads the 95% CI [low, high] of P(PPO-RPE > rival) (:func:`verdict`), in this order:

1. ``no data``: a method has no finite value;
2. ``too few seeds (n = N)``: a method has fewer than :data:`MIN_SEEDS` seeds;
3. (the two methods are compared on the seeds both finished, :func:`.stats.common_seeds`: in a
   grid still running, or one with a failed run, the verdict says how many)
4. ``supported``: the CI lies above 0.5 (low > 0.5); ``contradicted``: below (high < 0.5);
5. ``equivalent``: the CI lies strictly inside :data:`EQUIVALENCE_BOUNDS` (0.36, 0.64);
6. otherwise ``cannot tell at N seeds``.

The edges: a CI that touches a bound (an end equal to 0.5, 0.36 or 0.64, within
:data:`EDGE_TOLERANCE`) is not past it. Vargha and Delaney (2000) call P = 0.64 (or 0.36) a
medium effect, so a CI that reaches 0.64 does not rule out a medium effect, and is not
``equivalent``. A CI above 0.5 and inside the bounds is ``supported``, by less than a
medium effect.
"""

from __future__ import annotations

import math

from .figures import METHOD_LABELS
from .results import Cell
from .summary import Statistics, improvement_rows
from .tables import fmt_ci

__all__ = [
    "CLAIMS",
    "EDGE_TOLERANCE",
    "EQUIVALENCE_BOUNDS",
    "MIN_SEEDS",
    "claims_markdown",
    "short_verdict",
    "verdict",
]

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

MIN_SEEDS = 5
"""The fewest seeds a method needs for a verdict. With fewer, a bootstrap over seeds has
too few distinct resamples to be trusted (one seed each gives the CI [P, P])."""

EQUIVALENCE_BOUNDS = (0.36, 0.64)
"""P(PPO-RPE > rival) of a medium effect (Vargha and Delaney 2000: A = 0.64, the analogue of
Cohen's d = 0.5) either way: a CI strictly inside them rules out a difference of medium size
or more."""

EDGE_TOLERANCE = 1e-9
"""How close a CI's end must come to 0.5 or a bound to touch it (the ends are often exact
multiples of 1 / (n_x * n_y), e.g. 0.36 with 10 seeds each, up to float rounding)."""


def _past(x: float, bound: float) -> bool:
    """Whether ``x`` lies above ``bound`` by more than :data:`EDGE_TOLERANCE`."""
    return x - bound > EDGE_TOLERANCE


def verdict(low: float, high: float, n: tuple[int, int], left_out: int = 0) -> str:
    """What a probability-of-improvement CI ``[low, high]`` says (module docstring): ``n``
    holds the two methods' numbers of seeds compared, ``left_out`` the seeds of either left
    out because the other method has not (yet) finished them (:func:`.stats.common_seeds`)."""
    if min(n) == 0 or math.isnan(low) or math.isnan(high):
        return "no data"
    if min(n) < MIN_SEEDS:
        return f"too few seeds (n = {min(n)}; a verdict needs {MIN_SEEDS})"
    lo_bound, hi_bound = EQUIVALENCE_BOUNDS
    inside = _past(low, lo_bound) and _past(hi_bound, high)
    small = ", by less than a medium effect" if inside else ""
    bounds = f"{lo_bound} or {hi_bound}"
    if _past(low, 0.5):
        said = f"supported (PPO-RPE ahead{small})"
    elif _past(0.5, high):
        said = f"contradicted (PPO-RPE behind{small})"
    elif inside:
        said = f"equivalent (the CI stays clear of {bounds}: no medium difference)"
    else:
        said = f"cannot tell at {min(n)} seeds (the CI contains 0.5 and reaches {bounds})"
    if left_out:
        runs = "run" if left_out == 1 else "runs"
        said += f", on the {min(n)} seeds both finished ({left_out} other {runs} left out)"
    return said


def short_verdict(said: str) -> str:
    """A :func:`verdict` without what follows its word in brackets (the reason, and the
    seeds left out after it): ``cannot tell at 10 seeds``."""
    return said.split(" (")[0]


def claims_markdown(cells: list[Cell], stats: Statistics | None = None) -> str:
    """One line per claim, task and rival: the probability of improvement, the difference of
    the means and the verdict."""
    rows = improvement_rows(cells) if stats is None else stats.improvements
    lines = ["| claim | task | rival | P(PPO-RPE > rival) [95% CI] "
             "| mean difference, PPO-RPE - rival [95% CI] | verdict |",
             "| --- | --- | --- | :---: | :---: | --- |"]  # fmt: skip
    for stat, claim, tasks in CLAIMS:
        for r in rows:
            if tasks is not None and r["task"] not in tasks:
                continue
            said = verdict(r[f"{stat}_low"], r[f"{stat}_high"], r[f"{stat}_n"],
                           r[f"{stat}_left_out"])  # fmt: skip
            lines.append(
                f"| {claim.split(':')[0]} | {r['task']} | "
                f"{METHOD_LABELS.get(r['rival'], r['rival'])} | {fmt_ci(r, stat, 2)} | "
                f"{fmt_ci(r, f'{stat}_diff', DIFF_DIGITS[stat])} | {said} |"
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
        "amount), with a bootstrap CI resampling both methods' seeds.\n"
    )
