"""Every ``python`` block of docs/api.md runs, in order, in one namespace (issue 12); every
example of the README and of the guide pages runs, and every documented command parses."""

from __future__ import annotations

import os
import re
import shlex
from pathlib import Path

import pytest
import torch
import warm_process

API = Path(__file__).resolve().parents[1] / "docs" / "api.md"
BLOCKS = re.findall(r"^```python\n(.*?)^```$", API.read_text(), flags=re.S | re.M)


def test_api_page_has_an_example_per_public_part() -> None:
    text = "\n".join(BLOCKS)
    for name in ("surrogate_objective", "OnlineLearner", "PopulationLearner", "TrainConfig",
                 "zoo_config", "load_policy", "pporpe.sb3", "reproduce"):  # fmt: skip
        assert name in text, name


ROOT = API.parents[1]
README = (ROOT / "README.md").read_text()
PAGES = ["README.md", *(f"docs/{p.name}" for p in sorted(API.parent.glob("*.md")))]


def _every_block() -> list[tuple[str, int, str]]:
    """Every ``python`` block of the README and the docs: (page, its number, its code)."""
    found = []
    for page in PAGES:
        blocks = re.findall(r"^```python\n(.*?)^```$", (ROOT / page).read_text(), re.S | re.M)
        found += [(page, i + 1, code) for i, code in enumerate(blocks)]
    return found


BLOCKS_EVERYWHERE = _every_block()


def test_the_docs_have_their_examples() -> None:
    pages = {page for page, _, _ in BLOCKS_EVERYWHERE}
    assert {"README.md", "docs/api.md", "docs/batch.md", "docs/sb3.md"} <= pages
    assert len([b for b in BLOCKS_EVERYWHERE if b[0] == "docs/api.md"]) == len(BLOCKS) >= 8


@pytest.mark.parametrize(
    ("page", "number", "code"), BLOCKS_EVERYWHERE, ids=[f"{p}#{n}" for p, n, _ in BLOCKS_EVERYWHERE]
)
def test_every_docs_example_runs_on_its_own(page: str, number: int, code: str,
                                            tmp_path: Path) -> None:  # fmt: skip
    """As a reader runs it: the block alone, saved as a file, run by ``python`` in a fresh
    folder and a process of its own (:mod:`warm_process`), which catches an example that
    needs an earlier one, or a grid without its ``if __name__ == "__main__":`` guard."""
    script = tmp_path / "example.py"
    script.write_text(code)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    done = warm_process.run([], script=script, cwd=tmp_path, env=env, timeout=600)
    assert done.returncode == 0, f"{page} block {number} failed:\n{done.stderr[-3000:]}"




def _blocks(text: str, lang: str) -> list[str]:
    return re.findall(rf"^```{lang}\n(.*?)^```$", text, flags=re.S | re.M)


def _commands(text: str) -> list[list[str]]:
    """The ``pporpe ...`` command lines of a text's ``bash`` blocks, comments dropped."""
    lines = [ln for b in _blocks(text, "bash") for ln in b.splitlines()]
    return [shlex.split(ln, comments=True) for ln in lines if ln.startswith("pporpe ")]


def _run_blocks(blocks: list[str], where: str) -> dict[str, object]:
    torch.set_num_threads(1)
    namespace: dict[str, object] = {"__name__": "__docs__"}
    for i, block in enumerate(blocks):
        try:
            exec(compile(block, f"{where} block {i + 1}", "exec"), namespace)
        except Exception as exc:  # name the block that failed
            raise AssertionError(f"{where} block {i + 1} failed: {exc!r}\n{block}") from exc
    return namespace


def test_readme_python_examples_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every ``python`` block of the README runs as written: the surrogate in a loss of
    one's own, and the one-word switch inside Stable-Baselines3."""
    blocks = _blocks(README, "python")
    assert len(blocks) == 2
    monkeypatch.chdir(tmp_path)
    ns = _run_blocks(blocks, "README.md")
    assert torch.isfinite(ns["loss"]).item()  # type: ignore[arg-type]
    assert ns["logp_old"].requires_grad is False  # type: ignore[attr-defined]
    assert ns["ratio"].grad_fn is not None  # type: ignore[attr-defined]
    assert ns["model"].surrogate == "rpe"  # type: ignore[attr-defined]
    assert ns["model"].num_timesteps >= 1024  # type: ignore[attr-defined]


def test_readme_cli_example_runs_with_a_tiny_budget(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The README's command-line example, as written but for its budget (2 training
    episodes, 1 test episode, no compile step), trains and evaluates a run folder."""
    from pporpe.cli import main

    train, evaluate = _commands(README)
    assert train[:2] == ["pporpe", "train"] and evaluate[:2] == ["pporpe", "evaluate"]
    tiny = {"--episodes": "2", "--eval-episodes": "1"}
    monkeypatch.chdir(tmp_path)
    torch.set_num_threads(1)
    for argv in (train, evaluate):
        args = [tiny.get(prev, arg) for prev, arg in zip(["", *argv], argv)][1:]
        extra = ["--no-compile", "--quiet"] if argv[1] == "train" else []
        assert main([*args, *extra]) == 0, argv
    out = train[train.index("--out") + 1]
    assert (tmp_path / out / "done.json").exists()
    assert "test return over 1 episode:" in capsys.readouterr().out


def test_every_documented_command_parses() -> None:
    """Every ``pporpe ...`` line of the README's and the docs' ``bash`` blocks is a command
    the parser accepts (running them takes minutes to hours)."""
    from pporpe.cli import build_parser

    pages = [README, *(p.read_text() for p in sorted(API.parent.glob("*.md")))]
    commands = [c for text in pages for c in _commands(text)]
    assert len(commands) >= 8
    for argv in commands:
        args = [a.replace("HOST:PORT", "127.0.0.1:6379") for a in argv[1:]]
        try:
            build_parser().parse_args(args)
        except SystemExit as exc:
            raise AssertionError(f"{shlex.join(argv)} does not parse") from exc


def test_the_version_is_one_in_every_place() -> None:
    """pyproject.toml, pporpe.__version__, the changelog's top entry and the README's
    software citation name the same version."""
    import tomllib

    import pporpe

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    top = re.search(r"^## \[(\d+\.\d+\.\d+)\] - \d{4}-\d{2}-\d{2}$",
                    (ROOT / "CHANGELOG.md").read_text(), flags=re.M)  # fmt: skip
    cited = re.search(r"@software\{pporpe,.*?version = \{([^}]+)\}", README, flags=re.S)
    assert top is not None and cited is not None
    assert project["version"] == pporpe.__version__ == top.group(1) == cited.group(1)
    assert project["license"] == "MIT" and (ROOT / "LICENSE").read_text().startswith("MIT")


def test_readme_stays_a_front_page() -> None:
    """At most 150 lines: history belongs in CHANGELOG.md and results in docs/results/."""
    assert len(README.splitlines()) <= 150
    assert "arxiv.org/abs/2010.03290" in README and "results/headline.png" in README
    assert (ROOT / "results/headline.png").is_file()  # committed, not only drawn here
