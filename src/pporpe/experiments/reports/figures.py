"""The paper's analytic figures, drawn from the functions of :mod:`pporpe.surrogates`.

* :func:`relative_ratio_figure` - the paper's Fig. 1 (``img_symmetric``, Sec. II-C): the
  relative density ratio rho_beta over (pi, pi_b) in 3D and 2D, beside the raw ratio.
* :func:`negative_loss_figure` - the paper's Fig. 2 (``img_loss``, Sec. III-A): rho * A^dagger
  against rho for PPO, PPO-RB and PPO-RPE, for A > 0 and A < 0, with the thresholds marked.

:func:`draw_analytic_figures` writes both as PNG and PDF. The figures are
:class:`matplotlib.figure.Figure` objects drawn without pyplot, so this module leaves the
caller's matplotlib backend alone.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure

from ... import surrogates as S
from ...io import atomic_savefig

__all__ = [
    "METHOD_COLORS",
    "METHOD_LABELS",
    "METHOD_STYLES",
    "draw_analytic_figures",
    "negative_loss_figure",
    "relative_ratio_figure",
]

METHOD_LABELS = {"ppo": "PPO", "rb": "PPO-RB", "rpe": "PPO-RPE", "spo": "SPO"}
METHOD_COLORS = {"ppo": "tab:blue", "rb": "tab:green", "rpe": "tab:red", "spo": "tab:purple"}
METHOD_STYLES = {"ppo": "-", "rb": "--", "rpe": "-", "spo": "-."}  # identical curves stay visible


def relative_ratio_figure(beta: float = 0.5, n: int = 101) -> Figure:
    """The paper's Fig. 1 (``img_symmetric``): rho_beta = pi / (beta*pi + (1-beta)*pi_b).

    Drawn over (pi, pi_b).

    (a) 3D surfaces of the raw ratio rho (clipped for display) and of rho_beta;
    (b) 2D view of rho_beta, which is bounded by 1/beta and, for beta = 0.5, symmetric
    around one (rho_beta(pi, pi_b) - 1 = -(rho_beta(pi_b, pi) - 1)).
    """
    grid = torch.linspace(0.01, 1.0, n, dtype=torch.float64)
    pb, p = torch.meshgrid(grid, grid, indexing="xy")
    rho = p / pb
    rb = S.relative_ratio(rho, beta).numpy()
    cap = 1.0 / beta + 1.0 if beta > 0 else 3.0
    raw = np.minimum(rho.numpy(), cap)

    fig = Figure(figsize=(11, 4.6))
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    ax3.plot_surface(pb.numpy(), p.numpy(), raw, cmap="Greys", alpha=0.35, linewidth=0)
    ax3.plot_surface(pb.numpy(), p.numpy(), rb, cmap="coolwarm", alpha=0.9, linewidth=0)
    ax3.set_xlabel(r"baseline density $\pi_b$")
    ax3.set_ylabel(r"latest density $\pi$")
    ax3.set_zlabel("density ratio")
    ax3.set_zlim(0, cap)
    ax3.set_title(
        rf"(a) 3D view: $\rho_\beta$ (colour) and raw $\rho$ (grey, clipped at {cap:g})",
        fontsize=10,
    )
    ax3.view_init(elev=25, azim=-130)

    ax2 = fig.add_subplot(1, 2, 2)
    upper = 1.0 / beta if beta > 0 else float(rb.max())
    levels = np.linspace(0.0, upper, 21)
    cs = ax2.contourf(pb.numpy(), p.numpy(), rb, levels=levels, cmap="coolwarm")
    ax2.contour(pb.numpy(), p.numpy(), rb, levels=[1.0], colors="k", linewidths=1.5)
    ax2.plot([0.01, 1.0], [0.01, 1.0], "k--", linewidth=0.8)
    cbar = fig.colorbar(cs, ax=ax2)
    cbar.set_label(r"relative density ratio $\rho_\beta$")
    ax2.set_xlabel(r"baseline density $\pi_b$")
    ax2.set_ylabel(r"latest density $\pi$")
    ax2.set_title(
        rf"(b) 2D view, $\beta={beta:g}$: $\rho_\beta\in[0, {upper:g})$, "
        r"$\rho_\beta=1$ iff $\pi=\pi_b$",
        fontsize=10,
    )
    ax2.set_aspect("equal")
    fig.suptitle(r"Relative density ratio $\rho_\beta = \pi/(\beta\pi + (1-\beta)\pi_b)$")
    fig.tight_layout()
    return fig


def negative_loss_figure(
    eps: float = 0.1, beta: float = 0.5, eta: float = 0.3, rho_max: float = 2.0
) -> Figure:
    """The paper's Fig. 2 (``img_loss``): the objective rho * A^dagger against rho, A = +-1.

    PPO and PPO-RB have symmetric thresholds 1 -/+ eps on rho; PPO-RPE has its vertices at
    the asymmetric thresholds of :func:`pporpe.surrogates.ratio_thresholds`. SPO, not in the
    paper, is drawn beside them: its parabola peaks at 1 + sign(A) eps.
    """
    rho = torch.linspace(0.0, rho_max, 801, dtype=torch.float64)
    low, high = S.ratio_thresholds(eps, beta)
    fig = Figure(figsize=(11, 4.2))
    axes = fig.subplots(1, 2)
    for ax, sign in zip(axes, (1.0, -1.0), strict=True):
        adv = torch.full_like(rho, sign)
        for method in S.METHODS:  # the paper's three, then SPO beside them
            obj = S.surrogate_objective(method, rho, adv, eps=eps, beta=beta, eta=eta)
            label = METHOD_LABELS[method]
            if method == "rb":
                label += rf" ($\eta={eta:g}$)"
            elif method == "rpe":
                label += rf" ($\beta={beta:g}$)"
            ax.plot(
                rho.numpy(),
                obj.numpy(),
                color=METHOD_COLORS[method],
                label=label,
                lw=2,
                ls=METHOD_STYLES[method],
            )
        ax.plot(rho.numpy(), (rho * sign).numpy(), color="0.5", ls=":", lw=1, label=r"$\rho A$")
        ppo_thr = 1.0 + sign * eps
        rpe_thr = high if sign > 0 else low
        ax.axvline(ppo_thr, color=METHOD_COLORS["ppo"], ls="--", lw=1)
        ax.axvline(rpe_thr, color=METHOD_COLORS["rpe"], ls="--", lw=1)
        # focus on the region around rho = 1, where the surrogates differ in shape
        ymin, ymax = (-1.0, rho_max + 0.3) if sign > 0 else (-rho_max - 0.3, 1.0)
        ax.set_ylim(ymin, ymax)
        ax.text(ppo_thr, ymin + 0.05 * (ymax - ymin), f" {ppo_thr:.3g}", color="tab:blue")
        ax.text(rpe_thr, ymin + 0.12 * (ymax - ymin), f" {rpe_thr:.4g}", color="tab:red")
        ax.set_xlabel(r"density ratio $\rho = \pi/\pi_b$")
        ax.set_ylabel(r"negative loss $\rho A^\dagger$")
        panel = "(a) $A = +1 > 0$" if sign > 0 else "(b) $A = -1 < 0$"
        ax.set_title(panel + rf", $\epsilon={eps:g}$")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left" if sign > 0 else "upper right", fontsize=9)
    fig.suptitle("Negative loss of each surrogate; dashed lines mark the thresholds")
    fig.tight_layout()
    return fig


def draw_analytic_figures(
    out_dir: str | Path, eps: float = 0.1, beta: float = 0.5, eta: float = 0.3
) -> list[Path]:
    """Draw both analytic figures into ``out_dir`` as PNG and PDF; returns the file paths."""
    S.check_surrogate_params("rpe", eps, beta, eta)
    S.check_surrogate_params("rb", eps, beta, eta)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    for name, fig in (
        ("relative_density_ratio", relative_ratio_figure(beta)),
        ("negative_loss", negative_loss_figure(eps, beta, eta)),
    ):
        for ext in ("png", "pdf"):
            written.append(atomic_savefig(fig, out / f"{name}.{ext}"))
    return written
