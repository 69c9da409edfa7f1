"""How to train K batch PPO runs in one process, measured side by side (torch on one
thread, variants in alternating rounds so that the machine's noise hits them alike).

**Part 1: the options for one minibatch step** (loss, backward, per-member gradient
clipping, Adam) on synthetic Hopper-v4-sized minibatches (11 observations, 3 actions,
64 x 64 tanh policy and value networks, 64 rows, PPO clip with value clipping), in µs per
member-step, for K = 1, 4, 10, 30:

* ``separate``: K :class:`~pporpe.batch.model.ActorCritic` stepped one after another with
  the solo learner's code (``minibatch_loss``, backward into its flat gradient, clipping,
  ``torch.optim.Adam(fused=True)``): what K runs in one process cost without batching;
* ``vmap``: ``torch.func.vmap(torch.func.grad(loss))`` over the stacked flat parameters
  ``[K, n]`` (the networks by :class:`~pporpe.nn.mlp.FlatMLP`), then the population's
  clipping and :class:`~pporpe.batch.stacked.StackedAdam`;
* ``stacked``: what :class:`~pporpe.batch.population.BatchPopulation` does: the stacked
  networks of :class:`~pporpe.batch.stacked.StackedActorCritic` (one batched call per
  layer, each in the form that gives a run alone's bits: :mod:`pporpe.nn.stacked`),
  autograd into the ``[K, n]`` gradient, clipping, ``StackedAdam``;
* ``stacked-bmm``: the same with every layer as a plain ``baddbmm`` (the batched layers
  of the online population, :mod:`pporpe.nn.batched`, are that form): the price of bit
  equality with a run alone.

**Part 2: whole runs** on Hopper-v4 with CleanRL's settings (1 environment, n_steps 2048,
batch 64, 10 epochs, 64 x 64 tanh, lr 3e-4 annealed linearly, value clipping 0.2,
observation and reward normalisation): member-steps/s of one run alone
(:class:`~pporpe.batch.learner.BatchLearner`: rollout, then update) and of populations of
K = 1, 4, 10, 30 (:meth:`BatchPopulation.update`, members of all three methods), with the
split between rollout and update; and ``envs``, the members' environments alone stepped as
the population steps them (K = 10, zero actions): the floor of a member-step, and so the
ceiling of the ratio. Every update of a variant runs between two updates of the run alone,
and its ratio is taken against their mean (the load of the moment; the cores are shared).

    python benchmarks/batch_population.py [--ks 1 4 10 30] [--rounds 3] [--steps 200]
        [--parts options runs] [--note "what shared the cores"] [--out FILE]

Conclusion (benchmarks/results/batch_population.json, docs/batch.md; 2 cores, every other
job paused, Xeon with AVX-512): per minibatch step ``stacked`` costs 218 µs per member at
K = 10 against 953 for ``separate`` (4.4x; 139 against 968 at K = 30, 7.0x); ``vmap``
costs 388 and gives other bits than a run alone (its batching rules pick other kernels,
and it has no per-layer fallback); ``stacked-bmm`` is 12% cheaper than ``stacked`` and not
bit for bit. The population uses ``stacked``: bit for bit a run alone for about a tenth
more. Whole Hopper runs (the environment stepped by :mod:`pporpe.envs.mujoco`): K = 10
trains 2.77x the member-steps/s of a run alone (2.73-2.78 over the rounds), K = 30 3.55x.
Of K = 10's 174 µs per member-step, 82 are the environments' own step (the ``envs``
floor), 50 the rest of the rollout (some 130 small operations per step, 2K of them member
by member: the noise draws and the two small output layers) and 42 the update.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import write_json

import pporpe.nn.stacked as stacked_nn
from pporpe.batch import ActorCritic, BatchConfig, BatchLearner, Minibatch
from pporpe.batch.loss import NetOutputs, loss_terms, minibatch_loss
from pporpe.batch.population import BatchPopulation
from pporpe.batch.stacked import StackedActorCritic, StackedAdam
from pporpe.batch.vecenv import step_same_step
from pporpe.nn.mlp import flat_views
from pporpe.nn.stacked import backward_quietly

HERE = Path(__file__).resolve().parent
OBS, ACT, ROWS = 11, 3, 64
HOPPER = BatchConfig(
    env="Hopper-v4", n_envs=1, n_steps=2048, batch_size=64, n_epochs=10, lr=3e-4,
    lr_schedule="linear", clip_vf=0.2, total_steps=2048 * 1000, eval_episodes=0,
)  # fmt: skip
"""CleanRL's ppo_continuous_action.py settings for Hopper-v4 (its gamma, lambda, clip, max
grad norm, Adam epsilon and normalisation are BatchConfig's defaults)."""


@dataclass(frozen=True)
class Stepper:
    """One option's minibatch step of K members, and their parameters ``[K, n]``."""

    step: Callable[[], None]
    theta: Callable[[], Tensor]


# -- part 1: one minibatch step --------------------------------------------------------------
def _models(K: int) -> list[ActorCritic]:
    out = []
    for k in range(K):
        torch.manual_seed(k)
        out.append(ActorCritic(OBS, [-1.0] * ACT, [1.0] * ACT, HOPPER))
    return out


def _minibatch(K: int) -> Minibatch:
    gen = torch.Generator().manual_seed(0)
    packed = torch.randn(K, ROWS, OBS + ACT + 4, generator=gen)
    packed[..., OBS + ACT] = -3.0  # log pi_old near the policy's
    return Minibatch._from_packed(packed, OBS)


def separate_step(K: int) -> Stepper:
    """K runs' minibatch steps one after another, the solo learner's code."""
    models, mb = _models(K), _minibatch(K)
    opts = [torch.optim.Adam([m.theta], lr=3e-4, eps=1e-5, foreach=False, fused=True)
            for m in models]  # fmt: skip
    rows = [mb.members(torch.tensor([k])) for k in range(K)]
    mbs = [Minibatch._from_packed(r.packed[0], OBS) for r in rows]

    def step() -> None:
        for model, opt, m in zip(models, opts, mbs, strict=True):
            loss, _ = minibatch_loss(model, m, HOPPER)
            model.grad.zero_()
            loss.backward()
            with torch.no_grad():
                norm = torch.linalg.vector_norm(model.grad)
                model.grad.mul_(torch.clamp(0.5 / (norm + 1e-6), max=1.0))
                opt.step()

    return Stepper(step, lambda: torch.stack([m.theta.detach() for m in models]))


def _stacked(K: int) -> tuple[StackedActorCritic, StackedAdam]:
    models = _models(K)
    net = StackedActorCritic(models[0], K)
    for k, m in enumerate(models):
        net.load_member(k, m.theta)
    return net, StackedAdam(net.theta, net.grad)


def _clip_and_adam(net: StackedActorCritic, adam: StackedAdam, K: int) -> None:
    with torch.no_grad():
        norm = torch.linalg.vector_norm(net.grad, dim=1)
        net.grad.mul_(torch.clamp(torch.reciprocal(norm + 1e-6) * 0.5, max=1.0).unsqueeze(1))
        adam.step(range(K), [3e-4] * K, [1e-5] * K)


def stacked_step(K: int) -> Stepper:
    """The population's minibatch step."""
    net, adam = _stacked(K)
    mb = _minibatch(K)

    def step() -> None:
        logp, raw = net.log_prob(mb.obs, mb.u)
        loss, _ = loss_terms(NetOutputs(logp, raw, net.value(mb.obs)), mb, HOPPER, net.entropy)
        net.grad.zero_()
        backward_quietly(loss.sum())
        _clip_and_adam(net, adam, K)

    return Stepper(step, lambda: net.theta.detach())


def vmap_step(K: int) -> Stepper:
    """torch.func: vmap of grad of one run's loss over the stacked flat parameters."""
    template = _models(1)[0]
    flat = template.flat
    net, adam = _stacked(K)
    mb = _minibatch(K)
    n_pol = flat.n_policy

    def loss_fn(theta: Tensor, packed: Tensor) -> Tensor:
        m = Minibatch._from_packed(packed, OBS)
        pol = flat_views(theta[: n_pol - ACT], flat.shapes[: flat.n_policy_tensors])
        extra = theta[n_pol - ACT : n_pol]
        val = flat_views(theta[n_pol:], flat.value_shapes)
        loc = flat.policy_fn(pol, m.obs)
        row = torch.cat([torch.zeros(ACT), extra])
        logp = template.head.log_prob(row, m.u - loc)
        v = flat.value_fn(val, m.obs)[..., 0]
        loss, _ = loss_terms(NetOutputs(logp, row, v), m, HOPPER, template.entropy)
        return loss

    grad_fn = torch.func.vmap(torch.func.grad(loss_fn))

    def step() -> None:
        g = grad_fn(net.theta.detach(), mb.packed)
        net.grad.copy_(g)
        _clip_and_adam(net, adam, K)

    return Stepper(step, lambda: net.theta.detach())


def stacked_bmm_step(K: int) -> Stepper:
    """The population's step with every layer a plain baddbmm (not a run alone's bits)."""
    inner = stacked_step(K)

    def step() -> None:
        saved = stacked_nn.linear_mode
        stacked_nn.linear_mode = lambda *args: "bmm"  # type: ignore[assignment]
        try:
            inner.step()
        finally:
            stacked_nn.linear_mode = saved

    return Stepper(step, inner.theta)


OPTIONS: dict[str, Callable[[int], Stepper]] = {
    "separate": separate_step,
    "vmap": vmap_step,
    "stacked": stacked_step,
    "stacked-bmm": stacked_bmm_step,
}


def equal_to_separate(K: int = 4, steps: int = 3) -> dict[str, bool]:
    """Whether each option's parameters after ``steps`` minibatch steps are those of the
    runs stepped one after another (the solo learner's code), bit for bit."""
    ref = separate_step(K)
    for _ in range(steps):
        ref.step()
    out = {}
    for name, make in OPTIONS.items():
        option = make(K)
        for _ in range(steps):
            option.step()
        out[name] = bool(torch.equal(option.theta(), ref.theta()))
    return out


def _time(step: Callable[[], None], reps: int) -> float:
    step()  # warm-up (and the layer probes)
    t0 = time.perf_counter()
    for _ in range(reps):
        step()
    return (time.perf_counter() - t0) / reps


def options_part(ks: list[int], rounds: int, steps: int) -> list[dict[str, Any]]:
    """µs per member-step of every option at every K, the median over rounds."""
    steppers = {(name, K): make(K) for name, make in OPTIONS.items() for K in ks}
    times: dict[tuple[str, int], list[float]] = {key: [] for key in steppers}
    for r in range(rounds):
        for key, step in steppers.items():
            reps = max(3, steps // key[1])
            times[key].append(_time(step.step, reps) / key[1] * 1e6)
        print(f"options round {r + 1}/{rounds} done", flush=True)
    rows = []
    for (name, K), us in times.items():
        base = statistics.median(times[("separate", K)])
        med = statistics.median(us)
        rows.append({"option": name, "K": K, "us_per_member_step": med, "rounds_us": us,
                     "speedup_vs_separate": base / med})  # fmt: skip
    return rows


# -- part 2: whole runs ------------------------------------------------------------------
def _solo_update(learner: BatchLearner) -> tuple[float, float]:
    t0 = time.perf_counter()
    learner.collect_rollouts()
    t1 = time.perf_counter()
    learner.train()
    return t1 - t0, time.perf_counter() - t1


def _population_update(pop: BatchPopulation) -> tuple[float, float]:
    t0 = time.perf_counter()
    _, errors = pop.collect_rollouts()
    t1 = time.perf_counter()
    pop.train([k for k in pop.busy() if k not in errors])
    return t1 - t0, time.perf_counter() - t1


def _env_floor(pop: BatchPopulation) -> tuple[float, float]:
    """The environments alone: n_steps vector steps of every member with zero actions, as
    the population steps them (:func:`step_same_step`); (seconds, 0)."""
    action = np.zeros((pop.cfg.n_envs, pop.model.act_dim), dtype=np.float32)
    obs = np.zeros((pop.cfg.n_envs, pop.obs_dim))
    reward = np.zeros(pop.cfg.n_envs)
    term = np.zeros(pop.cfg.n_envs, dtype=bool)
    trunc = np.zeros(pop.cfg.n_envs, dtype=bool)
    envs = [pop.learner(k).envs for k in pop.busy()]
    t0 = time.perf_counter()
    for _ in range(pop.cfg.n_steps):
        for e in envs:
            step_same_step(e, action, obs, reward, term, trunc)  # type: ignore[arg-type]
    return time.perf_counter() - t0, 0.0


def _bracketed(
    variants: dict[str, Callable[[], tuple[float, float]]], rounds: int
) -> tuple[dict[str, list[tuple[float, float]]], dict[str, list[float]]]:
    """Every variant once per round, each between two updates of the run alone: the
    (rollout, update) seconds of every variant and, for each of its updates, the mean time
    of the two updates alone around it (the load of the moment)."""
    alone = variants["alone"]
    split: dict[str, list[tuple[float, float]]] = {name: [] for name in variants}
    around: dict[str, list[float]] = {name: [] for name in variants}
    for r in range(rounds):
        before = alone()
        split["alone"].append(before)
        for name, update in variants.items():
            if name == "alone":
                continue
            split[name].append(update())
            after = alone()
            split["alone"].append(after)
            around[name].append((sum(before) + sum(after)) / 2)
            before = after
        print(f"runs round {r + 1}/{rounds} done", flush=True)
    return split, around


def runs_part(ks: list[int], rounds: int) -> list[dict[str, Any]]:
    """Member-steps/s of a run alone and of populations of K (members of all three methods),
    each update of a population between two updates of the run alone."""
    torch.manual_seed(0)
    solo = BatchLearner(HOPPER)
    pops = {}
    for K in ks:
        pops[K] = BatchPopulation(HOPPER, K)
        for k in range(K):
            pops[K].start(k, replace(HOPPER, seed=k, method=("ppo", "rpe", "rb")[k % 3]))
    variants: dict[str, Callable[[], tuple[float, float]]] = {"alone": lambda: _solo_update(solo)}
    for K, pop in pops.items():
        variants[f"K={K}"] = lambda pop=pop: _population_update(pop)  # type: ignore[misc]
    floor_k = max(k for k in ks if k <= 10) if min(ks) <= 10 else min(ks)
    variants["envs"] = lambda: _env_floor(pops[floor_k])
    for update in variants.values():
        update()  # warm-up: the first rollout and the layer probes
    split, around = _bracketed(variants, rounds)
    members = {"alone": 1, **{f"K={K}": K for K in ks}, "envs": floor_k}
    rows = []
    for name, times in split.items():
        per_step = 1e6 / (HOPPER.n_steps * members[name])
        rates = [1e6 / ((a + b) * per_step) for a, b in times]
        # member-steps/s against the run alone's at the moment (the updates around it)
        ratios = [] if name == "alone" else [
            members[name] * t_alone / (a + b)
            for (a, b), t_alone in zip(times, around[name], strict=True)
        ]  # fmt: skip
        rows.append({
            "variant": name, "members": members[name],
            "member_steps_per_s": statistics.median(rates), "rounds_member_steps_per_s": rates,
            "us_per_member_step": 1e6 / statistics.median(rates),
            "rollout_us_per_member_step": statistics.median(a for a, _ in times) * per_step,
            "update_us_per_member_step": statistics.median(b for _, b in times) * per_step,
            "ratio_to_alone": statistics.median(ratios) if ratios else 1.0,
            "rounds_ratio_to_alone": ratios,
        })  # fmt: skip
    solo.close()
    for pop in pops.values():
        pop.close()
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--ks", type=int, nargs="+", default=[1, 4, 10, 30])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=200, help="minibatch steps per option round")
    ap.add_argument("--parts", nargs="+", default=["options", "runs"], choices=["options", "runs"])
    ap.add_argument("--note", default="", help="what shared the cores")
    ap.add_argument("--out", default=str(HERE / "results" / "batch_population.json"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    load = {"start": os.getloadavg()}
    payload: dict[str, Any] = {"ks": args.ks, "rounds": args.rounds, "note": args.note}
    if "options" in args.parts:
        payload["equal_to_runs_alone"] = equal_to_separate()
        payload["options"] = options_part(args.ks, args.rounds, args.steps)
    if "runs" in args.parts:
        payload["config"] = {k: getattr(HOPPER, k) for k in HOPPER.__dataclass_fields__}
        payload["runs"] = runs_part(args.ks, args.rounds)
    load["end"] = os.getloadavg()
    payload["load_average"] = load
    path = write_json(args.out, payload)
    print(f"wrote {path}")
    for row in payload.get("options", []):
        print(f"{row['option']:>12} K={row['K']:<3} {row['us_per_member_step']:8.1f} us/member-step"
              f"  x{row['speedup_vs_separate']:.2f}")  # fmt: skip
    for row in payload.get("runs", []):
        split = (row["rollout_us_per_member_step"], row["update_us_per_member_step"])
        print(f"{row['variant']:>6} {row['member_steps_per_s']:8.0f} member-steps/s "
              f"(rollout {split[0]:.0f} + update {split[1]:.0f} us)"
              f"  x{row['ratio_to_alone']:.2f}")  # fmt: skip


if __name__ == "__main__":
    main()
