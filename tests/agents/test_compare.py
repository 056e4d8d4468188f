"""``bimp compare`` says when the records it pairs come from more than one code version: a note naming them per arm,
first in its report and in its --json, and nothing when they come from one."""

import json
import shutil

import pytest

from bimp.agents.commands import compare
from bimp.agents.evaluation.evaluate import evaluate
from bimp.agents.evaluation.metrics import code_version
from bimp.agents.evaluation.records import EPISODES_FILE, read_records

OTHER = "f" * 40  # another commit


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    out = tmp_path_factory.mktemp("compare") / "base"
    evaluate(out=out, scenarios=["emergency-brake"], policies=["lane-keep", "zero"], episodes=2, seed=5, workers=1,
             traces=0, progress=False)
    return out


def _recommit(folder, to, label=None, seeds=None):
    """Rewrite the records of ``label`` (every one when None) on ``seeds`` (all when None) as made by commit ``to``,
    with uncommitted changes."""
    lines = []
    for r in read_records(folder):
        if (label is None or r["policy"] == label) and (seeds is None or r["seed"] in seeds):
            r.update(git_commit=to, git_dirty=True)
        lines.append(json.dumps(r) + "\n")
    (folder / EPISODES_FILE).write_text("".join(lines))


def _run(capsys, *argv):
    assert compare.main([*argv, "--policies", "lane-keep", "zero"]) == 0
    return capsys.readouterr().out


def test_records_of_one_code_version_get_no_note(folder, tmp_path, capsys):
    out = _run(capsys, str(folder), "--json", str(tmp_path / "c.json"))
    assert "code version" not in out and out.startswith("## emergency-brake")
    kept = json.loads((tmp_path / "c.json").read_text())
    (version,) = {code_version(r) for r in read_records(folder)}
    assert kept["code_versions"] == {"A": {version: 2}, "B": {version: 2}, "note": None}
    assert kept["emergency-brake"]["seeds"] == [5, 6]  # the scenarios are where they were


def test_two_folders_made_by_different_code_are_noted_naming_the_versions(folder, tmp_path, capsys):
    other = tmp_path / "other"
    shutil.copytree(folder, other)
    _recommit(other, OTHER)
    (mine,) = {code_version(r) for r in read_records(folder)}
    out = _run(capsys, str(folder), str(other), "--json", str(tmp_path / "c.json"))
    note = out.splitlines()[0]
    shown = mine[:7] + mine[40:] if len(mine) >= 40 else mine
    assert note == (f"note: the paired records come from 2 code versions: A (lane-keep) {shown} (2 episodes); "
                    "B (zero) fffffff+dirty (2 episodes); a difference may be the code's")
    assert out.count("code versions") == 1 and "## emergency-brake" in out
    kept = json.loads((tmp_path / "c.json").read_text())
    assert kept["code_versions"] == {"A": {mine: 2}, "B": {f"{OTHER}+dirty": 2}, "note": note}


def test_an_arm_resumed_under_another_code_version_is_noted(folder, tmp_path, capsys):
    out_dir = tmp_path / "resumed"
    shutil.copytree(folder, out_dir)
    _recommit(out_dir, OTHER, label="lane-keep", seeds={6})
    out = _run(capsys, str(out_dir))
    assert out.startswith("note: the paired records come from 2 code versions: A (lane-keep) ")
    assert "fffffff+dirty (1 episode)" in out.splitlines()[0]


def test_only_the_paired_records_count(folder, tmp_path, capsys):
    """A record without a partner is not compared: its code version is not the comparison's."""
    out_dir = tmp_path / "unpaired"
    shutil.copytree(folder, out_dir)
    lines = [r for r in read_records(out_dir) if not (r["policy"] == "zero" and r["seed"] == 6)]
    (out_dir / EPISODES_FILE).write_text("".join(json.dumps(r) + "\n" for r in lines))
    _recommit(out_dir, OTHER, label="lane-keep", seeds={6})
    assert "code versions" not in _run(capsys, str(out_dir))
