"""Everything that acts through the one :class:`Policy` protocol, plus training and evaluation."""

from bimp.agents.policy import Policy
from bimp.agents.registry import POLICIES, make_policy

__all__ = ["POLICIES", "Policy", "make_policy"]
