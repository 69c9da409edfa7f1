"""The author's test bed and pporpe's TESTBED learner, update by update, on the same numbers.

Builds the test bed's agent (``modules.ac.AC`` of a test_et checkout, loaded unmodified,
in pporpe's environment: it needs only torch and numpy) and a one-member
:class:`~pporpe.online.PopulationLearner` with ``OnlineConfig(**TESTBED)``, copies the
agent's parameters into pporpe's layout, then feeds both the same transitions and the same
actions for ``--steps`` updates and reports, after each, how far pporpe's parameters are
from the test bed's, relative to how far the test bed's moved from their start:

    python benchmarks/testbed_step.py --checkout ~/test_et [--steps 200] [--json FILE]

It runs three times: without the t-momentum (``k_dof`` inf, plain LaProp momentum on both
sides), with it (``k_dof`` 1, the test bed's), and with it but pporpe's joint policy head
(``head_tensors="joint"``: one output layer for the t-momentum where the test bed has
three), which shows what that choice alone changes. The yardstick of float rounding is
pporpe against itself started one ulp away.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _common import write_json  # noqa: E402
from testbed_worker import CONFIGS, provide_torch_six  # noqa: E402

from pporpe.online.config import TESTBED, OnlineConfig  # noqa: E402
from pporpe.online.population import PopulationLearner  # noqa: E402

OBS, ACT = 5, 1  # InvertedPendulum's sizes


def load_ac(checkout: Path) -> Any:
    """The test bed's agent class, from the checkout's unmodified modules."""
    provide_torch_six()
    sys.path.insert(0, str(checkout))
    from modules.ac import AC  # the author's code

    return AC


def testbed_theta(ac: Any) -> torch.Tensor:
    """The agent's parameters in pporpe's member layout: policy then value, each per hidden
    layer W, b, LayerNorm scale 1 and shift 0 (the test bed has none), then the output
    layer, the policy's rows ordered [loc, scale, dof] as pporpe's head."""
    out: list[torch.Tensor] = []
    for name in ("policy", "value"):
        body, head = ac.nets[name][0], ac.nets[name][1]
        for lin in body.deep_net:
            units = lin.weight.shape[0]
            out += [lin.weight.reshape(-1), lin.bias, torch.ones(units), torch.zeros(units)]
        if name == "policy":
            parts = (head.loc, head.scale, head.dof)
            out += [torch.cat([p.weight for p in parts]).reshape(-1)]
            out += [torch.cat([p.bias for p in parts])]
        else:
            out += [head.weight.reshape(-1), head.bias]
    return torch.cat([t.detach().reshape(-1) for t in out])


def transitions(steps: int, seed: int) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """``(next observation, next pre-squash action, reward)`` for every step."""
    rng = np.random.default_rng(seed)
    return [
        (
            rng.normal(size=OBS).astype(np.float32),
            rng.normal(size=ACT).astype(np.float32),
            float(rng.normal()),
        )
        for _ in range(steps)
    ]


def run_testbed(agent: Any, s0: np.ndarray, u0: np.ndarray, data: list) -> list:
    """The test bed's train() order with the given actions; parameters after each update."""
    agent.train()
    agent.reset()
    _, base_pi, base_v = agent(s0)
    _, pi, v = agent(s0)
    action = torch.as_tensor(u0).view(1, ACT)
    thetas = []
    for next_obs, next_u, reward in data:
        _, next_base_pi, next_base_v = agent(next_obs)
        tderr, decay, loss = agent.criterion(pi, base_pi, action, v, base_v, next_base_v,
                                             reward, False)  # fmt: skip
        agent.update(tderr, decay, loss)
        thetas.append(testbed_theta(agent))
        base_pi, base_v, action = next_base_pi, next_base_v, torch.as_tensor(next_u).view(1, ACT)
        _, pi, v = agent(next_obs)
    return thetas


def run_pporpe(cfg: OnlineConfig, s0: np.ndarray, u0: np.ndarray, data: list,
               theta0: torch.Tensor) -> list:  # fmt: skip
    """pporpe's member with the test bed's parameters, fed the same data."""
    pop = PopulationLearner(OBS, -np.ones(ACT), np.ones(ACT), [cfg], [0], compile_update=False)
    pop.set_member_theta(0, theta0)
    pop.begin_episode([0], s0.reshape(1, OBS), forced_u=torch.as_tensor(u0).view(1, ACT))
    no = np.zeros(1, dtype=bool)
    thetas = []
    for next_obs, next_u, reward in data:
        u = torch.as_tensor(next_u).view(1, ACT)
        pop.step(np.array([reward]), next_obs.reshape(1, OBS), no, no, forced_u=u)
        thetas.append(pop.member_theta(0).clone())
    return thetas


def compare(ac_cls: Any, k_dof: float, head: str, steps: int, seed: int) -> dict[str, Any]:
    """Both learners from the same start; per step the relative parameter gap."""
    torch.manual_seed(seed)
    opt = {"lr": 1e-4, "amsgrad": 0.99999, "method": "tlaprop", "k_dof": k_dof}
    ac = ac_cls(OBS, ACT, False, opt_params=opt, **CONFIGS["testbed"])
    theta0 = testbed_theta(ac)
    settings = {**TESTBED, "k_dof": k_dof, "head_tensors": head, "compile": False}
    cfg = OnlineConfig(**settings)  # type: ignore[arg-type]
    rng = np.random.default_rng(seed)
    s0 = rng.normal(size=OBS).astype(np.float32)
    u0 = rng.normal(size=ACT).astype(np.float32)
    data = transitions(steps, seed + 1)
    ours = run_pporpe(cfg, s0, u0, data, theta0)
    theirs = run_testbed(ac, s0, u0, data)
    # the control: pporpe against itself from a start 1 ulp away (every parameter's last
    # bit flipped at random), the size of float rounding grown through the same updates
    flip = torch.from_numpy(rng.choice([-1.0, 1.0], size=theta0.numel()).astype(np.float32))
    nudged = torch.nextafter(theta0, theta0 + flip)
    control = run_pporpe(cfg, s0, u0, data, nudged)
    return {
        "k_dof": k_dof,
        "head_tensors": head,
        "steps": steps,
        "testbed": gaps_per_step(ours, theirs, theta0, cfg),
        "control_one_ulp": gaps_per_step(ours, control, theta0, cfg),
    }


def gaps_per_step(
    ours: list, other: list, theta0: torch.Tensor, cfg: OnlineConfig
) -> list[dict[str, Any]]:
    """Per update and group of parameters: the largest gap between the two, and that gap
    relative to the largest move of ``other`` from the start."""
    parts = tensor_parts(cfg)
    gaps = []
    for a, b in zip(ours, other, strict=True):
        row: dict[str, Any] = {}
        for name, (lo, hi) in parts.items():
            moved = float((b[lo:hi] - theta0[lo:hi]).abs().max())
            gap = float((a[lo:hi] - b[lo:hi]).abs().max())
            row[name] = {"gap_max": gap, "moved_max": moved, "relative": gap / max(moved, 1e-30)}
        gaps.append(row)
    return gaps


def tensor_parts(cfg: OnlineConfig) -> dict[str, tuple[int, int]]:
    """Where the groups of parameters lie in the member layout: all of them, the policy's
    hidden layers, its output layer, the value network."""
    pop = PopulationLearner(OBS, -np.ones(ACT), np.ones(ACT), [cfg], [0], compile_update=False)
    n_pol = len(pop.lay.real_index[0])
    n_all = n_pol + len(pop.lay.real_index[1])
    n_head = (cfg.units + 1) * pop.head.raw_dim
    return {
        "all": (0, n_all),
        "policy hidden": (0, n_pol - n_head),
        "policy output": (n_pol - n_head, n_pol),
        "value": (n_pol, n_all),
    }


def row_text(row: dict[str, Any]) -> str:
    names = ("policy hidden", "policy output", "value")
    return " ".join(f"{row[k]['relative']:.1e}" for k in names)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--checkout", type=Path, required=True, help="folder of test_et")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, default=HERE / "results" / "testbed" / "step.json")
    args = ap.parse_args()
    torch.set_num_threads(1)
    ac_cls = load_ac(args.checkout.resolve())
    cases = ((math.inf, "per_output"), (1.0, "per_output"), (1.0, "joint"))
    runs = [compare(ac_cls, k, head, args.steps, args.seed) for k, head in cases]
    print("largest parameter gap after n updates, relative to the largest move (policy hidden,")
    print("policy output, value): pporpe against the test bed | pporpe against itself 1 ulp away")
    for r in runs:
        for when in sorted({1, 2, 10, 50, 100, r["steps"]}):
            if when <= r["steps"]:
                ours, control = r["testbed"][when - 1], r["control_one_ulp"][when - 1]
                label = f"k_dof {r['k_dof']}, {r['head_tensors']} head, n = {when}"
                print(f"{label}: {row_text(ours)} | {row_text(control)}")
    keep = sorted({1, 2, 5, 10, 20, 50, 100, 150, args.steps} & set(range(1, args.steps + 1)))
    for r in runs:  # the JSON holds the gaps after these numbers of updates
        r["after_updates"] = keep
        for key in ("testbed", "control_one_ulp"):
            r[key] = [r[key][n - 1] for n in keep]
    write_json(args.json, {"runs": runs})


if __name__ == "__main__":
    main()
