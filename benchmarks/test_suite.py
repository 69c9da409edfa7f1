"""How long ``make test`` takes from a fresh clone: commits timed side by side, and the page
``benchmarks/results/test_suite.md`` rendered from ``test_suite.json``.

    python benchmarks/test_suite.py measure --run A=9c7f8e3 --run B=HEAD --order ABAB \\
        --title "..." --held "..."
    python benchmarks/test_suite.py render

``measure`` clones this repository once per trial (``git clone``, then ``git checkout``: no
venv, no numba kernel cache, no mypy cache, no docs build), and times the README's test
command there in two parts: the install (``make .venv/.installed-dev``: a new venv, pip
from its local cache) and ``make test`` itself. Each trial records the wall seconds of each,
the CPU seconds ``/usr/bin/time`` counts (make and every process it waited for: a Ray
daemon, or a process forked from a forkserver, is not counted), the share of the machine's
CPU time that was idle during ``make test`` (from ``/proc/stat``), the load averages, and
pytest's summary line and slowest tests. The trials run in the order given, one after the
other; what else ran on the machine goes in ``--held``. The results are appended to the
JSON as one study, and the page is rendered from all of them (``render`` alone rewrites
the page). ``tests/test_benchmark_summaries.py`` checks that the committed page is the
rendering of the committed JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
JSON_PATH = HERE / "results" / "test_suite.json"
PAGE_PATH = HERE / "results" / "test_suite.md"
SLOWEST = 15
"""How many of the slowest tests a trial keeps (pytest ``--durations``)."""


def cpu_idle_jiffies() -> tuple[int, int]:
    """The machine's idle and total CPU time so far, in clock ticks (``/proc/stat``)."""
    fields = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    return fields[3] + fields[4], sum(fields)  # idle + iowait, all


def timed(command: list[str], cwd: Path, log: Path) -> dict[str, Any]:
    """Run ``command`` under ``/usr/bin/time``: exit status, wall and CPU seconds, and the
    machine's idle share meanwhile; its output goes to ``log``."""
    times = log.with_suffix(".time")
    idle0, all0 = cpu_idle_jiffies()
    with log.open("w") as out:
        timer = ["/usr/bin/time", "-f", "%e %U %S", "-o", str(times)]
        done = subprocess.run([*timer, *command], cwd=cwd, stdout=out, stderr=subprocess.STDOUT,
                              check=False)  # fmt: skip
    idle1, all1 = cpu_idle_jiffies()
    wall, user, system = (float(x) for x in times.read_text().split()[-3:])
    return {"exit_status": done.returncode, "wall_s": wall, "cpu_s": round(user + system, 1),
            "idle_share": round((idle1 - idle0) / max(all1 - all0, 1), 3)}  # fmt: skip


def pytest_summary(text: str) -> tuple[str | None, float | None, list[dict[str, Any]]]:
    """pytest's last summary line, its seconds, and the slowest tests it listed."""
    lines = re.findall(r"^=*\s*(\d+ (?:passed|failed).* in ([\d.]+)s.*?)\s*=*$", text, re.M)
    slow = [{"s": float(s), "when": when, "test": test} for s, when, test in
            re.findall(r"^([\d.]+)s (call|setup|teardown)\s+(\S+)$", text, re.M)]  # fmt: skip
    if not lines:
        return None, None, slow
    line, seconds = lines[-1]
    return re.sub(r" in [\d.]+s.*$", "", line), float(seconds), slow[:SLOWEST]


def machine(clone: Path) -> dict[str, Any]:
    """The machine, and the versions the clone's venv installed of what sets the pace."""
    cpu = next((line.split(":", 1)[1].strip() for line in
                Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")), "?")  # fmt: skip
    code = (
        "import importlib.metadata as m, sys; print(sys.version.split()[0], "
        "*(m.version(p) for p in ('pytest', 'pytest-xdist', 'torch', 'mypy', 'sphinx')))"
    )
    found = subprocess.run([str(clone / ".venv" / "bin" / "python"), "-c", code],
                           capture_output=True, text=True, check=False).stdout.split()  # fmt: skip
    names = ("python", "pytest", "pytest_xdist", "torch", "mypy", "sphinx")
    return {"cpu": cpu, "cores": os.cpu_count(), **dict(zip(names, found, strict=False))}


def trial(label: str, commit: str, work: Path) -> dict[str, Any]:
    """One fresh clone of ``commit``: its install and its ``make test``, timed."""
    clone = work / f"clone_{label}_{int(time.time())}"
    subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
    subprocess.run(["git", "checkout", "-q", commit], cwd=clone, check=True)
    full = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=clone, check=True,
                          capture_output=True, text=True).stdout.strip()  # fmt: skip
    start = time.strftime("%H:%M:%S")
    load0 = [round(x, 2) for x in os.getloadavg()]
    install = timed(["make", ".venv/.installed-dev"], clone, work / f"{clone.name}.install.log")
    env_opts = f"--durations={SLOWEST} -p no:cacheprovider"
    test = timed(["env", f"PYTEST_ADDOPTS={env_opts}", "make", "test"], clone,
                 work / f"{clone.name}.test.log")  # fmt: skip
    line, seconds, slow = pytest_summary((work / f"{clone.name}.test.log").read_text())
    return {
        "label": label, "commit": full, "start": start, "load_at_start": load0,
        "load_at_end": [round(x, 2) for x in os.getloadavg()],
        "install_s": install["wall_s"], "install_cpu_s": install["cpu_s"],
        "exit_status": test["exit_status"], "wall_s": test["wall_s"], "cpu_s": test["cpu_s"],
        "idle_share": test["idle_share"], "pytest_line": line, "pytest_s": seconds,
        "durations_top15": slow, "machine": machine(clone),
    }  # fmt: skip


def measure(args: argparse.Namespace) -> None:
    runs = dict(r.split("=", 1) for r in args.run)
    if set(args.order) - set(runs):
        raise SystemExit(f"--order {args.order}: a label without a --run")
    counts: dict[str, int] = {}
    trials = []
    with tempfile.TemporaryDirectory(prefix="suite_") as tmp:
        for label in args.order:
            counts[label] = counts.get(label, 0) + 1
            name = f"{label}{counts[label]}" if args.order.count(label) > 1 else label
            trials.append(trial(name, runs[label], Path(tmp)))
            print(json.dumps(trials[-1]), flush=True)
    study = {
        "title": args.title,
        "how": (f"`python benchmarks/test_suite.py measure --run {' --run '.join(args.run)} "
                f"--order {args.order}` (and the texts below): per "
                "trial `git clone` and `git checkout`, then `make .venv/.installed-dev` (the "
                "install: a new venv, pip from its local cache) and `make test`, each timed "
                "by /usr/bin/time (wall; CPU = user + sys of make and every process it "
                "waited for, so not Ray's daemons nor processes forked from a forkserver); "
                "idle = the machine's idle share of CPU time during make test (/proc/stat). "
                f"Trials in the order {args.order}."),
        "labels": {label: desc for label, desc in (d.split("=", 1) for d in args.describe)},
        "held": args.held,
        "trials": trials,
        "ratios": [[args.order[1], args.order[0]]] if len(runs) == 2 else [],
        "durations_of": [t["label"] for t in trials[-len(runs):]],
        "machine": {k: v for k, v in trials[-1]["machine"].items()
                    if all(t["machine"].get(k) == v for t in trials)},  # what every trial shared
    }  # fmt: skip
    data = json.loads(JSON_PATH.read_text()) if JSON_PATH.exists() else {"studies": []}
    data["studies"].append(study)
    write(data)


def write(data: dict[str, Any]) -> None:
    from pporpe.io import atomic_write_json, atomic_write_text

    atomic_write_json(JSON_PATH, data)
    atomic_write_text(PAGE_PATH, render(data))
    print(f"wrote {JSON_PATH.relative_to(ROOT)} and {PAGE_PATH.relative_to(ROOT)}")


def _num(x: float | None, digits: int = 1) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def _trial_row(t: dict[str, Any]) -> str:
    install = t.get("install_s")
    total = None if install is None else install + t["wall_s"]
    loads = f"{t['load_at_start'][0]} / {t['load_at_end'][0]}"
    idle = "-" if t.get("idle_share") is None else f"{100 * t['idle_share']:.0f}%"
    tests = re.sub(r" in [\d.]+s.*$", "", t.get("pytest_line") or f"exit {t['exit_status']}")
    return (f"| {t['label']} | {t['commit']} | {_num(install)} | {_num(t['wall_s'])} | "
            f"{_num(total)} | {_num(t['cpu_s'])} | {idle} | {_num(t.get('pytest_s'))} | "
            f"{tests} | {loads} |")  # fmt: skip


def _ratio_line(study: dict[str, Any], after: str, before: str) -> str:
    """The means of the trials of label ``after`` over those of ``before`` (A1, A2, ... are
    trials of A)."""

    def mean(label: str, key: str) -> float | None:
        values = [t.get(key) for t in study["trials"] if t["label"].rstrip("0123456789") == label]
        return None if not values or None in values else sum(values) / len(values)

    parts = []
    for key, name in (("install_s", "install"), ("wall_s", "make test"), ("cpu_s", "CPU"),
                      ("pytest_s", "pytest")):  # fmt: skip
        a, b = mean(after, key), mean(before, key)
        if a and b:
            parts.append(f"{name} {a / b:.2f}")
    a_install, b_install = mean(after, "install_s"), mean(before, "install_s")
    a_test, b_test = mean(after, "wall_s"), mean(before, "wall_s")
    if a_install and b_install and a_test and b_test:
        both = (a_install + a_test) / (b_install + b_test)
        parts.append(f"install and make test {both:.2f}")
    return f"{after} / {before} (means of their trials): " + ", ".join(parts) + "."


def _durations(t: dict[str, Any]) -> list[str]:
    rows = [f"| {d['s']:.1f} | {d['test'].removeprefix('tests/')} ({d['when']}) |"
            for d in t.get("durations_top15", [])]  # fmt: skip
    return [f"### {t['label']} ({t['commit']})", "", "| s | test |", "| ---: | --- |", *rows, ""]


def render_study(study: dict[str, Any]) -> list[str]:
    out = [f"## {study['title']}", "", study["how"], ""]
    if study.get("machine"):
        out += ["Machine: " + ", ".join(f"{k} {v}" for k, v in study["machine"].items()) + ".", ""]
    out += [f"- {label}: {desc}" for label, desc in study.get("labels", {}).items()]
    out += ["", "| run | commit | install (s) | make test (s) | both (s) | CPU (s) | idle | "
            "pytest (s) | tests | load at start / end |",
            "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | --- | --- |"]  # fmt: skip
    out += [_trial_row(t) for t in study["trials"]] + [""]
    out += [_ratio_line(study, after, before) for after, before in study.get("ratios", [])]
    out += ["", f"Held: {study['held']}", ""]
    if study.get("note"):
        out += [study["note"], ""]
    shown = [t for t in study["trials"] if t["label"] in study.get("durations_of", [])]
    if any(t.get("durations_top15") for t in shown):
        out += [f"### Slowest {SLOWEST} (pytest --durations)", ""]
        for t in shown:
            out += _durations(t)
    return out


def render(data: dict[str, Any]) -> str:
    """The page: every study, newest first."""
    out = ["# make test, timed (issue 54, item 5)", "",
           "Generated by `python benchmarks/test_suite.py render` from "
           "`benchmarks/results/test_suite.json`; each study was measured by "
           "`python benchmarks/test_suite.py measure` or, before that script, by hand as its "
           "text says.", ""]  # fmt: skip
    for study in reversed(data["studies"]):
        out += render_study(study)
    return "\n".join(out).rstrip("\n") + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    m = sub.add_parser("measure", help="time make test from fresh clones of commits")
    m.add_argument("--run", action="append", required=True, help="LABEL=COMMIT")
    m.add_argument("--describe", action="append", default=[], help="LABEL=what it is")
    m.add_argument("--order", required=True, help="labels in the order to run, e.g. ABAB")
    m.add_argument("--title", required=True)
    m.add_argument("--held", required=True, help="what else ran on the machine")
    sub.add_parser("render", help="rewrite the page from the JSON")
    args = parser.parse_args()
    if args.command == "measure":
        measure(args)
    else:
        write(json.loads(JSON_PATH.read_text()))


if __name__ == "__main__":
    main()
