"""Everything that acts through the one :class:`Policy` protocol, plus training and evaluation."""

from bimp.agents.policy import Policy
from bimp.agents.registry import POLICIES, PolicySpec, make_policy, register_policy

__all__ = ["POLICIES", "Policy", "PolicySpec", "make_policy", "register_policy"]
