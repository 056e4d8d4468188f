"""bimp: Bayesian inferential motion planning (EnKTS, EnKS and their peers) as Gymnasium agents on highway-env.

Importing ``bimp`` registers its environments with Gymnasium::

    import gymnasium as gym
    import bimp

    env = gym.make("bimp/Overtaking-v0")
    policy = bimp.make_policy("enkts", env)

A new policy or scenario is one module plus one table entry: ``bimp.register_policy(bimp.PolicySpec(...))``,
``bimp.register_scenario(bimp.ScenarioSpec(...))``.

The subpackages: :mod:`bimp.envs` (scenarios), :mod:`bimp.planners` (EnKTS/EnKS, MPPI, NMPC, the vehicle model),
:mod:`bimp.agents` (the policy table, evaluation and the ``bimp`` command), :mod:`bimp.configs` (frozen configs).
"""

from importlib import metadata

from bimp import envs  # noqa: F401  (registers the bimp/... ids)
from bimp.agents.registry import PolicySpec, make_policy, register_policy
from bimp.envs import ScenarioSpec, register_scenario

try:
    __version__ = metadata.version("bimp")
except metadata.PackageNotFoundError:  # a source tree put on sys.path by hand, not installed
    __version__ = "0+unknown"

__all__ = ["PolicySpec", "ScenarioSpec", "__version__", "make_policy", "register_policy", "register_scenario"]
