"""Every upgrade of a run folder written by an earlier pporpe, in one place.

Old run folders stay readable and resumable as the runs they were. What changed on disk:

* ``config.json`` of 0.1.0 has no ``"kind"``: a batch run said ``"learner": "batch"``, an
  online run nested its learner settings under ``"learner"`` (:func:`upgrade_config`);
* online learner settings added after a run was written are filled with the value that
  run ran with, never with today's default (:data:`ONLINE_FIELDS_ADDED`);
* a population checkpoint of 0.4.0 and earlier named its runs by their full paths
  (:func:`packing_names`);
* an online checkpoint of 0.1.0 holds a flat ``theta`` and no sampling stream: its policy
  still loads, the run cannot be continued (:func:`check_online_resumable`).

Each upgrade has a fixture test (tests/fixtures; tests/test_runs.py, test_fidelity_choices.py).

Not upgraded, on purpose: batch runs once logged a ``trace_decay`` of 1.0 (batch PPO has no
eligibility traces) where they now leave the cell empty (None). Such folders and their
checkpoints read 1.0, as written (:func:`pporpe.runs.logger.read_records`); no number of
the report reads the trace decay.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from types import MappingProxyType
from typing import Any

__all__ = [
    "ONLINE_FIELDS_ADDED",
    "check_online_resumable",
    "packing_names",
    "upgrade_config",
]

ONLINE_FIELDS_ADDED: Mapping[str, Any] = MappingProxyType(
    {
        # added in 0.2.x, when the author's test bed was read: what 0.2.0 ran with
        "critic_signal": "td",
        "td_units": "scaled",
        "entropy_density": "action",
        "amsgrad_max": "bias_corrected",
        "amsgrad_decay": 0.999,
        "layer_norm_affine": True,
        "trace_divergence": "sample",
        # added in 0.5.0, for the test bed's learner: what every earlier run did
        "policy_gradient": "surrogate",
        "time_limit": "bootstrap",
        "min_scale": 1e-3,
        "head_tensors": "joint",
        "engine": "torch",
    }
)
"""Online learner settings that a run folder may lack, with the value such a run ran with
(the learner before the setting existed). Fixed history: never follows today's defaults."""


def upgrade_config(data: dict[str, Any]) -> dict[str, Any]:
    """``config.json`` content in today's form: the kind of a 0.1.0 folder added, and the
    online learner's settings that did not exist when it was written filled in."""
    if "kind" not in data:
        if data.get("learner") == "batch":
            data = {"kind": "batch", **{k: v for k, v in data.items() if k != "learner"}}
        else:
            data = {"kind": "online", **data}
    learner = data.get("learner")
    if data["kind"] == "online" and isinstance(learner, dict):
        missing = {k: v for k, v in ONLINE_FIELDS_ADDED.items() if k not in learner}
        if missing:
            data = {**data, "learner": {**learner, **missing}}
    return data


def packing_names(
    saved_runs: Any, names: Sequence[str], full_paths: Sequence[str]
) -> Sequence[str] | None:
    """The spelling of the runs in a saved population checkpoint: ``names`` (relative to
    the home folder), the full paths of 0.4.0 and earlier, or None (another job's)."""
    for spelling in (names, full_paths):
        if saved_runs == list(spelling):
            return spelling
    return None


def check_online_resumable(member: Mapping[str, Any]) -> None:
    """Refuse to continue an online checkpoint of 0.1.0 (a flat ``theta``, no stream)."""
    if "params" not in member:
        raise ValueError(
            "this run was started by pporpe's first release (0.1.0), which sampled from "
            "torch's global random stream; it cannot be continued exactly. Its policy "
            "still evaluates (pporpe evaluate); train it again in a new folder"
        )
