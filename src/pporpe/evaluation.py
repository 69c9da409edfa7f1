"""Evaluation of a trained policy: returns of test episodes and their summary.

The paper scores a trained policy by the *median* return of 50 test episodes acted
with the policy's location (no sampling).
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .envs import make_env, resolve_env_id
from .envs.registration import is_gymnasium_mujoco
from .run_files import read_evaluation

__all__ = [
    "EVAL_SEED_OFFSET",
    "MUJOCO_GL_HEADLESS",
    "EvalResult",
    "check_mujoco_gl",
    "check_video_support",
    "evaluate_policy",
    "load_evaluation",
    "prefer_egl_without_display",
    "summarize_returns",
]

EVAL_SEED_OFFSET = 1_000_003
"""Test episodes of a run with seed s use environment seed s + EVAL_SEED_OFFSET, apart from
training seeds."""


@dataclass(frozen=True)
class EvalResult:
    """Summary of test returns."""

    episodes: int
    """Number of test episodes."""
    median: float
    """Median return: the paper's score."""
    mean: float
    """Mean return."""
    q25: float
    """25th percentile of the returns."""
    q75: float
    """75th percentile of the returns."""
    returns: list[float]
    """Every test return, in episode order."""

    @property
    def iqr(self) -> float:
        """Interquartile range q75 - q25."""
        return self.q75 - self.q25

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (with the IQR)."""
        return {**asdict(self), "iqr": self.iqr}


def summarize_returns(returns: list[float]) -> EvalResult:
    """Median, mean and quartiles of a list of returns."""
    if not returns:
        raise ValueError("returns must hold at least one episode return; got []")
    arr = np.asarray(returns, dtype=np.float64)
    q25, med, q75 = np.percentile(arr, [25, 50, 75])
    return EvalResult(
        len(returns),
        float(med),
        float(arr.mean()),
        float(q25),
        float(q75),
        [float(r) for r in returns],
    )


def load_evaluation(run_dir: str | Path) -> EvalResult | None:
    """The test-episode summary saved in ``run_dir/evaluation.json``, or None without one;
    the file is read as data (:func:`pporpe.run_files.read_evaluation`: ``ValueError``
    naming it if it is not an evaluation)."""
    path = Path(run_dir) / "evaluation.json"
    if not path.exists():
        return None
    stored = read_evaluation(run_dir)
    if "returns" not in stored:
        raise ValueError(f"{path}: it holds no returns (only their median); run pporpe "
                         "evaluate on the folder again")  # fmt: skip
    return summarize_returns(stored["returns"])


def evaluate_policy(
    act: Callable[[np.ndarray], np.ndarray],
    env_name: str,
    episodes: int,
    seed: int,
    video_dir: str | Path | None = None,
    video_episodes: int = 1,
    progress: bool = False,
) -> EvalResult:
    """Run ``episodes`` test episodes with the deterministic policy ``act``.

    The environment is seeded once with ``seed`` (callers pass the training seed plus
    :data:`EVAL_SEED_OFFSET`) and each episode runs until termination or truncation.
    ``progress``: a progress bar of the test episodes on standard error, shown only when
    that is a terminal (50 HalfCheetah episodes take about a minute).

    With ``video_dir``, the first ``video_episodes`` test episodes are also recorded there
    as MP4 files (``rl-video-episode-<i>.mp4``, one frame per step plus the reset frame)
    through Gymnasium's ``RecordVideo``, rendering with ``render_mode="rgb_array"``
    (headless for the PyBullet tasks); the returns are the same as without it. Needs
    moviepy (``pip install "pporpe[video]"``) and what the task renders with
    (:func:`check_video_support`, before any episode); a ``video_dir`` created here is
    removed again if the call fails and it is empty.
    """
    if not (isinstance(episodes, int) and episodes >= 1):
        raise ValueError(f"episodes must be an int >= 1; got episodes={episodes!r}")
    if video_dir is None:
        env = make_env(env_name, seed=seed, render_mode=None)
        return _run_episodes(act, env, episodes, seed, progress)
    if not (isinstance(video_episodes, int) and 1 <= video_episodes <= episodes):
        raise ValueError(
            f"video_episodes must be an int in [1, episodes={episodes}]; got {video_episodes!r}"
        )
    check_video_support(env_name)
    created = not Path(video_dir).exists()
    try:
        from gymnasium.wrappers import RecordVideo

        env = RecordVideo(
            make_env(env_name, seed=seed, render_mode="rgb_array"),
            str(video_dir),
            episode_trigger=lambda i: i < video_episodes,
            disable_logger=True,
        )
        return _run_episodes(act, env, episodes, seed, progress)
    except BaseException:
        if created:
            with contextlib.suppress(OSError):  # only if empty
                Path(video_dir).rmdir()
        raise


def _run_episodes(
    act: Callable[[np.ndarray], np.ndarray], env: Any, episodes: int, seed: int,
    progress: bool = False,
) -> EvalResult:  # fmt: skip
    """``episodes`` episodes of ``act`` in ``env`` (seeded once with ``seed``), then closed;
    with ``progress``, a bar of them (on a terminal only)."""
    from tqdm import tqdm

    returns: list[float] = []
    # disable=None: tqdm draws nothing when standard error is not a terminal
    bar = tqdm(total=episodes, desc="test episodes", unit="ep", dynamic_ncols=True,
               disable=None if progress else True)  # fmt: skip
    try:
        obs, _ = env.reset(seed=seed)
        for i in range(episodes):
            total, done = 0.0, False
            while not done:
                obs, reward, terminated, truncated, _ = env.step(act(obs))
                total += float(reward)
                done = terminated or truncated
            returns.append(total)
            bar.update(1)
            if i + 1 < episodes:
                obs, _ = env.reset()
    finally:
        bar.close()
        env.close()
    return summarize_returns(returns)


def check_video_support(env_name: str | None = None) -> None:
    """Raise ImportError, saying what to install, when video recording is unavailable:
    moviepy, and with ``env_name`` what that task renders its frames with (pygame for
    Gymnasium's classic-control tasks such as Pendulum-v1; one frame is rendered to see).

    A MuJoCo task renders through OpenGL, which ``MUJOCO_GL`` chooses (GLFW, its default,
    needs a display): on Linux without a display (no ``DISPLAY`` or ``WAYLAND_DISPLAY``)
    and ``MUJOCO_GL`` unset, it is set to ``egl`` (a GPU driver's headless OpenGL) for
    this process; a frame that still cannot be rendered raises one line naming
    ``MUJOCO_GL`` and what to set it to."""
    import importlib.util

    if importlib.util.find_spec("moviepy") is None:
        raise ImportError(
            'recording video needs moviepy: pip install "pporpe[video]" (or pip install moviepy)'
        )
    if env_name is None:
        return
    from gymnasium.error import DependencyNotInstalled

    env = make_env(env_name, render_mode="rgb_array")
    mujoco = _is_mujoco(env)
    if mujoco:
        prefer_egl_without_display()
    try:
        with warnings.catch_warnings():  # GLFW warns before it fails without a display
            warnings.simplefilter("ignore")
            env.reset(seed=0)
            env.render()
    except DependencyNotInstalled as exc:
        reason = (str(exc).strip().splitlines() or ["a package is missing"])[0]
        raise ImportError(f"recording video of {env_name} needs its renderer: {reason}") from None
    except Exception as exc:
        if not mujoco:
            raise
        raise ImportError(_mujoco_gl_problem(env_name, exc)) from None
    finally:
        env.close()


MUJOCO_GL_HEADLESS = "egl"
"""What ``MUJOCO_GL`` is set to for a video on Linux without a display, when unset."""


def prefer_egl_without_display() -> bool:
    """Set ``MUJOCO_GL`` to :data:`MUJOCO_GL_HEADLESS` on Linux without a display when it is
    unset (MuJoCo would try GLFW, which needs a display); whether it was set."""
    import os
    import sys

    if os.environ.get("MUJOCO_GL") or not sys.platform.startswith("linux"):
        return False
    if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        return False
    os.environ["MUJOCO_GL"] = MUJOCO_GL_HEADLESS
    return True


def check_mujoco_gl(env_name: str) -> None:
    """For a MuJoCo task, with ``MUJOCO_GL`` set: import MuJoCo now. MuJoCo reads
    ``MUJOCO_GL`` on import, and a backend it cannot load (``osmesa`` without libOSMesa, a
    misspelt value) fails there with an AttributeError or RuntimeError; here that is one
    ``ImportError`` naming ``MUJOCO_GL``. An ImportError is MuJoCo itself missing, which
    building the task names (with what to install). Other tasks never import MuJoCo: nothing
    to do."""
    import importlib.util
    import os

    import gymnasium

    gl = os.environ.get("MUJOCO_GL")
    if not gl or importlib.util.find_spec("mujoco") is None:
        return
    if not is_gymnasium_mujoco(gymnasium.envs.registry[resolve_env_id(env_name)].entry_point):
        return
    try:
        import mujoco  # noqa: F401
    except ImportError:  # MuJoCo itself is missing, not its backend: building the task says so
        return
    except Exception as exc:
        reason = " ".join(str(exc).split())[:160] or "no reason given"
        raise ImportError(
            f"{env_name} is a MuJoCo task, and MuJoCo cannot load the OpenGL backend "
            f"MUJOCO_GL={gl} ({type(exc).__name__}: {reason}); set MUJOCO_GL=egl (a GPU "
            "driver's EGL) or MUJOCO_GL=osmesa (software, needs libOSMesa), or unset it "
            "(docs/getting-started.md)"
        ) from None


def _is_mujoco(env: Any) -> bool:
    """Whether ``env`` is a Gymnasium MuJoCo task (rendered through ``MUJOCO_GL``)."""
    import sys

    if "mujoco" not in sys.modules:  # a MuJoCo task has imported it
        return False
    from gymnasium.envs.mujoco.mujoco_env import MujocoEnv

    return isinstance(env.unwrapped, MujocoEnv)


def _mujoco_gl_problem(env_name: str, exc: Exception) -> str:
    """One line: the MuJoCo task's frame could not be rendered with this ``MUJOCO_GL``."""
    import os

    gl = os.environ.get("MUJOCO_GL")
    chosen = f"MUJOCO_GL={gl}" if gl else "MUJOCO_GL unset (GLFW, which needs a display)"
    reason = " ".join(str(exc).split())[:160] or "no reason given"
    return (
        f"recording video of {env_name} needs an OpenGL context, and {chosen} gave none "
        f"({type(exc).__name__}: {reason}); set MUJOCO_GL=egl (a GPU driver's EGL) or "
        "MUJOCO_GL=osmesa (software, needs libOSMesa) (docs/getting-started.md)"
    )
