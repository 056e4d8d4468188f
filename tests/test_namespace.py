"""One import namespace (``bimp.*``): nothing installs or imports a top-level ``envs``, ``agents``, ``configs`` or
``planners``, each also the name of another package on PyPI."""

import ast
import json
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
OLD = ("envs", "agents", "planners", "configs")


def _python_files() -> list[Path]:
    return [p for folder in (*OLD, "bimp", "tests", "benchmarks") for p in (ROOT / folder).rglob("*.py")]


@pytest.mark.parametrize("path", _python_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_module_imports_an_old_top_level_name(path):
    # From the checkout the old names would still import (its root is on sys.path) and give second copies of
    # every module and class: only the installed namespace may be used.
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                 else [node.module or ""] if isinstance(node, ast.ImportFrom) and node.level == 0 else [])
        for name in names:
            assert name.split(".")[0] not in OLD, f"{path.name}:{node.lineno} imports {name}: use bimp.{name}"


def test_the_distribution_installs_only_the_bimp_namespace():
    # Asked from outside the checkout (-I, cwd /), whose folders would import and whose build leftovers
    # (bimp.egg-info) would be read as the installed distribution: a wheel's files, and the top-level names an
    # editable install's finder serves.
    code = ("import importlib.util, json; from importlib import metadata\n"
            "tops = sorted({f.parts[0] for f in metadata.files('bimp') if f.parts[0] != '..'})\n"
            f"print(json.dumps([tops, [n for n in {OLD!r} if importlib.util.find_spec(n)]]))")
    out = subprocess.run([sys.executable, "-I", "-c", code], cwd="/", capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    tops, importable = json.loads(out.stdout)
    assert "bimp-" + metadata.version("bimp") + ".dist-info" in tops, tops
    assert not set(tops) & set(OLD) and importable == [], (tops, importable)


def test_import_bimp_alone_registers_the_envs_and_exposes_the_api():
    code = ("import gymnasium as gym, sys, bimp\n"
            "env = gym.make('bimp/Overtaking-v0'); env.reset(seed=0)\n"
            "policy = bimp.make_policy('lane-keep', env); policy.act(env.reset(seed=0)[0])\n"
            "print(bimp.__version__, sorted(m for m in sys.modules if m.split('.')[0] in "
            f"{OLD!r}))\n")
    out = subprocess.run([sys.executable, "-I", "-c", code], cwd="/", capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    version, loaded = out.stdout.split(" ", 1)
    assert version == metadata.version("bimp")
    assert loaded.strip() == "[]", f"old top-level modules loaded: {loaded}"
