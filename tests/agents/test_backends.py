"""Where episodes run (``bimp.agents.evaluation.backends``): the local pool and Ray run the same groups with the same
records.

The Ray tests are slow (``-m slow``) and need the extra (``pip install -e ".[ray]"``); the fast ones check that a
bad backend request fails before anything runs, with Ray or without it."""

import os
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import pytest

from bimp.agents.cli import EvaluationError
from bimp.agents.commands import evaluate as ev
from bimp.agents.evaluation.backends import THREADS, BackendError, connect_ray
from bimp.agents.evaluation.evaluate import evaluate
from bimp.agents.evaluation.records import read_records
from bimp.agents.rollout import one_thread
from tests.agents.test_evaluate import ARGS, FAULTY, deadline

TIMING = {"plan_time_ms_p50", "plan_time_ms_p95"}  # wall-clock: the only metrics allowed to differ


# The observations MPPI acts on over its first 6 steps of lane-drop-hard seed 3001, as hashes: "loop" through the
# episode loop, "bare" by the same steps outside it. On two BLAS threads MPPI's action 3 parts from one thread's.
OBSERVATIONS = """
import hashlib, sys
import gymnasium as gym
import numpy as np
import bimp
from bimp.agents.rollout import episode_seeds, rollout
env = gym.make("bimp/lane-drop-hard-v0")
policy = bimp.make_policy("mppi", env)
seen = []
if sys.argv[1] == "loop":
    rollout(env, policy, 3001, max_steps=6, observations=seen)
else:
    env_seed, policy_seed = episode_seeds(3001)
    obs, _ = env.reset(seed=env_seed)
    policy.reset(policy_seed)
    for _ in range(6):
        seen.append(obs)
        obs, *_ = env.step(policy.act(obs))
print(" ".join(hashlib.sha1(np.asarray(o).tobytes()).hexdigest() for o in seen))
"""


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="one core: every BLAS runs one thread anyway")
def test_the_episode_loop_in_process_gives_a_workers_episode(tmp_path):
    """The episode loop runs on one BLAS and torch thread (one_thread) in the command's own process (``--workers
    1``, ``bimp render``), as a pool worker does: the same episode, whatever cores the machine has. The control (the
    same steps outside the loop, this process's threads) shows that the threads do change it here."""
    script = tmp_path / "observations.py"
    script.write_text(OBSERVATIONS)
    own = {k: v for k, v in os.environ.items() if k not in THREADS}  # an earlier pool may have set them here
    run = lambda env, mode: subprocess.run([sys.executable, str(script), mode], env=env, capture_output=True,  # noqa: E731
                                           text=True, timeout=600, check=True).stdout.split()
    worker = run({**own, **THREADS}, "bare")
    bare = run(own, "bare")
    if bare == worker:
        pytest.skip("this machine's BLAS gave one thread's floats on more: nothing to tell apart")
    assert len(worker) == 6 and run(own, "loop") == worker


def test_one_thread_limits_numpys_blas_and_restores_the_threads_it_found():
    import torch
    from threadpoolctl import threadpool_info

    before = torch.get_num_threads(), [pool["num_threads"] for pool in threadpool_info()]
    with one_thread():
        pools = threadpool_info()
        assert any(pool["internal_api"] == "openblas" for pool in pools)  # numpy's: an old threadpoolctl misses it
        assert torch.get_num_threads() == 1 and all(pool["num_threads"] == 1 for pool in pools)
    assert (torch.get_num_threads(), [pool["num_threads"] for pool in threadpool_info()]) == before


# JAX's CPU LAPACK loads scipy's own OpenBLAS the first time a planner solves, inside the episode: after
# one_thread's limit started, unless one_thread loads it first.
LATE_BLAS = """
import jax.numpy as jnp
from threadpoolctl import threadpool_info
from bimp.agents.rollout import one_thread
with one_thread():
    jnp.linalg.solve(jnp.eye(3) * 2.0, jnp.ones(3)).block_until_ready()
    print(max(pool["num_threads"] for pool in threadpool_info()), len(threadpool_info()))
"""


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one core: every library runs one thread anyway")
def test_one_thread_also_limits_the_blas_a_planners_first_solve_loads():
    own = {k: v for k, v in os.environ.items() if k not in THREADS}  # a fresh interpreter, BLAS at its defaults
    done = subprocess.run([sys.executable, "-c", LATE_BLAS], env=own, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    most, pools = map(int, done.stdout.split()[-2:])
    assert most == 1 and pools >= 2, done.stdout  # numpy's OpenBLAS and scipy's, both at one thread


@pytest.mark.parametrize("argv, message", [
    (["--backend", "dask"], "unknown backend 'dask'"),
    (["--address", "10.0.0.1:6379"], "not 'local'"),
    (["--backend", "ray", "--address", "localhost:6379", "--ray-cpus", "2"], "not with --address"),
])
def test_a_bad_backend_request_exits_before_anything_runs(tmp_path, capsys, argv, message):
    out = tmp_path / "out"
    assert ev.main(["--policy", "lane-keep", "--episodes", "1", *argv, "--out", str(out)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_ray_without_the_extra_names_the_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError, as without the extra
    with pytest.raises(EvaluationError, match=r'pip install -e "\.\[ray\]"'):
        evaluate(out=tmp_path / "out", backend="ray", **ARGS)
    assert not (tmp_path / "out").exists()


def test_an_address_where_no_cluster_answers_is_named_at_once(tmp_path):
    ray = pytest.importorskip("ray")
    if ray.is_initialized():
        pytest.skip("this process is already connected to a Ray instance")
    for address, message in (("127.0.0.1:1", "no Ray cluster answers"), ("headnode", "expected HOST:PORT")):
        with deadline(30), pytest.raises(BackendError, match=f"'{address}'.*{message}"):
            connect_ray(address)
    with pytest.raises(EvaluationError, match="127.0.0.1:1"):
        evaluate(out=tmp_path / "out", backend="ray", address="127.0.0.1:1", **ARGS)
    assert not (tmp_path / "out").exists() and not ray.is_initialized()


def test_tune_refuses_a_bad_backend_request_before_any_trial(tmp_path, monkeypatch, capsys):
    from bimp.agents.commands import tune as tune_command
    from bimp.agents.evaluation import tune

    argv = ["--policy", "lane-keep", "--scenario", "emergency-brake", "--trials", "1", "--episodes", "1"]
    for extra, message in ((["--parallel", "2"], "with --backend ray"), (["--backend", "dask"], "'dask'")):
        assert tune_command.main([*argv, *extra, "--out", str(tmp_path / "out")]) == 2
        assert message in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(tune.TuneError, match=r'pip install -e "\.\[ray\]"'):
        tune.tune("lane-keep", ["emergency-brake"], 1, 1, out=tmp_path / "out", backend="ray", progress=False)
    assert not (tmp_path / "out").exists()


# --- on a local Ray instance ------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ray_local():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


@pytest.mark.slow
def test_ray_gives_the_process_pools_per_seed_metrics(tmp_path, ray_local):
    args = {**ARGS, "policies": ["enkts", "lane-keep"], "episodes": 4, "traces": 0,
            "overrides": {"enkts": {"n_particles": 16, "problem.horizon": 8}}}
    with deadline(600):
        evaluate(out=tmp_path / "pool", **{**args, "workers": 2})
        evaluate(out=tmp_path / "ray", backend="ray", **args)
    per_seed = {}
    for name in ("pool", "ray"):
        records = read_records(tmp_path / name)
        assert len(records) == 8 and all(r["status"] == "ok" for r in records), [r.get("error") for r in records]
        per_seed[name] = {(r["label"], r["seed"]): (r["config_hash"], r["env_seed"], r["policy_seed"], r["steps"],
                                                    r["scenario_params"],
                                                    {k: v for k, v in r["metrics"].items() if k not in TIMING})
                          for r in records}
    assert per_seed["ray"] == per_seed["pool"]


@pytest.mark.slow
def test_a_killed_ray_worker_is_retried_not_lost(tmp_path, ray_local):
    flag = tmp_path / "died-once"
    with deadline(300):
        summary = evaluate(out=tmp_path / "once", backend="ray", **{
            **ARGS, "policies": [FAULTY], "overrides": {FAULTY: {"flag": str(flag), "mode": "die", "once": True}}})
    assert flag.exists()  # a worker did die
    e = summary[f"{FAULTY}/emergency-brake"]
    assert e["episodes"] == 3 and e["errors"] == 0  # retried, not lost
    assert sorted(r["seed"] for r in read_records(tmp_path / "once")) == [5, 6, 7]  # each recorded once


@pytest.mark.slow
def test_a_ray_worker_that_always_dies_is_recorded_and_the_rest_runs(tmp_path, ray_local):
    with deadline(300):
        summary = evaluate(out=tmp_path, backend="ray", **{
            **ARGS, "policies": ["lane-keep", FAULTY], "episodes": 2,
            "overrides": {FAULTY: {"flag": str(tmp_path / "never"), "mode": "die"}}})
    assert summary["lane-keep/emergency-brake"]["episodes"] == 2
    e = summary[f"{FAULTY}/emergency-brake"]
    assert e["errors"] == 2 and e["episodes"] == 0
    errors = [r["error"] for r in read_records(tmp_path) if r["status"] == "error"]
    assert len(errors) == 2 and all(err.startswith("WorkerDied: WorkerCrashedError") for err in errors)


@pytest.mark.slow
def test_tune_on_ray_runs_the_trials_in_parallel_against_one_study(tmp_path, ray_local):
    import optuna

    from bimp.agents.evaluation.tune import tune

    args = dict(scenarios=["emergency-brake"], episodes=2, out=tmp_path / "study", progress=False, backend="ray")
    with deadline(600):
        study = tune("lane-keep", trials=5, parallel=2, **args)
    trials = study.get_trials(deepcopy=False)
    assert len(trials) == 5 and {t.state for t in trials} == {optuna.trial.TrialState.COMPLETE}  # the exact budget
    assert len({t.params["k_speed"] for t in trials}) == 5  # two workers, two sampler seeds: no repeated draws
    assert (tmp_path / "study" / "best.yaml").is_file()
    starts = sorted((t.datetime_start, t.datetime_complete) for t in trials)
    assert any(b[0] < a[1] for a, b in zip(starts, starts[1:]))  # some trials overlapped: in parallel
    with deadline(600):
        assert len(tune("lane-keep", trials=5, **args).trials) == 5  # a finished study runs nothing more
        assert len(tune("lane-keep", trials=6, parallel=2, **args).trials) == 6  # one more, not two


class ScriptedPool:
    """A stand-in for the process pool, with no processes and no clock: its groups finish only when ``run_local``
    waits (``backends.wait`` is patched to :meth:`wait`), so what it has started by then is what ran together. A
    group ``("die", ...)`` in flight then breaks the pool, failing everything in flight in it as a dead worker does;
    else the first ``("ok",)`` in flight returns ``[group]``. With ``at_submit`` a dying group breaks the pool as it
    is submitted, before anything else can start beside it (a worker that dies at once, or a loaded machine where
    ``run_local`` is descheduled between two submits: the next submit raises ``BrokenProcessPool``). Records how many
    groups were in flight beside each one submitted.

    (It once broke the pool on a 10 ms timer after the submit and assumed the next submit came within those 10 ms:
    under heavy load it did not, and the log, not the code, was wrong.)"""

    log: list = []
    at_submit = False
    current = None

    def __init__(self, workers, **_):
        self.pending, self.broken = [], False
        ScriptedPool.current = self

    def submit(self, run, group):
        from concurrent.futures import Future
        from concurrent.futures.process import BrokenProcessPool

        if self.broken:
            raise BrokenProcessPool("broken")
        future = Future()
        self.log.append((group, sum(not f.done() for f, _ in self.pending)))
        self.pending.append((future, group))
        if self.at_submit and group[0] == "die":
            self._break()
        return future

    def _break(self):
        from concurrent.futures.process import BrokenProcessPool

        self.broken = True
        for f, _ in self.pending:
            if not f.done():
                f.set_exception(BrokenProcessPool("a worker died"))

    @classmethod
    def wait(cls, futures, return_when):
        pool, futures = cls.current, list(futures)
        running = [(f, group) for f, group in pool.pending if not f.done()]
        if any(group[0] == "die" for _, group in running):
            pool._break()
        elif running:
            future, group = running[0]
            future.set_result([group])
        done = {f for f in futures if f.done()}
        assert done, "run_local waits on futures that are not this pool's"
        return done, set(futures) - done

    def shutdown(self, wait=True, cancel_futures=False):
        pass


die, innocent, die_later = ("die", 0), ("ok",), ("die", 2)


@pytest.mark.parametrize("at_submit, log", [
    # the first two ran together; after the crash each ran alone, in the order given, then die_later alone
    (False, [(die, 0), (innocent, 1), (die, 0), (innocent, 0), (die_later, 0), (die_later, 0)]),
    # die broke the pool before innocent could start (its submit raised: innocent stayed queued); die reran alone;
    # then innocent ran with die_later, was killed by it, and reran alone before die_later did
    (True, [(die, 0), (die, 0), (innocent, 0), (die_later, 1), (innocent, 0), (die_later, 0)]),
], ids=["dies-in-company", "dies-at-once"])
def test_a_suspect_rerun_alone_has_no_company_that_could_kill_it(monkeypatch, at_submit, log):
    """After a crash each group then in flight reruns alone. The last of them once had the next queued group
    started beside it, and a group that dies then took the innocent one down, recorded as dying twice."""
    from bimp.agents.evaluation import backends

    monkeypatch.setattr(backends, "ProcessPoolExecutor", ScriptedPool)
    monkeypatch.setattr(backends, "wait", ScriptedPool.wait)
    monkeypatch.setattr(ScriptedPool, "log", [])
    monkeypatch.setattr(ScriptedPool, "at_submit", at_submit)
    written = []
    with deadline(60):
        backends.run_local([die, innocent, die_later], 2, None, lambda group, why: [("crashed", group)],
                           written.append)
    assert written == [("crashed", die), innocent, ("crashed", die_later)]
    assert ScriptedPool.log == log


# --- workers die with their parent --------------------------------------------------------------------------------
ROOT = Path(__file__).resolve().parents[2]
DRIVER = """import os, sys, time
from pathlib import Path


def nap(started):
    (Path(started) / str(os.getpid())).touch()  # this worker is up, past its initializer, running a group
    time.sleep(120)
    return []


if __name__ == "__main__":
    from bimp.agents.evaluation.backends import run_groups

    ray = sys.argv[2] == "ray"
    run_groups([sys.argv[1]] * 4, nap, None, print, backend=sys.argv[2], workers=2, cpus=2 if ray else None)
"""


def _stat(pid: int) -> list[str]:
    """``/proc/PID/stat`` after the command name: state, parent pid, ...; empty once the process is gone."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    except OSError:
        return []


def _alive(pid: int) -> bool:
    return _stat(pid)[:1] not in ([], ["Z"])  # a zombie is dead, only not yet reaped by its new parent


def _descendants(pid: int) -> set[int]:
    parents = {int(d.name): _stat(int(d.name))[1:2] for d in Path("/proc").iterdir() if d.name.isdigit()}
    found, more = set(), {pid}
    while more:
        more = {child for child, parent in parents.items() if parent and int(parent[0]) in more} - found
        found |= more
    return found


def _within(seconds: float, condition) -> bool:
    end = time.monotonic() + seconds
    while not condition():
        if time.monotonic() > end:
            return False
        time.sleep(0.1)
    return True


def _left(pids: set[int]) -> list[str]:
    return [Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()[:120] for pid in pids
            if _alive(pid)]


@contextmanager
def busy_driver(tmp_path, backend: str):
    """A driver process of ``run_groups`` on ``backend`` whose groups sleep two minutes, once two workers run one:
    yields the driver's ``Popen``, those workers' pids, and every process then descended from the driver. Whatever
    of them is left afterwards is killed: a failed test leaves nothing behind."""
    (tmp_path / "driver.py").write_text(DRIVER)
    started = tmp_path / "started"
    started.mkdir()
    driver = subprocess.Popen([sys.executable, str(tmp_path / "driver.py"), str(started), backend],
                              env={**os.environ, "PYTHONPATH": str(ROOT)})
    descendants: set[int] = set()
    try:
        assert _within(120, lambda: len(list(started.iterdir())) == 2), "the two workers never started"
        descendants = _descendants(driver.pid)
        yield driver, {int(p.name) for p in started.iterdir()}, descendants
    finally:
        driver.kill()
        driver.wait()
        for pid in filter(_alive, descendants):
            os.kill(pid, signal.SIGKILL)


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="finds the workers through /proc")
def test_the_pool_workers_die_with_their_parent(tmp_path):
    """A SIGKILLed ``bimp evaluate --workers 2`` left both workers (about 860 MB each) and multiprocessing's
    resource tracker running under PID 1. Once both workers run a group, their parent is killed: every process it
    had started must be gone within 10 s."""
    with busy_driver(tmp_path, "local") as (driver, workers, descendants):
        assert workers < descendants  # and the resource tracker
        driver.kill()
        driver.wait()
        assert _within(10, lambda: not any(map(_alive, descendants))), _left(descendants)


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="finds the workers through /proc")
def test_ray_task_workers_die_with_their_driver(tmp_path):
    """A driver that started its own Ray instance is killed while two tasks run: their workers go within seconds
    (as do the GCS and the raylet; the raylet's two agent processes take about a minute, docs/scaling.md)."""
    pytest.importorskip("ray")
    with busy_driver(tmp_path, "ray") as (driver, workers, descendants):
        assert workers < descendants
        driver.kill()
        driver.wait()
        assert _within(15, lambda: not any(map(_alive, workers))), _left(workers)


ORPHAN = """import os, sys, time
from pathlib import Path

from bimp.agents.evaluation import backends

if os.fork() == 0:
    sys.platform = "other"  # as where there is no prctl: the fallback looks at its parent pid every second
    backends.die_with(os.getppid())
    Path(sys.argv[1]).write_text(str(os.getpid()))
    time.sleep(60)
    os._exit(0)
time.sleep(60)
"""


@pytest.mark.skipif(not hasattr(os, "fork") or not Path("/proc/self/stat").exists(), reason="forks, reads /proc")
def test_without_prctl_a_worker_sees_its_parent_die_and_exits(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    # a parent already gone when the worker starts (no process is its own parent): exit at once, quietly
    code = "import os; from bimp.agents.evaluation.backends import die_with; die_with(os.getpid()); print('alive')"
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert (run.returncode, run.stdout, run.stderr) == (1, "", "")
    child = tmp_path / "child"
    parent = subprocess.Popen([sys.executable, "-c", ORPHAN, str(child)], env=env)
    pid = None
    try:
        assert _within(30, lambda: child.exists() and child.read_text()), "the child never started"
        pid = int(child.read_text())
        parent.kill()
        parent.wait()
        assert _within(5, lambda: not _alive(pid))
    finally:
        parent.kill()
        parent.wait()
        if pid and _alive(pid):
            os.kill(pid, signal.SIGKILL)
