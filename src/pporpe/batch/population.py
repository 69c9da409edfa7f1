r"""K batch PPO runs trained in lockstep in one process: :class:`BatchPopulation`.

A batch run spends its time in many small operations (a 64 x 64 network evaluated on one
observation per step, minibatches of 64 rows: each call costs about as much as its
arithmetic), so K runs whose networks and rollouts have one shape are computed together:
one batched call per layer for all K members, one stacked normalisation, one GAE, one Adam
kernel call. Each member keeps what makes it a run of its own:

* its :class:`~pporpe.batch.learner.BatchLearner` (built as a run alone builds it, seeded
  by its config), which owns its vector environment, holds its counters, and is where
  its state is written back for a checkpoint (:meth:`BatchPopulation.member_state`,
  the format of a run alone, so a run moves freely between a population and a process
  of its own);
* its random stream, a ``torch.Generator`` that continues the global stream a run alone
  would use: action noise and the minibatch permutations are drawn from it in the same
  order;
* row k of the stacked parameters, gradients and Adam state
  (:mod:`pporpe.batch.stacked`) and of the observation and reward statistics
  (:class:`~pporpe.batch.normalize.StackedNormalizer`), its own columns of the rollout
  buffer;
* its settings: method, surrogate thresholds, learning rate and schedule, Adam's
  epsilon, gradient clipping, value clipping, loss weights, target KL, gamma, lambda, the
  clip bounds of its normalisation, its seed and budget. Members whose loss settings
  agree share one call of :func:`pporpe.batch.loss.loss_terms`; the others get one per
  group. What fixes the shape of the computation is common (:data:`SHARED_FIELDS`).

A member computes what the run alone computes: every operation is the solo learner's on
the member's rows, and the batched layers are the forms probed to give the same bits
(:mod:`pporpe.nn.stacked`), so on the machine tested (an AVX-512 Xeon) a member equals a
run of its own bit for bit (``tests/test_batch_population.py``: up to 12 members; 30
checked by hand). A member whose values go non-finite stops alone: nothing mixes the rows
of two members (the loss that is differentiated is the sum of the members' losses, whose
gradient is 1 for each whatever its value).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..envs import env_spec_summary, make_env
from ..nn.stacked import backward_quietly
from .buffer import FinishedEpisode, Minibatch, RolloutBuffer
from .config import BatchConfig
from .learner import (
    BatchLearner,
    UpdateRecord,
    UpdateStats,
    rollout_advantages,
    scheduled_lr,
    update_stats,
)
from .loss import LossMetrics, NetOutputs, config_objective, loss_terms
from .member_envs import EnvStep, step_members
from .model import ActorCritic
from .normalize import StackedNormalizer
from .population_update import LossGroup, Minibatches, StepSettings, grouped_objective
from .stacked import FixedScale, StackedActorCritic, StackedAdam

__all__ = ["SHARED_FIELDS", "BatchPopulation", "Member", "MemberReport", "check_member"]

SHARED_FIELDS: tuple[str, ...] = (
    "env", "n_envs", "n_steps", "batch_size", "n_epochs", "layers", "units", "activation",
    "layer_norm", "policy", "scale", "action_bound", "adv_norm", "normalize_obs",
    "normalize_reward",
)  # fmt: skip
""":class:`BatchConfig` fields every member of a population shares: the task, the shape
of the rollouts, minibatches and networks, and what is normalised."""

_SURROGATE_FIELDS = ("method", "eps", "beta", "eta", "rpe_form")
_LOSS_FIELDS = ("vf_coef", "ent_coef", "clip_vf")
_GAE_FIELDS = ("gamma", "gae_lambda", "bootstrap_truncated")


def check_member(first: BatchConfig, cfg: BatchConfig) -> None:
    """``ValueError`` naming every :data:`SHARED_FIELDS` field where ``cfg`` differs from
    ``first``, and refusing what a population does not run."""
    if cfg.policy != "normal":
        raise ValueError(
            f"a batch population runs policy='normal' only (its members draw their action "
            f"noise from their own generators); got policy={cfg.policy!r}"
        )
    diff = [f for f in SHARED_FIELDS if getattr(cfg, f) != getattr(first, f)]
    if diff:
        pairs = ", ".join(f"{f}={getattr(cfg, f)!r} (not {getattr(first, f)!r})" for f in diff)
        raise ValueError(f"a batch population's members share {list(SHARED_FIELDS)}; got {pairs}")


@dataclass(frozen=True)
class MemberReport:
    """What one :meth:`BatchPopulation.update` did for one member."""

    episodes: list[FinishedEpisode]
    """Episodes that ended during its rollout."""
    stats: UpdateStats | None
    """Its update's statistics (None when it failed)."""
    error: str | None = None
    """Why it failed (a non-finite reward or observation), or None."""


@dataclass
class Member:
    """A member's own pieces: its learner (environments, counters, checkpoint state) and
    its random stream."""

    learner: BatchLearner
    generator: torch.Generator
    lr: float
    """Learning rate of its last update (what its optimizer's state says)."""


class BatchPopulation:
    """Up to ``capacity`` batch runs shaped like ``cfg`` (:data:`SHARED_FIELDS`), trained
    in lockstep: :meth:`update` collects one rollout of every member and learns from it.

    Usage::

        pop = BatchPopulation(cfgs[0], capacity=len(cfgs))
        for k, cfg in enumerate(cfgs):
            pop.start(k, cfg)
        while any(not pop.finished(k) for k in pop.busy()):
            reports = pop.update()
    """

    def __init__(self, cfg: BatchConfig, capacity: int) -> None:
        check_member(cfg, cfg)
        self.cfg = cfg
        """The shape every member shares."""
        self.capacity = capacity
        env = make_env(cfg.env)
        try:
            spec = env_spec_summary(env)
            raw_dtype = np.asarray(env.observation_space.sample()).dtype
        finally:
            env.close()
        self.obs_dim = d = int(spec["obs_dim"])
        with torch.random.fork_rng(devices=[]):
            template = ActorCritic(d, spec["action_low"], spec["action_high"], cfg)
        self.model = StackedActorCritic(template, capacity)
        self.adam = StackedAdam(self.model.theta, self.model.grad)
        K, N = capacity, cfg.n_envs
        self.normalizer = StackedNormalizer(K, N, d, cfg.normalize_obs, cfg.normalize_reward)
        self.buffer = RolloutBuffer(cfg.n_steps, K * N, d, template.act_dim)
        self.raw_obs = np.zeros((K, N, d), dtype=raw_dtype)
        self.obs = np.zeros((K, N, d), dtype=np.float32)
        self.ep_ret = np.zeros((K, N))
        self.ep_len = np.zeros((K, N), dtype=np.int64)
        self.members: list[Member | None] = [None] * K
        self._noise_buffer = torch.zeros(K, N, template.act_dim)
        self._noise_rows = self._noise_buffer.unbind(0)
        n = cfg.rollout_size
        self._diag_ratio = torch.zeros(K, cfg.n_epochs * n)
        self._diag_adv = torch.zeros(K, cfg.n_epochs * n)
        self._mb_stats = torch.zeros(K, cfg.n_epochs * -(-n // cfg.batch_size), 3)

    # -- members in and out -------------------------------------------------------------
    def busy(self) -> list[int]:
        """Slots holding a run."""
        return [k for k, m in enumerate(self.members) if m is not None]

    def _member(self, k: int) -> Member:
        m = self.members[k]
        if m is None:
            raise RuntimeError(f"slot {k} holds no run")
        return m

    def start(self, k: int, cfg: BatchConfig, state: dict[str, Any] | None = None) -> None:
        """Begin run ``cfg`` in free slot ``k``: built and seeded as a run alone
        (``torch.manual_seed(cfg.seed)``, then :class:`BatchLearner`), or continued from
        ``state`` (:meth:`member_state`, or the checkpoint of a run alone)."""
        if self.members[k] is not None:
            raise RuntimeError(f"slot {k} already holds a run")
        check_member(self.cfg, cfg)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(cfg.seed)
            learner = BatchLearner(cfg)
            rng = torch.get_rng_state()
        if state is not None:
            try:
                learner.load_state_dict(state["learner"])
            except Exception:
                learner.close()
                raise
            rng = state["torch_rng"]
        generator = torch.Generator()
        generator.set_state(rng)
        lr = float(learner.optimizer.param_groups[0]["lr"])
        self.members[k] = Member(learner, generator, lr)
        self._load(k)

    def _load(self, k: int) -> None:
        """Slot ``k``'s rows := its learner's state."""
        learner = self._member(k).learner
        self.model.load_member(k, learner.model.theta)
        self.adam.load_member(k, learner.optimizer, learner.model.theta)
        self.normalizer.load_member(k, learner.normalizer)
        self.raw_obs[k], self.obs[k] = learner._raw_obs, learner._obs
        self.ep_ret[k], self.ep_len[k] = learner.ep_ret, learner.ep_len

    def _store(self, k: int) -> BatchLearner:
        """Slot ``k``'s rows written back into its learner (which is returned)."""
        m = self._member(k)
        learner = m.learner
        with torch.no_grad():
            learner.model.theta.copy_(self.model.theta[k])
        self.adam.store_member(k, learner.optimizer, learner.model.theta)
        learner.optimizer.param_groups[0]["lr"] = m.lr
        self.normalizer.store_member(k, learner.normalizer)
        learner._raw_obs, learner._obs = self.raw_obs[k].copy(), self.obs[k].copy()
        learner.ep_ret, learner.ep_len = self.ep_ret[k].copy(), self.ep_len[k].copy()
        return learner

    def member_learner(self, k: int) -> BatchLearner:
        """Member ``k`` as a run alone: its learner with the population's state written
        back (e.g. for :meth:`BatchLearner.act_deterministic`; valid until the next update)."""
        return self._store(k)

    def member_state(self, k: int) -> dict[str, Any]:
        """Member ``k``'s checkpoint state, in the format of a run alone
        (``{"learner": BatchLearner.state_dict(), "torch_rng": ...}``)."""
        learner = self._store(k)
        return {"learner": learner.state_dict(), "torch_rng": self._member(k).generator.get_state()}

    def learner(self, k: int) -> BatchLearner:
        """Member ``k``'s learner: its config, counters and environments (its parameters,
        optimiser and normaliser live in the population: :meth:`member_learner`)."""
        return self._member(k).learner

    def release(self, k: int) -> Member:
        """Free slot ``k`` and return its member, its state written back into its learner
        and its environments open (for :meth:`admit` into another population)."""
        self._store(k)
        member = self._member(k)
        self.members[k] = None
        self.model.clear_member(k)
        self.adam.clear_member(k)
        return member

    def admit(self, k: int, member: Member) -> None:
        """Put a member from :meth:`release` into free slot ``k``."""
        if self.members[k] is not None:
            raise RuntimeError(f"slot {k} already holds a run")
        check_member(self.cfg, member.learner.cfg)
        self.members[k] = member
        self._load(k)

    def stop(self, k: int) -> BatchLearner:
        """Free slot ``k`` (its environments are closed); returns the member's learner with
        its final state written back."""
        learner = self._store(k)
        learner.close()
        self.members[k] = None
        self.model.clear_member(k)
        self.adam.clear_member(k)
        return learner

    def finished(self, k: int) -> bool:
        """Whether member ``k`` has done all its updates."""
        learner = self._member(k).learner
        return learner.updates >= learner.cfg.n_updates

    def parameters_finite(self, k: int) -> bool:
        """Whether every parameter of member ``k`` is finite."""
        return bool(self.model.finite()[k])

    def close(self) -> None:
        """Close every member's environments."""
        for k in self.busy():
            self.stop(k)

    # -- one update of every member ---------------------------------------------------------
    def update(self) -> dict[int, MemberReport]:
        """One rollout of every busy member, then one update of every member whose rollout
        went through (a member with a non-finite reward or observation reports the error)."""
        episodes, errors = self.collect_rollouts()
        ok = [k for k in episodes if k not in errors]
        stats = self.train(ok) if ok else {}
        return {k: MemberReport(episodes[k], stats.get(k), errors.get(k)) for k in sorted(episodes)}

    @torch.no_grad()
    def collect_rollouts(self) -> tuple[dict[int, list[FinishedEpisode]], dict[int, str]]:
        """n_steps vector steps of every busy member with its current policy, then GAE.
        Returns the episodes that ended, by member, and the errors of members whose
        environment gave a non-finite reward or observation (they stop stepping)."""
        busy = self.busy()
        finished: dict[int, list[FinishedEpisode]] = {k: [] for k in busy}
        errors: dict[int, str] = {}
        obs = torch.from_numpy(self.obs)
        fixed = self.model.fixed_scale(self.cfg.n_envs)
        for t in range(self.cfg.n_steps):
            going = [k for k in busy if k not in errors]
            obs = self._rollout_step(t, obs, fixed, going, finished, errors)
        self.obs = obs.numpy()
        self._advantages(self.model.value(obs), [k for k in busy if k not in errors])
        return finished, errors

    def _rollout_step(
        self,
        t: int,
        obs: Tensor,
        fixed: FixedScale | None,
        busy: list[int],
        finished: dict[int, list[FinishedEpisode]],
        errors: dict[int, str],
    ) -> Tensor:
        """Act in every busy member's environments at ``obs`` ``[K, N, obs_dim]``, store
        step ``t``; return the next normalised observations."""
        model, buf, K, N = self.model, self.buffer, self.capacity, self.cfg.n_envs
        u, logp = model.act(obs, self._noise(busy), fixed)
        buf.obs[t] = obs.reshape(K * N, -1)
        buf.u[t] = u.reshape(K * N, -1)
        buf.logp[t] = logp.reshape(K * N)
        buf.values[t] = model.value(obs).reshape(K * N)
        action = model.to_action(u).numpy()
        step = self._step_envs(busy, action, errors)
        ep_ret, ep_len = self.ep_ret, self.ep_len
        ep_ret += step.reward
        ep_len += 1
        reward = self.normalizer.reward(step.reward, step.done)
        buf.rewards[t] = torch.from_numpy(reward).reshape(-1)
        buf.terminated[t] = torch.from_numpy(step.term).reshape(-1)
        buf.truncated[t] = torch.from_numpy(step.trunc).reshape(-1)
        self.raw_obs = step.raw_obs
        next_obs = torch.from_numpy(self.normalizer.obs(step.raw_obs, update=True))
        for k in busy:
            if k not in errors and step.done[k].any():
                finished[k] += self._end_episodes(k, t, step)
        return next_obs

    def _noise(self, busy: list[int]) -> Tensor:
        """Every busy member's standard normal draws ``[N, act_dim]`` from its own stream,
        stacked ``[K, N, act_dim]`` (a free slot's rows are left as they are)."""
        noise, rows = self._noise_buffer, self._noise_rows
        for k in busy:
            torch.randn(noise.shape[1:], generator=self._member(k).generator, out=rows[k])
        return noise

    def _step_envs(self, busy: list[int], action: np.ndarray, errors: dict[int, str]) -> EnvStep:
        """Step every busy member's vector environment with its actions
        (:func:`.member_envs.step_members`)."""
        learners = {k: self._member(k).learner for k in busy}
        return step_members(learners, action, self.raw_obs, self.cfg.n_envs, errors)

    def _end_episodes(self, k: int, t: int, step: EnvStep) -> list[FinishedEpisode]:
        """Member ``k``'s part of :meth:`BatchLearner._end_episodes`: V of the final
        observation of every truncated episode into the buffer, the episodes that ended."""
        term, trunc, done = step.term[k], step.trunc[k], step.done[k]
        idx = np.nonzero(trunc)[0]
        N = self.cfg.n_envs
        if idx.size:
            final = np.stack([np.asarray(step.final_obs[k][int(i)]) for i in idx])
            x = torch.from_numpy(self.normalizer.member_obs(k, final))
            value = self.model.member_value(k, x)
            self.buffer.next_values[t, torch.from_numpy(idx + k * N)] = value
        total = self._member(k).learner.total_steps
        ep_ret, ep_len = self.ep_ret[k], self.ep_len[k]
        ended = [
            FinishedEpisode(int(i), float(ep_ret[i]), int(ep_len[i]), total, bool(term[i]))
            for i in np.nonzero(done)[0]
        ]
        ep_ret[done] = 0.0
        ep_len[done] = 0
        return ended

    def _advantages(self, last_value: Tensor, members: list[int]) -> None:
        """GAE of ``members``' columns, one call per group of equal (gamma, lambda, bootstrap)."""
        N = self.cfg.n_envs
        last = last_value.reshape(-1)
        for cfg, rows in self._groups(members, _GAE_FIELDS):
            if rows is None:
                rollout_advantages(self.buffer, last, cfg)
                continue
            cols = (rows.unsqueeze(1) * N + torch.arange(N)).reshape(-1)
            rollout_advantages(self.buffer, last[cols], cfg, cols)

    def _groups(
        self, members: list[int], fields: tuple[str, ...]
    ) -> list[tuple[BatchConfig, Tensor | None]]:
        """``members`` grouped by their settings ``fields``: (a member's config, its
        group's rows), the rows None when one group holds every slot."""
        groups: dict[tuple[Any, ...], list[int]] = {}
        for k in members:
            cfg = self._member(k).learner.cfg
            groups.setdefault(tuple(getattr(cfg, f) for f in fields), []).append(k)
        out: list[tuple[BatchConfig, Tensor | None]] = []
        for rows in groups.values():
            cfg = self._member(rows[0]).learner.cfg
            whole = len(rows) == self.capacity
            out.append((cfg, None if whole else torch.tensor(rows)))
        return out

    # -- learning -----------------------------------------------------------------------------
    def train(self, members: list[int]) -> dict[int, UpdateStats]:
        """One PPO update of each of ``members`` on its collected rollout: its n_epochs of
        shuffled minibatches, all members' minibatch steps computed together."""
        cfg = self.cfg
        settings = self._step_settings(members)
        rollout = self._rollout_batch()
        book = Minibatches(list(members), dict.fromkeys(members, 0), dict.fromkeys(members, 0),
                            dict.fromkeys(members, 0), {})  # fmt: skip
        pos = row = 0
        n, bs = cfg.rollout_size, cfg.batch_size
        for _epoch in range(cfg.n_epochs):
            if not book.active:
                break
            shuffled = rollout.index_rows(self._permutations(book.active))
            for start in range(0, n, bs):
                mb = shuffled.slice(start, start + bs)
                self._minibatch_step(mb, book, settings, pos, row)
                pos, row = pos + len(mb), row + 1
                if not book.active:
                    break
            for k in book.active:
                book.epochs[k] += 1
        return {k: self._member_stats(k, book) for k in members}

    def _step_settings(self, members: list[int]) -> StepSettings:
        """What the minibatch steps of this update need of each member, gathered once (its
        learning rate under its schedule is recorded as the member's)."""
        cfgs = {k: self._member(k).learner.cfg for k in members}
        lrs = {k: scheduled_lr(c, self._member(k).learner.updates) for k, c in cfgs.items()}
        for k, lr in lrs.items():
            self._member(k).lr = lr
        limits = [cfgs[k].max_grad_norm if k in cfgs else None for k in range(self.capacity)]
        return StepSettings(
            lr=lrs,
            adam_eps={k: c.adam_eps for k, c in cfgs.items()},
            clip=torch.tensor([1.0 if v is None else v for v in limits], dtype=torch.float32),
            no_clip=torch.tensor([v is None for v in limits]),
            target_kl={k: c.target_kl for k, c in cfgs.items() if c.target_kl is not None},
            loss_groups={},
        )

    def _rollout_batch(self) -> Minibatch:
        """Every slot's rollout as one ``[K, n, ...]`` batch (advantages normalised per
        member when ``adv_norm="batch"``)."""
        N, n = self.cfg.n_envs, self.cfg.rollout_size
        batches = []
        for k in range(self.capacity):
            cols = slice(k * N, (k + 1) * N)
            adv = self.buffer.advantages[:, cols].reshape(n)
            if self.cfg.adv_norm == "batch":
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
            batches.append(Minibatch.from_buffer(self.buffer, adv, cols))
        return Minibatch.stack(batches)

    def _permutations(self, active: list[int]) -> Tensor:
        """``[K, n]``: a permutation of the rollout's rows from each active member's stream
        (the identity for the others)."""
        n = self.cfg.rollout_size
        perms = [torch.arange(n)] * self.capacity
        for k in active:
            perms[k] = torch.randperm(n, generator=self._member(k).generator)
        return torch.stack(perms)

    def _minibatch_step(
        self, mb: Minibatch, book: Minibatches, settings: StepSettings, pos: int, row: int
    ) -> None:
        """Loss, backward, per-member clipping and Adam step of one minibatch of every active
        member (a member past its target KL stops before its step, as a run alone)."""
        model = self.model
        logp, raw = model.log_prob(mb.obs, mb.u)
        out = NetOutputs(logp, raw, model.value(mb.obs))
        losses, m = self._losses(out, mb, book.active, settings)
        book.last_raw = m.raw
        self._stop_past_target_kl(m, book, settings)
        if not book.active:
            return
        model.grad.zero_()
        backward_quietly(losses.sum())
        with torch.no_grad():
            norm = torch.linalg.vector_norm(model.grad, dim=1)
            # min(1, max_grad_norm / (norm + 1e-6)) as a run alone computes it: for a float
            # c and a tensor t, PyTorch's c / t is reciprocal(t) * c
            coef = torch.clamp(torch.reciprocal(norm + 1e-6) * settings.clip, max=1.0)
            model.grad.mul_(torch.where(settings.no_clip, 1.0, coef).unsqueeze(1))
            active = book.active
            lr = [settings.lr[k] for k in active]
            self.adam.step(active, lr, [settings.adam_eps[k] for k in active])
            self._diag_ratio[:, pos : pos + len(mb)] = m.ratio
            self._diag_adv[:, pos : pos + len(mb)] = m.adv
            self._mb_stats[:, row] = torch.stack([m.policy_loss, m.value_loss, norm], dim=1)
        for k in active:
            book.rows[k] += 1
            book.samples[k] += len(mb)

    def _losses(
        self, out: NetOutputs, mb: Minibatch, members: list[int], settings: StepSettings
    ) -> tuple[Tensor, LossMetrics]:
        """Every member's loss ``[K]`` (zero for the others) and the metrics: one
        :func:`loss_terms` call per group of equal loss weights and value clipping, each with
        the surrogate of every subgroup of equal surrogate settings on its rows."""
        key = tuple(members)
        if key not in settings.loss_groups:
            settings.loss_groups[key] = self._loss_groups(members)
        groups = settings.loss_groups[key]
        if len(groups) == 1 and groups[0].rows is None:
            return loss_terms(out, mb, groups[0].cfg, self.model.entropy, groups[0].objective)
        K = self.capacity
        losses = torch.zeros(K)
        policy, value = torch.zeros(K), torch.zeros(K)
        ratio, adv = torch.ones(mb.adv.shape), torch.zeros(mb.adv.shape)
        for g in groups:
            rows = g.rows
            assert rows is not None
            part = NetOutputs(out.logp[rows], out.raw[rows], out.value[rows])
            loss, m = loss_terms(part, mb.members(rows), g.cfg, self.model.entropy, g.objective)
            losses = losses.index_put((rows,), loss)
            policy[rows], value[rows], ratio[rows], adv[rows] = (
                m.policy_loss,
                m.value_loss,
                m.ratio,
                m.adv.detach(),
            )
        return losses, LossMetrics(policy, value, ratio, adv, out.raw)

    def _loss_groups(self, members: list[int]) -> list[LossGroup]:
        """``members`` grouped by loss weights and value clipping, each group's surrogate
        one function over the group's rows (per subgroup of equal surrogate settings)."""
        out = []
        for cfg, rows in self._groups(members, _LOSS_FIELDS):
            group = members if rows is None else [int(k) for k in rows]
            subgroups = self._groups(group, _SURROGATE_FIELDS)
            if len(subgroups) == 1:
                out.append(LossGroup(cfg, rows, config_objective(subgroups[0][0])))
                continue
            local = {k: i for i, k in enumerate(group)}
            parts = [(config_objective(c), torch.tensor([local[int(k)] for k in r]))
                     for c, r in subgroups if r is not None]  # fmt: skip
            out.append(LossGroup(cfg, rows, grouped_objective(parts)))
        return out

    def _stop_past_target_kl(
        self, m: LossMetrics, book: Minibatches, settings: StepSettings
    ) -> None:
        """Remove from ``book.active`` every member whose minibatch KL estimate exceeds
        1.5 x its target_kl (the Stable-Baselines3 rule of a run alone), keeping the raw
        policy output of that minibatch for its entropy statistic, as a run alone does."""
        targets = [(k, settings.target_kl[k]) for k in book.active if k in settings.target_kl]
        if not targets:
            return
        kl = (m.ratio - 1.0 - torch.log(m.ratio)).mean(-1)
        for k, target in targets:
            if float(kl[k]) > 1.5 * target:
                book.active.remove(k)
                book.raw[k] = m.raw[k]

    def _member_stats(self, k: int, book: Minibatches) -> UpdateStats:
        """Member ``k``'s :class:`UpdateStats` (the statistics of a run alone)."""
        learner = self._member(k).learner
        rows, samples = book.rows[k], book.samples[k]
        raw = book.raw.get(k, book.last_raw[k] if book.last_raw is not None else None)
        with torch.no_grad():
            entropy = self.model.entropy(raw).mean() if rows and raw is not None else None
        record = UpdateRecord(
            self._mb_stats[k, :rows],
            self._diag_ratio[k, :samples],
            self._diag_adv[k, :samples],
            entropy,
            book.epochs[k],
            self._member(k).lr,
        )
        N = self.cfg.n_envs
        cols = slice(k * N, (k + 1) * N)
        learner.updates += 1
        buf = self.buffer
        return update_stats(learner.cfg, record, buf.returns[:, cols], buf.values[:, cols])
