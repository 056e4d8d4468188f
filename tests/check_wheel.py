"""``make check-wheel``: the built wheel, installed into a fresh virtualenv beside PyPI's ``envs`` package, leaves
both importable, installs nothing but ``bimp``, and its ``bimp`` command runs. Run by that virtualenv's Python
from outside the checkout (so the checkout's folders cannot stand in for the installed ones)."""

import importlib
import subprocess
import sys
import tempfile
from importlib import metadata
from pathlib import Path

site = Path(metadata.distribution("bimp").locate_file(""))
tops = sorted({f.parts[0] for f in metadata.files("bimp") if f.parts[0] != ".."})  # ..: the bin/bimp script
assert tops == ["bimp", f"bimp-{metadata.version('bimp')}.dist-info"], f"the wheel installs {tops}"

other = importlib.import_module("envs")  # PyPI's envs (environment variables), not ours
assert Path(other.__file__).parent == site / "envs", other.__file__
assert hasattr(other, "Env") and not hasattr(other, "ENV_IDS"), dir(other)
import gymnasium as gym  # noqa: E402

import bimp  # noqa: E402
import bimp.envs  # noqa: E402

assert Path(bimp.envs.__file__).parent == site / "bimp" / "envs", bimp.envs.__file__
env = gym.make("bimp/EmergencyBrake-v0")
obs, _ = env.reset(seed=0)
policy = bimp.make_policy("ppo", env)  # the shipped model and its defaults.json are package data
assert env.action_space.contains(policy.act(obs))

with tempfile.TemporaryDirectory() as out:
    cli = Path(sys.executable).parent / "bimp"
    run = subprocess.run([str(cli), "evaluate", "--scenario", "emergency-brake", "--policy", "zero", "--episodes",
                          "1", "--workers", "1", "--out", out], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    assert (Path(out) / "episodes.jsonl").is_file()
print(f"check-wheel: ok: the wheel installs {tops}; `import envs` is {other.__file__}, "
      f"`import bimp.envs` is {bimp.envs.__file__}; `bimp evaluate` ran from the wheel")
