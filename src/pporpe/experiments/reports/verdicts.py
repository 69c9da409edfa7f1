"""The verdict on a claim, for both reports: what the CI of a probability of improvement says.

The online report's claims table (:mod:`.online.claims`) gives one per claim (final score,
early learning, regularisation), task and rival; the batch report one per metric, task and
rival. The verdict reads the 95% CI [low, high] of P(PPO-RPE > rival) (:func:`verdict`), in
this order:

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

Beside a ``cannot tell`` verdict, :func:`seeds_to_settle` projects roughly how many seeds per
method would give one, were the estimate of P to stay where it is.
"""

from __future__ import annotations

import math

__all__ = [
    "EDGE_TOLERANCE",
    "EQUIVALENCE_BOUNDS",
    "MIN_SEEDS",
    "SETTLE_CAP",
    "SETTLE_LEGEND",
    "seeds_to_settle",
    "settle_text",
    "short_verdict",
    "verdict",
]

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


SETTLE_CAP = 1000
"""The most seeds per method :func:`settle_text` names; a projection above it reads "over
1000"."""


def _arms_needed(n: int, arm: float, room: float) -> int:
    """The fewest seeds at which a CI arm of length ``arm`` at ``n`` seeds, shrinking as
    1/sqrt(seeds), is shorter than ``room`` by more than :data:`EDGE_TOLERANCE` (as
    :func:`verdict` reads a CI): ``n * (arm / (room - EDGE_TOLERANCE))**2``, rounded up past
    it."""
    room -= EDGE_TOLERANCE
    return n + 1 if arm <= 0 else max(n + 1, math.floor(n * (arm / room) ** 2) + 1)


def seeds_to_settle(value: float, low: float, high: float, n: int) -> tuple[int, str] | None:
    """A rough projection for a ``cannot tell`` CI ``[low, high]`` of P(PPO-RPE > rival) =
    ``value`` at ``n`` seeds per method: the fewest seeds per method at which it would give a
    verdict, and which (``supported``, ``contradicted`` or ``equivalent``), if ``value``
    stayed and each arm of the CI (``value - low``, ``high - value``) shrank as 1/sqrt(seeds),
    as a bootstrap CI's arms do once there are many.

    To clear 0.5 the arm towards it must become shorter than ``abs(value - 0.5)``: ``n * (arm
    / abs(value - 0.5))**2`` seeds; to be equivalent both arms must fit inside
    :data:`EQUIVALENCE_BOUNDS`. The smaller wins; at a tie, supported or contradicted, as
    :func:`verdict` reads a CI above 0.5 and inside the bounds. None where :func:`verdict`
    already gives a verdict (or no data, or too few seeds).

    It is where the CI's expected end just reaches the bound: even if P were exactly
    ``value``, a grid of that many seeds would give the verdict about half the time (about
    twice as many give it with 80% odds, ((1.96 + 0.84) / 1.96)**2 = 2.04), and an
    estimate far from 0.5 tends to overstate the distance, so it is a planning figure, not
    a prediction."""
    if not all(map(math.isfinite, (value, low, high))):
        return None
    if not short_verdict(verdict(low, high, (n, n))).startswith("cannot tell"):
        return None
    lo_bound, hi_bound = EQUIVALENCE_BOUNDS
    options = []
    if value > 0.5:
        options.append((_arms_needed(n, value - low, value - 0.5), "supported"))
    elif value < 0.5:
        options.append((_arms_needed(n, high - value, 0.5 - value), "contradicted"))
    if lo_bound < value < hi_bound:
        both = max(_arms_needed(n, value - low, value - lo_bound),
                   _arms_needed(n, high - value, hi_bound - value))  # fmt: skip
        options.append((both, "equivalent"))
    seeds, said = min(options, key=lambda o: (o[0], o[1] == "equivalent"))
    return seeds, said


def settle_text(value: float, low: float, high: float, n: int) -> str:
    """:func:`seeds_to_settle` for a table: ``about 61 (supported)``, ``over 1000
    (equivalent)``, or ``-`` where there is nothing to project."""
    got = seeds_to_settle(value, low, high, n)
    if got is None:
        return "-"
    seeds, said = got
    return f"over {SETTLE_CAP} ({said})" if seeds > SETTLE_CAP else f"about {seeds} ({said})"


SETTLE_LEGEND = (
    "**Seeds to settle it**: for a claim that cannot be told, a rough projection of the seeds "
    "per method (per task, for a pooled row) at which the CI would give a verdict, and which "
    "one, if P stayed at its estimate and each arm of its CI shrank as 1/sqrt(seeds), as a "
    "bootstrap CI's do for many seeds. Even then that many seeds give the verdict only about "
    "half the time (twice as many: about 80%), and P moves as seeds are added: a planning "
    "figure, not a prediction."
)
"""The sentence under a table with a seeds-to-settle column."""


def short_verdict(said: str) -> str:
    """A :func:`verdict` without what follows its word in brackets (the reason, and the
    seeds left out after it): ``cannot tell at 10 seeds``."""
    return said.split(" (")[0]
