"""Every ``python`` block of docs/api.md runs, in order, in one namespace (issue 12)."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest
import torch

API = Path(__file__).resolve().parents[1] / "docs" / "api.md"
BLOCKS = re.findall(r"^```python\n(.*?)^```$", API.read_text(), flags=re.S | re.M)


def test_api_page_has_an_example_per_public_part() -> None:
    text = "\n".join(BLOCKS)
    for name in ("surrogate_objective", "OnlineLearner", "PopulationLearner", "TrainConfig",
                 "zoo_config", "load_policy", "pporpe.sb3", "reproduce"):  # fmt: skip
        assert name in text, name


def test_api_examples_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    torch.set_num_threads(1)
    monkeypatch.chdir(tmp_path)
    namespace: dict[str, object] = {"__name__": "__api_docs__"}
    for i, block in enumerate(BLOCKS):
        try:
            exec(compile(block, f"docs/api.md block {i + 1}", "exec"), namespace)
        except Exception as exc:  # name the block that failed
            raise AssertionError(f"docs/api.md block {i + 1} failed: {exc!r}\n{block}") from exc
    # What the examples wrote is there.
    assert (tmp_path / "runs/online/done.json").exists()
    assert (tmp_path / "runs/batch/evaluation.json").exists()
    assert (tmp_path / "ppo_rpe_pendulum.zip").exists()
    assert (tmp_path / "results/tiny/summary.md").exists()
    assert os.listdir(tmp_path / "results/tiny")


def test_readme_sb3_switch_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    readme = (API.parents[1] / "README.md").read_text()
    blocks = re.findall(r"^```python\n(.*?)^```$", readme, flags=re.S | re.M)
    (snippet,) = [b for b in blocks if "from pporpe.sb3 import PPO" in b]
    torch.set_num_threads(1)
    monkeypatch.chdir(tmp_path)
    namespace: dict[str, object] = {}
    exec(compile(snippet, "README.md (sb3)", "exec"), namespace)
    assert namespace["model"].surrogate == "rpe"  # type: ignore[attr-defined]
    assert (tmp_path / "ppo_rpe_pendulum.zip").exists()
