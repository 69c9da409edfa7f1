"""The torch engine (``engine="torch"``): the readable reference of the population's step,
batched torch operations shared by the members.

:mod:`.update` is its elementwise update (traces, td-AmsProp, t-soft) over all members;
:mod:`.traces`, :mod:`.optim` and :mod:`.tsoft` are the same components for one
parameter vector (:class:`.AdaptiveTraces`, :class:`.TDAmsProp`, :class:`.TSoftUpdate`),
usable on their own, from which the tests' single-run reference learner is built.
"""
