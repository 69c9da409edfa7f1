"""Networks: the paper's MLP, flat parameter views, the actor-critic both learners train,
and the policy heads with the map of their samples into the action bounds."""

from .actor_critic import FlatActorCritic
from .mlp import ACTIVATIONS, INITS, FlatMLP, flat_views, mlp, mlp_num_params
from .policies import HEAD_KINDS, ActionMap, NormalHead, PolicyHead, StudentTHead, make_head

__all__ = [
    "ACTIVATIONS",
    "HEAD_KINDS",
    "INITS",
    "ActionMap",
    "FlatActorCritic",
    "FlatMLP",
    "NormalHead",
    "PolicyHead",
    "StudentTHead",
    "flat_views",
    "make_head",
    "mlp",
    "mlp_num_params",
]
