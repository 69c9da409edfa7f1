"""The analytic-figures command, CLI error handling and atomic writes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest

from pporpe.cli import main
from pporpe.io import atomic_path, atomic_savefig, atomic_write_json


def test_figures_command_writes_png_and_pdf(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["figures", "--out", str(tmp_path)]) == 0
    names = {p.name for p in tmp_path.iterdir()}
    assert names == {
        "relative_density_ratio.png",
        "relative_density_ratio.pdf",
        "negative_loss.png",
        "negative_loss.pdf",
    }
    for png in tmp_path.glob("*.png"):
        img = mpimg.imread(png)
        assert img.shape[0] > 400 and img.shape[1] > 1000  # two readable panels side by side
        assert float(np.std(img)) > 0.05  # not a blank canvas
    for pdf in tmp_path.glob("*.pdf"):
        assert pdf.read_bytes()[:5] == b"%PDF-"
    printed = capsys.readouterr().out.split()
    assert len(printed) == 4


@pytest.mark.parametrize(
    ("args", "name"),
    [(["--beta", "0.95"], "beta*(1+eps)"), (["--eps", "1.5"], "eps"), (["--eta", "-1"], "eta")],
)
def test_figures_command_rejects_bad_parameters(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], name: str
) -> None:
    assert main(["figures", "--out", str(tmp_path / "f"), *args]) == 2
    err = capsys.readouterr().err
    assert name in err and "got" in err
    assert not (tmp_path / "f").exists()  # rejected before any work


def test_atomic_write_replaces_whole_file(tmp_path: Path) -> None:
    target = tmp_path / "r.json"
    atomic_write_json(target, {"a": 1})
    assert json.loads(target.read_text()) == {"a": 1}
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("torn")
        raise RuntimeError("crash mid-write")
    assert json.loads(target.read_text()) == {"a": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]  # no temporary left behind


@pytest.mark.parametrize(("ext", "date_mark"), [("pdf", b"/CreationDate"), ("png", None)])
def test_saved_figures_carry_no_date_so_the_same_figure_gives_the_same_bytes(
    tmp_path: Path, ext: str, date_mark: bytes | None
) -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    ax.plot([0, 1, 2], [1, 0, 2])
    first = atomic_savefig(fig, tmp_path / f"a.{ext}").read_bytes()
    second = atomic_savefig(fig, tmp_path / f"b.{ext}").read_bytes()
    assert first == second
    if date_mark is not None:
        assert date_mark not in first  # matplotlib writes the save time there by default
        dated = atomic_savefig(fig, tmp_path / f"c.{ext}", metadata={}).read_bytes()
        assert date_mark in dated  # an explicit metadata argument is left to the caller
    plt.close(fig)


def test_report_and_figures_leave_the_matplotlib_backend_alone(tmp_path: Path) -> None:
    """Importing pporpe's report and drawing its figures neither switches the caller's
    matplotlib backend nor imports pyplot (a notebook's inline backend stays)."""
    script = (
        "import sys, matplotlib\n"
        "matplotlib.use('svg')\n"
        "import pporpe.experiments.reports.report, pporpe.experiments.reports.figures as F\n"
        f"F.draw_analytic_figures({str(tmp_path)!r})\n"
        "print(matplotlib.get_backend(), 'matplotlib.pyplot' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, check=True
    ).stdout.split()
    assert out == ["svg", "False"]
    assert (tmp_path / "negative_loss.png").stat().st_size > 0
