"""Location-free provenance (issue 28, item 1): no committed file names a folder of the machine it was made on, and a
record made in one checkout resumes from a copy of the project at another path."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

from bimp import envs
from bimp.agents.cli import main
from bimp.agents.evaluation.evaluate import resolve_arms
from bimp.agents.registry import POLICIES

ROOT = Path(__file__).resolve().parent.parent
# A home, work or temporary folder of a machine (Linux, macOS), or this checkout's own path. Not preceded by a word
# character or a slash, so a URL's path (https://host/home/...) is not one.
MACHINE_PATH = re.compile(rb"(?<![\w./~-])/(work|root|home|tmp|Users)/|" + re.escape(str(ROOT).encode()))
# A Windows drive (C:\...), in text files only: compressed bytes (a PNG) hold such a pair by chance.
DRIVE_PATH = re.compile(rb"(?<!\w)[A-Za-z]:\\{1,2}\w")
# Tracked text files outside results/ where an absolute path is the point, each with why. None is needed today:
# docs/scaling.md's NFS mount (/mnt/nfs/...) and tests/conftest.py's XDG_RUNTIME_DIR (/tmp, no trailing slash) are
# not machine folders in the sense above.
ALLOWED: dict[str, str] = {}


def tracked(*pathspec: str) -> list[str]:
    out = subprocess.run(["git", "ls-files", "-z", *pathspec], cwd=ROOT, capture_output=True, check=True)
    return [p for p in out.stdout.decode().split("\0") if p and (ROOT / p).is_file()]


def machine_paths(paths: list[str], binary: bool) -> list[str]:
    """``file:line: excerpt`` of each line with a machine's path (at most 3 per file, then a count);
    ``binary``: search files with NUL bytes too (their "lines" are then only approximate)."""
    found = []
    for path in paths:
        data = (ROOT / path).read_bytes()
        text = b"\0" not in data
        if not (text or binary):
            continue
        hits = [(n, m) for n, line in enumerate(data.split(b"\n"), 1)
                if (m := MACHINE_PATH.search(line) or (text and DRIVE_PATH.search(line)))]
        for n, m in hits[:3]:
            excerpt = m.string[max(0, m.start() - 40):m.end() + 60].decode(errors="replace")
            found.append(f"{path}:{n}: ...{excerpt}...")
        if len(hits) > 3:
            found.append(f"{path}: and {len(hits) - 3} more line(s)")
    return found


def test_no_committed_result_names_a_folder_of_the_machine_it_was_made_on():
    paths = tracked("results")
    assert paths, "git ls-files results found nothing"
    found = machine_paths(paths, binary=True)  # the Optuna studies (SQLite) too
    assert not found, "absolute paths in committed results:\n" + "\n".join(found)


def test_no_other_tracked_text_file_names_a_folder_of_a_machine():
    paths = [p for p in tracked() if not p.startswith("results/") and p not in ALLOWED]
    found = machine_paths(paths, binary=False)
    assert not found, "absolute paths in tracked files:\n" + "\n".join(found)


def test_no_resolved_config_names_the_checkout():
    # What a record's config and hash are made of, for every registered policy on every scenario.
    # idm drives highway-env's own roads only (it is highway-env's driver, through bimp.envs.wrap)
    arms = [*resolve_arms(envs.default_scenarios(), sorted(set(POLICIES) - {"idm"})),
            *resolve_arms(["highway-fast-v0"], ["idm", "enkts", "mppi", "lane-keep"])]
    for arm in arms:
        assert not MACHINE_PATH.search(arm.config.encode()), (arm.scenario, arm.label, arm.config)


def test_a_record_made_here_resumes_from_a_copy_of_the_project_at_another_path(tmp_path):
    args = ["evaluate", "--policy", "ppo", "--scenario", "emergency-brake", "--episodes", "1", "--seed", "1000",
            "--traces", "0", "--workers", "1"]
    made = tmp_path / "made"
    assert main([*args, "--out", str(made)]) == 0
    # The project copied elsewhere in the layout it installs as (bimp/{envs,agents,...}), run by its own code.
    copy = tmp_path / "elsewhere" / "project"
    (copy / "bimp").mkdir(parents=True)
    shutil.copy(ROOT / "bimp" / "__init__.py", copy / "bimp")
    for name in ("envs", "agents", "planners", "configs"):
        shutil.copytree(ROOT / name, copy / "bimp" / name, ignore=shutil.ignore_patterns("__pycache__"))
    resumed = tmp_path / "elsewhere" / "made"
    shutil.copytree(made, resumed)
    records = (resumed / "episodes.jsonl").read_bytes()
    code = ("import sys, bimp.agents.cli as cli\n"
            "assert cli.__file__.startswith(sys.argv[1]), cli.__file__\n"
            "raise SystemExit(cli.main(sys.argv[2:]))")
    run = subprocess.run([sys.executable, "-c", code, str(copy), *args, "--out", str(resumed)], cwd=copy,
                         env={**os.environ, "PYTHONPATH": str(copy)}, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    assert (resumed / "episodes.jsonl").read_bytes() == records, "the copy ran the episode again"
