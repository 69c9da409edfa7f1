"""The one run loop: same numbers as before the package reshape, run folders of pporpe 0.1.0
still load, every learner kind records its kind, and a new kind plugs in by registration."""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from pporpe.batch import BatchConfig, load_batch_learner, train_batch
from pporpe.cli import main
from pporpe.config import config_from_dict
from pporpe.experiments.grid import parse_spec
from pporpe.online.config import OnlineConfig, TrainConfig
from pporpe.runs import (
    Episode,
    Progress,
    get_kind,
    kind_of,
    load_policy,
    open_run_dir,
    read_config,
    read_records,
    register_kind,
    train,
)
from pporpe.runs.kinds import kinds

FIXTURES = Path(__file__).parent / "fixtures"
BEHAVIOUR = json.loads((FIXTURES / "behaviour_v0_1.json").read_text())


def records_without_time(records: list[Any]) -> list[dict[str, Any]]:
    return [{k: v for k, v in r.__dict__.items() if k != "wall_time"} for r in records]


def assert_same_records(records: list[Any], expected: list[dict[str, Any]]) -> None:
    """Equal records; ``trace_decay`` (a logged per-episode mean of float32 values) to the
    last bit of float32 only: pporpe 0.1.0 averaged a strided column of a stacked
    ``[steps, 5]`` tensor, which sums the same values in another order than a contiguous
    1-D tensor. Every other field, and every learned number, is compared exactly."""
    got = records_without_time(records)
    assert [{k: v for k, v in r.items() if k != "trace_decay"} for r in got] == [
        {k: v for k, v in r.items() if k != "trace_decay"} for r in expected
    ]
    np.testing.assert_allclose(
        [r["trace_decay"] for r in got], [r["trace_decay"] for r in expected], rtol=2e-7
    )


def theta_summary(theta: torch.Tensor) -> dict[str, Any]:
    t = theta.detach()
    return {
        "theta_sum": float(t.double().sum()),
        "theta_abs_sum": float(t.double().abs().sum()),
        "theta_head": [float(x) for x in t[:8]],
    }


def fixture_config(name: str) -> Any:
    """The run configuration saved in the behaviour fixture (a 0.1.0 config.json)."""
    data = dict(BEHAVIOUR[name]["config"])
    if name == "batch":
        data.pop("learner")
        return config_from_dict(BatchConfig, data)
    return config_from_dict(TrainConfig, data)


@pytest.mark.parametrize("name", ["online", "batch"])
def test_same_numbers_as_before_the_reshape(name: str, tmp_path: Path) -> None:
    """Records, test returns and final parameters equal those pporpe 0.1.0 produced."""
    expected = BEHAVIOUR[name]
    cfg = fixture_config(name)
    result = train(cfg, tmp_path / name, progress=False)
    assert_same_records(result.records, expected["records"])
    assert result.evaluation is not None
    assert result.evaluation.returns == expected["eval_returns"]
    state = torch.load(tmp_path / name / "checkpoint.pt", weights_only=False)
    assert theta_summary(state["learner"]["theta"]) == {
        k: expected[k] for k in ("theta_sum", "theta_abs_sum", "theta_head")
    }


def test_config_json_records_the_kind(tmp_path: Path) -> None:
    online = TrainConfig(episodes=1, eval_episodes=0, learner=OnlineConfig(layers=1, units=4))
    train(online, tmp_path / "o", progress=False)
    batch = BatchConfig(total_steps=32, n_steps=32, batch_size=32, n_epochs=1, eval_episodes=0)
    train(batch, tmp_path / "b", progress=False)
    assert json.loads((tmp_path / "o" / "config.json").read_text())["kind"] == "online"
    assert json.loads((tmp_path / "b" / "config.json").read_text())["kind"] == "batch"
    assert read_config(tmp_path / "o")[1] == online
    assert read_config(tmp_path / "b")[1] == batch
    assert kind_of(online).name == "online" and kind_of(batch).name == "batch"


@pytest.mark.parametrize("name", ["online", "batch"])
def test_run_folder_of_version_0_1_still_loads(name: str, tmp_path: Path) -> None:
    """A folder written by pporpe 0.1.0 (no "kind" in config.json): its config and kind are
    read, its policy acts as it did (same test returns), and training it again returns the
    finished run without touching it."""
    run = tmp_path / name
    shutil.copytree(FIXTURES / f"run_v0_1_{name}", run)
    assert "kind" not in json.loads((run / "config.json").read_text())
    kind, cfg = read_config(run)
    assert kind.name == name and cfg == fixture_config(name)
    saved = json.loads((run / "evaluation.json").read_text())
    assert main(["evaluate", str(run), "--episodes", str(saved["episodes"])]) == 0
    again = json.loads((run / "evaluation.json").read_text())
    assert again["returns"] == saved["returns"] == BEHAVIOUR[name]["eval_returns"]
    csv_before = (run / "episodes.csv").read_text()
    result = train(cfg, run, progress=False)
    assert records_without_time(result.records) == BEHAVIOUR[name]["records"]
    assert (run / "episodes.csv").read_text() == csv_before
    assert "kind" not in json.loads((run / "config.json").read_text())  # left as it was


def test_unfinished_version_0_1_folder_resumes_as_the_same_run(tmp_path: Path) -> None:
    """A 0.1.0 online folder without done.json resumes from its checkpoint to the records an
    uninterrupted run gives."""
    run = tmp_path / "old"
    shutil.copytree(FIXTURES / "run_v0_1_online", run)
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    (run / "done.json").unlink()
    # roll the folder back to its checkpoint after 2 episodes: rerun the first 2 episodes
    cfg = fixture_config("online")
    two = train(
        TrainConfig(**{**cfg.__dict__, "episodes": 2, "eval_episodes": 0}),
        tmp_path / "two",
        progress=False,
    )
    ckpt = torch.load(tmp_path / "two" / "checkpoint.pt", weights_only=False)
    legacy = {k: ckpt[k] for k in ("learner", "records", "total_steps", "wall_time")}
    legacy.update(torch_rng=ckpt["torch_rng"], env_rng=ckpt["env_rng"])  # 0.1.0 layout
    torch.save(legacy, run / "checkpoint.pt")
    assert len(state["records"]) == 4 and len(two.records) == 2
    result = train(cfg, run, progress=False)
    assert result.resumed_from == 2
    assert_same_records(result.records, BEHAVIOUR["online"]["records"])


def test_legacy_and_current_config_json_are_the_same_run(tmp_path: Path) -> None:
    run = tmp_path / "old"
    shutil.copytree(FIXTURES / "run_v0_1_batch", run)
    kind, cfg = read_config(run)
    from pporpe.runs.folder import config_json

    _, done = open_run_dir(run, config_json(kind, cfg))  # no "different config" error
    assert done
    with pytest.raises(ValueError, match="different config"):
        open_run_dir(run, {**config_json(kind, cfg), "seed": 99})
    cfg2, learner = load_batch_learner(run)
    assert cfg2 == cfg and learner.model.parameters_finite()


def test_unknown_kind_is_refused_by_name() -> None:
    with pytest.raises(ValueError, match=r"kind must be one of \['batch', 'online'.*got kind='x'"):
        get_kind("x")
    with pytest.raises(ValueError, match="no learner kind runs a int"):
        kind_of(3)


# --- a new learner kind plugs into the loop by registration --------------------------
@dataclass(frozen=True)
class CountConfig:
    """A toy run: ``episodes`` episodes of ``length`` steps, return = episode index."""

    env: str = "pendulum"
    seed: int = 0
    episodes: int = 5
    length: int = 3
    checkpoint_every: int = 2
    eval_episodes: int = 0


class CountTrainer:
    bar_unit = "ep"

    def __init__(self, cfg: CountConfig) -> None:
        self.cfg, self.done = cfg, 0
        self.bar_total = cfg.episodes
        self.noise = float(torch.rand(()))  # seeded by the loop

    def advance(self) -> Progress:
        self.done += 1
        ep = Episode(
            self.done * self.cfg.length, self.done + self.noise, self.cfg.length, 0.0, 0.0, 1.0, 0.0
        )
        return Progress([ep], self.done % self.cfg.checkpoint_every == 0, 1)

    def finished(self) -> bool:
        return self.done >= self.cfg.episodes

    def bar_position(self) -> int:
        return self.done

    def counters(self) -> dict[str, int]:
        return {"total_steps": self.done * self.cfg.length, "chunks": self.done}

    def state_dict(self) -> dict[str, Any]:
        return {"done": self.done, "noise": self.noise}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.done, self.noise = state["done"], state["noise"]

    def parameters_finite(self) -> bool:
        return True

    def act_deterministic(self, obs: Any) -> np.ndarray:
        return np.zeros(1)

    def close(self) -> None:
        pass


class CountKind:
    name = "count"
    config_type = CountConfig

    def make_trainer(self, cfg: CountConfig) -> CountTrainer:
        return CountTrainer(cfg)

    def load_policy(self, cfg: CountConfig, state: dict[str, Any]) -> Any:
        return CountTrainer(cfg).act_deterministic

    def grid_config(self, env, method, seed, budget, common, learner, where):  # type: ignore[no-untyped-def]
        return CountConfig(env=env, seed=seed, episodes=budget["episodes"], **common)

    def description(self, cfg: CountConfig) -> str:
        return "count"


def test_a_registered_kind_trains_resumes_and_runs_in_a_grid(tmp_path: Path) -> None:
    register_kind(CountKind())
    assert "count" in kinds()
    full = train(CountConfig(seed=7), tmp_path / "full", progress=False)
    assert [r.episode for r in full.records] == [0, 1, 2, 3, 4]
    assert json.loads((tmp_path / "full" / "done.json").read_text())["chunks"] == 5

    class Stop(RuntimeError):
        pass

    def stop_at_3(rec: Any) -> None:
        if rec.episode == 2:
            raise Stop

    with pytest.raises(Stop):
        train(CountConfig(seed=7), tmp_path / "cut", progress=False, on_episode=stop_at_3)
    assert len(read_records(tmp_path / "cut" / "episodes.csv")) == 2  # checkpoint after 2
    resumed = train(CountConfig(seed=7), tmp_path / "cut", progress=False)
    assert resumed.resumed_from == 2
    assert records_without_time(resumed.records) == records_without_time(full.records)
    spec = parse_spec(
        {
            "kind": "count",
            "methods": ["ppo"],
            "seeds": 2,
            "tasks": [{"env": "pendulum", "episodes": 4}],
        }
    )
    assert [r.config for r in spec.runs] == [
        CountConfig(seed=s, episodes=4, checkpoint_every=10, eval_episodes=50) for s in (0, 1)
    ]
    cfg, act = load_policy(tmp_path / "full")
    assert cfg == CountConfig(seed=7) and act(None).shape == (1,)


def test_grid_of_batch_runs(tmp_path: Path) -> None:
    """A spec with kind = "batch" builds zoo configs with the overrides, and refuses
    episode budgets and unknown fields by name."""
    base = {"kind": "batch", "methods": ["ppo", "rpe"], "seeds": 1, "eval_episodes": 0}
    spec = parse_spec(
        {
            **base,
            "learner": {"n_steps": 64, "n_envs": 1},
            "tasks": [{"env": "pendulum", "steps": 128}],
        }
    )
    cfgs = [r.config for r in spec.runs]
    assert all(isinstance(c, BatchConfig) for c in cfgs)
    assert [(c.method, c.total_steps, c.n_steps, c.lr) for c in cfgs] == [
        ("ppo", 128, 64, 2.5e-4),
        ("rpe", 128, 64, 2.5e-4),
    ]
    with pytest.raises(ValueError, match=r"tasks\[0\]\.learner: batch runs take 'steps'"):
        parse_spec({**base, "tasks": [{"env": "pendulum", "episodes": 3}]})
    with pytest.raises(ValueError, match=r"unknown field\(s\) \['kappa'\] of BatchConfig"):
        parse_spec({**base, "learner": {"kappa": 1.0}, "tasks": [{"env": "pendulum", "steps": 64}]})
    with pytest.raises(ValueError, match="field 'kind'"):
        parse_spec({**base, "kind": "nope", "tasks": [{"env": "pendulum", "steps": 64}]})
    result = train_batch(cfgs[1], tmp_path / "rpe", progress=False)
    assert result.updates == 2 and result.total_steps == 128
