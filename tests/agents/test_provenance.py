"""bimp.agents.provenance: a run is dirty when the code differs from its commit, not when its results folder does."""

import subprocess

from bimp.agents.provenance import git_state


def test_a_changed_results_file_is_not_dirty_a_changed_code_file_is(tmp_path):
    git = lambda *a: subprocess.run(["git", *a], cwd=tmp_path, check=True, capture_output=True)  # noqa: E731
    git("init", "-q")
    (tmp_path / "planners").mkdir()
    (tmp_path / "results").mkdir()
    (tmp_path / "planners" / "core.py").write_text("x = 1\n")
    (tmp_path / "results" / "episodes.jsonl").write_text("{}\n")
    git("add", ".")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "start")
    commit, dirty = git_state(tmp_path)
    assert len(commit) == 40 and dirty is False
    (tmp_path / "results" / "episodes.jsonl").write_text("{}\n{}\n")  # a run appending to its tracked folder
    assert git_state(tmp_path) == (commit, False)
    (tmp_path / "planners" / "core.py").write_text("x = 2\n")
    assert git_state(tmp_path) == (commit, True)


def test_outside_a_checkout_there_is_no_state(tmp_path):
    assert git_state(tmp_path) == (None, None)


def test_a_package_inside_another_checkout_records_no_commit(tmp_path):
    """A wheel installed into a .venv inside some project's repository: that repository's commit is not ours."""
    subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True)
    subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "--allow-empty", "-m", "x"],
                   cwd=tmp_path, check=True)
    package = tmp_path / ".venv" / "lib" / "site-packages" / "bimp"
    package.mkdir(parents=True)
    assert git_state(tmp_path)[0] is not None and git_state(package) == (None, None)
