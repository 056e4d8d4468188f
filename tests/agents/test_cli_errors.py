"""Every file-system and file-content error is one line and exit 2, and writes nothing (issue 24, item 5): a config
file that is not YAML, ``--out`` at a file, under a file, where no folder can be made, or empty, a negative seed, an
input folder that cannot be read."""

import pathlib

import pytest

from bimp.agents.cli import main

EB = ["--scenario", "emergency-brake", "--episodes", "1"]
COMMANDS = {  # each cheap, and refused before its first episode
    "evaluate": ["evaluate", "--policy", "zero", *EB, "--workers", "1"],
    "sweep": ["sweep", "--param", "lane-keep.k_lat=0.004", *EB],
    "frontier": ["frontier", "--policies", "zero", *EB],
    "tune": ["tune", "--policy", "lane-keep", *EB, "--trials", "1"],
    "render": ["render", "--policy", "zero", "--scenario", "emergency-brake"],
    "plot": ["plot", "."],
}


def one_line_error(capsys, *named: str) -> str:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err and "error:" in err, err
    assert all(name in err for name in named), err
    return err


def tree(path: pathlib.Path) -> list:
    return sorted(str(p.relative_to(path)) for p in path.rglob("*"))


PLACES = ["at a file", "under a file", "empty", "cannot be made"]


# plot makes its folder only when there is something to draw: not here
@pytest.mark.parametrize("command, where", [(c, w) for w in PLACES for c in COMMANDS
                                            if (c, w) != ("plot", "cannot be made")])
def test_a_bad_out_exits_2_in_one_line_and_writes_nothing(tmp_path, monkeypatch, capsys, command, where):
    work = tmp_path / "work"
    work.mkdir()
    (work / "afile").write_text("mine\n")
    monkeypatch.chdir(work)  # --out "" would write here
    if where == "cannot be made":  # a read-only parent, as root (which ignores permissions) cannot make one
        real = pathlib.Path.mkdir

        def refuse(self, *args, **kwargs):
            if "locked" in self.parts:
                raise PermissionError(13, "Permission denied", str(self))
            return real(self, *args, **kwargs)

        monkeypatch.setattr(pathlib.Path, "mkdir", refuse)
    out = {"at a file": "afile", "under a file": "afile/sub", "empty": "", "cannot be made": "locked/out"}[where]
    assert main([*COMMANDS[command], "--out", out]) == 2
    one_line_error(capsys, "--out", out)
    assert tree(work) == ["afile"] and (work / "afile").read_text() == "mine\n"


@pytest.mark.parametrize("content, why", [
    (b"horizon: [20\n", "line 2, column 1: not valid YAML"),
    (b"!!python/object/apply:os.system ['touch MARK']\n", "could not determine a constructor"),
    (bytes(range(256)), "not a UTF-8 text file"),
], ids=["malformed", "tagged", "binary"])
@pytest.mark.parametrize("command", ["evaluate", "render"])
def test_a_config_file_that_is_not_yaml_exits_2_naming_it(tmp_path, monkeypatch, capsys, content, why, command):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "odd.yaml").write_bytes(content)
    argv = {"evaluate": ["evaluate", *EB, "--workers", "1"], "render": ["render", "--scenario", "emergency-brake"]}
    assert main([*argv[command], "--policy", "enkts", "--set", "enkts.config=odd.yaml", "--out", "out"]) == 2
    assert "<unicode string>" not in one_line_error(capsys, "odd.yaml", why)
    assert tree(tmp_path) == ["odd.yaml"]  # no out, no MARK


def test_render_refuses_a_negative_seed(tmp_path, capsys):
    assert main(["render", "--policy", "zero", "--seed", "-1", "--out", str(tmp_path / "out")]) == 2
    one_line_error(capsys, "seed", "-1")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv", [["compare", "{d}", "--policies", "a", "b"],
                                  ["aggregate", "{d}", "--runs", "a", "b", "--name", "x"], ["plot", "{d}"]],
                         ids=["compare", "aggregate", "plot"])
def test_an_unreadable_records_file_exits_2_naming_it(tmp_path, capsys, argv):
    (tmp_path / "episodes.jsonl").mkdir()  # there, but not a file
    assert main([a.format(d=tmp_path) for a in argv]) == 2
    one_line_error(capsys, "episodes.jsonl")
    assert tree(tmp_path) == ["episodes.jsonl"]


def test_compare_json_that_cannot_be_written_exits_2(tmp_path, capsys):
    from bimp.agents.evaluation.evaluate import evaluate

    evaluate(["emergency-brake"], ["zero", "lane-keep"], episodes=1, seed=5, workers=1, out=tmp_path, traces=0,
             progress=False)
    assert main(["compare", str(tmp_path), "--policies", "zero", "lane-keep", "--json", str(tmp_path)]) == 2
    one_line_error(capsys, "--json", str(tmp_path))


@pytest.mark.parametrize("command", [["demo", "--policy", "zero", "--episodes", "1"], ["bench", "--quick"]])
def test_demo_and_bench_refuse_a_bad_out_before_running(tmp_path, monkeypatch, capsys, command):
    """demo tracebacked on a refused request; bench checked its --out only after minutes of timing (review)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("mine\n")
    out = "afile" if command[0] == "demo" else "afile/result.json"
    assert main([*command, "--out", out]) == 2
    one_line_error(capsys, "--out", "afile")
    assert tree(tmp_path) == ["afile"]


@pytest.mark.parametrize("config, out, named", [
    (b"timesteps: [1\n", None, "not valid YAML"),
    (b"- 1\n- 2\n", None, "expected a mapping"),
    (None, None, "cannot be read"),
    (b"timesteps: 100\n", "afile", "is a file"),
    (b"timesteps: 100\n", "afile/sub", "under"),
    (b"n_stepz: 8\n", None, "n_stepz"),  # an unknown key, named
    (b"1: 8\n", None, "['1']"),  # a key YAML reads as no string, named as the others
    (b"gamma: 1.5\n", None, "gamma must be in (0, 1]"),
])
def test_train_rl_file_errors_exit_2_in_one_line(tmp_path, monkeypatch, capsys, config, out, named):
    """train-rl read its --config with a bare yaml.safe_load and never checked --out (review finding)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("mine\n")
    if config is not None:
        (tmp_path / "rl.yaml").write_bytes(config)
    command = ["train-rl", "--scenario", "overtaking", "--config", "rl.yaml", "--no-progress"]
    with pytest.raises(SystemExit) as exit_:
        main([*command, *(["--out", out] if out else ["--out", "run"])])
    assert exit_.value.code == 2
    one_line_error(capsys, named)
    assert sorted(tree(tmp_path)) == sorted(["afile"] + (["rl.yaml"] if config is not None else []))


def test_train_rl_refuses_two_algorithms(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "rl.yaml").write_text("algo: sac\n")
    with pytest.raises(SystemExit) as exit_:
        main(["train-rl", "--scenario", "overtaking", "--config", "rl.yaml", "--algo", "ppo", "--out", "run"])
    assert exit_.value.code == 2
    one_line_error(capsys, "algo: sac", "--algo is ppo")
    assert sorted(tree(tmp_path)) == ["rl.yaml"]


@pytest.mark.parametrize("backend", [["--backend", "bogus"], ["--ray-cpus", "2"]])
def test_a_dry_run_checks_the_backend_request_as_a_real_run(tmp_path, capsys, backend):
    """--dry-run skipped the backend checks: a request a real run refuses came out as fine (review finding)."""
    assert main([*COMMANDS["evaluate"], *backend, "--out", str(tmp_path / "out"), "--dry-run"]) == 2
    one_line_error(capsys, backend[0].lstrip("-"))
    assert tree(tmp_path) == []
