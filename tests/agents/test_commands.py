"""The command line's layout: each ``bimp`` command is one module of ``bimp.agents.commands`` with its ``main``;
argparse lives there and in the dispatcher only, and the library never imports either."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

from bimp.agents.cli import COMMANDS, command_module

ROOT = Path(__file__).resolve().parents[2]
LIBRARY = [p for folder in ("agents", "envs", "planners", "configs") for p in sorted((ROOT / folder).rglob("*.py"))
           if "commands" not in p.relative_to(ROOT).parts and p != ROOT / "agents" / "cli.py"]


@pytest.mark.parametrize("name", list(COMMANDS))
def test_every_command_is_a_module_with_its_main(name):
    module = importlib.import_module(command_module(name))
    assert callable(module.main) and module.__doc__


def test_no_library_module_parses_arguments_or_imports_the_command_line():
    assert len(LIBRARY) > 50
    offenders = [str(p.relative_to(ROOT)) for p in LIBRARY
                 if re.search(r"^\s*(import argparse|from argparse import|from bimp\.agents\.(cli|commands)\b"
                              r"|import bimp\.agents\.(cli|commands)\b|from bimp\.agents import .*\b(cli|commands)\b)",
                              p.read_text(), re.M)]
    assert offenders == []
