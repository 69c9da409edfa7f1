"""The fused kernel's inputs by name: the columns of the per-member constants and flags
matrices, the codes of the surrogates, activations and heads, the entries of a layout's
geometry vector (:class:`~pporpe.online.fused_engine.engine.FusedEngine` fills them)."""

from __future__ import annotations

__all__ = ["ACTIVATIONS", "C_NAMES", "F_NAMES", "HEADS", "METHOD_CODES"]

C_NAMES: tuple[str, ...] = (
    "reward_scale", "gamma", "one_m_gamma", "beta_td", "beta_de", "td_scale", "neg_kappa",
    "gl1", "gl2", "beta2_f32", "one_m_beta2", "opt_eps", "omb_mom", "w_coef", "tau", "nu",
    "sigma2_min", "beta1", "beta2", "lr", "ams_decay", "eps", "beta", "eta",
)  # fmt: skip
"""Columns of the per-member float constants matrix (float64 ``[K, len(C_NAMES)]``)."""
(
    C_REWARD_SCALE, C_GAMMA, C_ONE_M_GAMMA, C_BETA_TD, C_BETA_DE, C_TD_SCALE, C_NEG_KAPPA,
    C_GL1, C_GL2, C_BETA2_F32, C_ONE_M_BETA2, C_OPT_EPS, C_OMB_MOM, C_W_COEF, C_TAU, C_NU,
    C_SIGMA2_MIN, C_BETA1, C_BETA2, C_LR, C_AMS_DECAY, C_EPS, C_BETA, C_ETA,
) = range(len(C_NAMES))  # fmt: skip

F_NAMES: tuple[str, ...] = (
    "kappa_pos", "mom_only", "polyak", "pre_squash", "critic_actor", "kl_analytic",
    "weighted_score", "limit_terminal", "ln_frozen", "ams_raw", "method",
)  # fmt: skip
"""Columns of the per-member flags matrix (int64 ``[K, len(F_NAMES)]``)."""
(
    F_KAPPA_POS, F_MOM_ONLY, F_POLYAK, F_PRE_SQUASH, F_CRITIC_ACTOR, F_KL_ANALYTIC,
    F_WEIGHTED, F_LIMIT_TERMINAL, F_LN_FROZEN, F_AMS_RAW, F_METHOD,
) = range(len(F_NAMES))  # fmt: skip

METHOD_CODES = {("ppo", "derived"): 0, ("ppo", "printed"): 0, ("rb", "derived"): 1,
                ("rb", "printed"): 1, ("rpe", "derived"): 2, ("rpe", "printed"): 3,
                ("spo", "derived"): 4, ("spo", "printed"): 4}  # fmt: skip
"""Surrogate code of (method, rpe_form)."""

ACTIVATIONS = {"swish": 0, "relu": 1, "tanh": 2}
"""Code of each activation (``OnlineConfig.activation``)."""
HEADS = {"student_t": 0, "normal": 1}
"""Code of each policy head (``OnlineConfig.policy``)."""

# entries of a layout's geometry vector (int64 [10]; FusedEngine.__init__ writes it)
G_OBS, G_UNITS, G_RAW, G_OUT_W, G_OUT_B, G_LN, G_ACT, G_HEAD, G_ACT_DIM, G_LAYERS = range(10)
