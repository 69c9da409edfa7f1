"""Every committed grid's report is what ``pporpe report`` writes from its run folders today.

Each folder ``results/<grid>/`` with a ``grid.json`` is copied to a temporary folder of the
same name with only what the report reads (``grid.json``, the hand-written ``notes.md``, a
pre-registration (``preregistration.json`` and its document), the
run folders without checkpoints), ``pporpe report`` runs on the copy through the CLI's entry
point, and every file it writes must be committed: the text files (``REPORT.md``, the
summaries, ``runs.csv``) byte for byte, the figures by what they draw (the PDF's page
content: every path, mark and label with its position, to 0.01 pt; the PNG only its pixel
size, not its pixels). A committed file of the folder that the report does not write must be
an input or a known hand-written or grid file, so that a report output left stale (a figure
the report no longer draws) fails too. One test per grid, so that ``pytest -n`` spreads
the grids' bootstraps (10,000 resamples per interval) over the workers.
"""

from __future__ import annotations

import json
import re
import shutil
import struct
import zlib
from pathlib import Path

import pytest

from pporpe.cli import main as pporpe_main

ROOT = Path(__file__).resolve().parents[1]
GRIDS = sorted(p.parent.name for p in (ROOT / "results").glob("*/grid.json"))
INPUTS = ("grid.json", "notes.md", "preregistration.json", "preregistration.md")
"""The files at the top of a grid's folder that the report reads."""
NOT_FROM_THE_REPORT = {"status.json", "preregistration.md"}
"""Committed beside a report, written by something else: the grid's status
(``pporpe reproduce``) and a hand-written pre-registration."""
LEFT_OUT = shutil.ignore_patterns("checkpoint.pt", "tensorboard", ".lock", ".*.tmp")
"""What a clone has no copy of (``.gitignore``): checkpoints, logs, locks."""
TOLERANCE_PT = 0.01
"""How far a drawn coordinate may move (PDF points) and still be the same figure."""


def test_the_committed_grids_are_found() -> None:
    assert {"paper", "paper-testbed", "paper-50seeds", "paper-full", "batch-mujoco"} <= set(GRIDS)


def copy_inputs(grid: Path, into: Path) -> Path:
    """The report's inputs of ``grid`` copied to ``into/<grid name>`` (the report names its
    folder in REPORT.md, so the copy keeps the name)."""
    out = into / grid.name
    out.mkdir(parents=True)
    for name in INPUTS:
        if (grid / name).is_file():
            shutil.copy2(grid / name, out / name)
    for sub in grid.iterdir():
        if sub.is_dir() and sub.name != "populations":
            shutil.copytree(sub, out / sub.name, ignore=LEFT_OUT)
    return out


def top_files(folder: Path) -> set[str]:
    return {p.name for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")}


_TOKEN = re.compile(
    rb"\((?:\\.|[^\\)])*\)"  # a string
    rb"|<[0-9A-Fa-f\s]*>"  # a hex string
    rb"|/[^\s/\[\]()<>{}%]+"  # a name
    rb"|[-+]?(?:\d+\.\d*|\.\d+|\d+)"  # a number
    rb"|[A-Za-z'\"*]+|\[|\]"  # an operator, an array's bracket
)


def pdf_drawing(path: Path) -> list[bytes | float]:
    """The tokens of a PDF's page content streams (numbers as floats): what the page draws
    and where, without the file's fonts, metadata, object numbering or compression."""
    data = path.read_bytes()
    pages = re.findall(rb"/Type\s*/Page\b[^>]*?/Contents\s+(\d+)\s+0\s+R", data, re.S)
    assert pages, f"{path}: no page with contents"
    tokens: list[bytes | float] = []
    for number in pages:
        found = re.search(rb"\b" + number + rb"\s+0\s+obj\s*(<<.*?>>)\s*stream\r?\n", data, re.S)
        assert found is not None, f"{path}: content stream {number.decode()} not found"
        start = found.end()
        end = data.index(b"endstream", start)
        raw = data[start:end]
        stream = zlib.decompressobj().decompress(raw) if b"/FlateDecode" in found[1] else raw
        for tok in _TOKEN.findall(stream):
            is_number = tok[:1].isdigit() or tok[:1] in b"+-."
            tokens.append(float(tok) if is_number else tok)
    return tokens


def same_drawing(got: list[bytes | float], want: list[bytes | float]) -> str | None:
    """None if the two drawings are the same (numbers to :data:`TOLERANCE_PT`), else where
    they first differ."""
    if len(got) != len(want):
        return f"{len(got)} drawing tokens, committed {len(want)}"
    for i, (a, b) in enumerate(zip(got, want, strict=True)):
        if isinstance(a, float) and isinstance(b, float):
            if abs(a - b) > TOLERANCE_PT:
                return f"token {i}: {a} against committed {b}"
        elif a != b:
            return f"token {i}: {a!r} against committed {b!r}"
    return None


def png_size(path: Path) -> tuple[int, int]:
    """Width and height in pixels from a PNG's header."""
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR", f"{path} is no PNG"
    width, height = struct.unpack(">II", head[16:24])
    return width, height


def test_the_drawing_comparison_sees_a_moved_point_and_ignores_metadata(tmp_path: Path) -> None:
    from matplotlib.figure import Figure

    def draw(y: float, name: str, creator: str) -> Path:
        fig = Figure(figsize=(3, 2))
        fig.subplots().plot([0.0, 1.0, 2.0], [0.0, y, 1.0], label="curve")
        path = tmp_path / name
        fig.savefig(path, format="pdf", metadata={"Creator": creator, "CreationDate": None})
        return path

    base = pdf_drawing(draw(0.5, "a.pdf", "one"))
    assert base and any(isinstance(t, float) for t in base)
    assert same_drawing(pdf_drawing(draw(0.5, "b.pdf", "another")), base) is None
    assert same_drawing(pdf_drawing(draw(0.52, "c.pdf", "one")), base) is not None


@pytest.mark.parametrize("name", GRIDS)
def test_a_committed_report_regenerates_from_its_run_folders(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    committed = ROOT / "results" / name
    out = copy_inputs(committed, tmp_path)
    before = top_files(out)
    assert pporpe_main(["report", str(out)]) == 0, capsys.readouterr().err
    capsys.readouterr()
    written = top_files(out) - before
    assert {"REPORT.md", *tables_of(committed)} <= written
    assert written <= top_files(committed), "written, never committed"
    unexplained = top_files(committed) - written - set(INPUTS) - NOT_FROM_THE_REPORT
    assert not unexplained, f"committed, no longer written by the report: {sorted(unexplained)}"
    differences = [f"{file}: {why}" for file in sorted(written)
                   if (why := difference(out / file, committed / file))]  # fmt: skip
    assert not differences, "differs from the committed file: " + "; ".join(differences)


def tables_of(grid: Path) -> tuple[str, ...]:
    """The tables a grid's report writes beside REPORT.md: a tuning sweep's (stage 1) its
    sensitivity and trust-region tables, any other grid's its summary."""
    stage = (json.loads((grid / "grid.json").read_text()).get("sweep") or {}).get("stage")
    return ("sensitivity.csv", "trust_region.csv") if stage == 1 else ("summary.md", "summary.csv")


def difference(got: Path, want: Path) -> str | None:
    """How a regenerated file differs from the committed one (None: it does not): text
    byte for byte, a PDF by its drawing, a PNG by its size."""
    if got.suffix == ".pdf":
        return same_drawing(pdf_drawing(got), pdf_drawing(want))
    if got.suffix == ".png":
        sizes = png_size(got), png_size(want)
        return None if sizes[0] == sizes[1] else f"{sizes[0]} pixels, committed {sizes[1]}"
    return None if got.read_bytes() == want.read_bytes() else "other text"
