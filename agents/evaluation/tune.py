"""A policy's config tuned by Optuna on training seeds, the same budget for every method (:func:`tune`; the
command ``bimp tune``: :mod:`bimp.agents.commands.tune`).

Search space. Each tunable policy's :class:`~bimp.agents.registry.PolicySpec` names a ``search_space`` function
beside its config: ``{key: optuna distribution}``, keys as its config names them (``temperature``;
``barrier.edge_margin`` in a nested config; ``sigma_du[1]`` one entry of a list; ``problem.sigma_barrier`` the shared
problem a peer planner's cost is built from). Every key is checked against the policy's resolved config, and the
policy built at the space's bounds, before any trial runs.

Trial. The sampled values replace those keys in the policy's resolved config; the trial is an ordinary evaluation
(:func:`bimp.agents.evaluation.evaluate.evaluate`) of that config on seeds ``seed .. seed + episodes - 1`` of every
scenario, in ``OUT/trials/<config hash>``, so a trial that is retried after an interruption resumes its episodes. It
runs in rungs of ``--rung`` seeds; after each the running objective is reported and the median pruner stops a trial that
trails the median of earlier trials at the same rung. Episodes that raise fail the trial with their error (a user
attribute ``error``), and the study goes on; so does a sampled config that the policy rejects. A new study's first trial
is not sampled: it is the config the policy ships with (its searched keys' values, those inside the space), so the best
config is never one that trails what users run on the study's own seeds.

Objective (maximized; ``--objective``): ``success`` (the default), the success rate over all episodes, ties broken
safety-first by the collision rate, then the off-road rate, then the share of steps over an input or rate bound:
``success - e (collision + e (offroad + e violation))`` with ``e = 1 / (n + 2)`` for ``n`` episodes, small enough
that no tie-break outweighs one success. ``score``: the mean closed-loop score (``docs/suite.md``: its gates zero an
at-fault collision, leaving the road or missing the env's goal; progress, time to collision, speed and comfort grade
the rest), for the suite's families: where there is no goal, waiting behind an obstacle succeeds and success no
longer tells plans apart; where there is one, the goal gate scores waiting 0.

Seeds. Tuning uses the training seeds (100-199 by convention, ``docs/evaluation.md``); seeds from 1000 on are the
safety, results and claims seeds and are refused.

Storage and resume. ``--storage`` is any Optuna RDB URL (default ``sqlite:///OUT/study.db``); several machines can
share one study through PostgreSQL or MySQL. The study's name holds the policy, scenarios, seeds and episodes, so a
different budget never mixes into it. ``--trials`` is the study's total: a rerun continues where it stopped;
a trial left running by a killed process is failed after its heartbeat lapses and retried with the same values,
the retry counting in its place.

Parallel trials. ``--backend ray [--address ADDR] [--parallel N]`` runs N trial workers on a Ray cluster, each
loading the study from the one storage and running its share of the remaining trials (their episodes in that
worker); the total stays ``--trials``. A cluster of several machines needs a shared storage (PostgreSQL, MySQL)
and ``--out`` on a disk every node sees (``docs/scaling.md``).
"""

from __future__ import annotations

import functools
import math
import warnings
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from bimp.agents.errors import EvaluationError, check_out_dir
from bimp.agents.evaluation.backends import BackendError, connect_ray, in_worker, ray_options, start_backend
from bimp.agents.evaluation.evaluate import evaluate
from bimp.agents.evaluation.provenance import config_hash
from bimp.agents.evaluation.records import read_records

# The search space and the config edits (their names re-exported here, where bimp sweep and the tests find them).
from bimp.agents.evaluation.tune_space import (  # noqa: F401  (re-exported: the names of `bimp tune`'s space)
    TuneError,
    check_space,
    factory_kwargs,
    get_value,
    overrides_for,
    search_space,
    set_value,
    shipped_params,
    suggest,
    with_params,
)
from bimp.agents.files import write_atomic
from bimp.configs import tuned_files

# optuna (a second or so to load) is imported inside the functions that run a study, as in tune_space: the config
# editing there (bimp sweep's) needs none of it.

RESULTS_SEEDS = 1000  # seeds from here on are reported, never tuned on


class TrialError(RuntimeError):
    """A trial whose episodes raised: the trial fails with this message and the study goes on."""


# --- the objective -------------------------------------------------------------------------------------------
OBJECTIVES = ("success", "score")


def objective_value(summary: dict, objective: str = "success") -> float:
    """``objective`` of :data:`OBJECTIVES` (see the module docstring): success first, then fewer collisions, off-road
    exits and bound violations; or the mean closed-loop score. ``summary`` as
    :func:`bimp.agents.evaluation.metrics.summarize` returns it. Rates and scores are pooled over the arms by
    episodes."""
    arms = [a for a in summary.values() if a["episodes"]]
    n = sum(a["episodes"] for a in arms)
    if not n:
        raise TrialError("no episode ran to its end")

    def rate(name: str) -> float:
        return sum(a[name]["mean"] * a["episodes"] for a in arms) / n

    if objective == "score":
        return rate("score")

    violation = (rate("input_violation_rate") + rate("rate_violation_rate")) / 2
    e = 1.0 / (n + 2)
    return rate("success_rate") - e * (rate("collision_rate") + e * (rate("offroad_rate") + e * violation))


def _trial_error(out: Path) -> str:
    errors = [r for r in read_records(out) if r["status"] != "ok"]
    first = errors[0]
    return f"{len(errors)} episode(s) raised; seed {first['seed']} on {first['scenario']}: {first.get('error')}"


# --- the study -------------------------------------------------------------------------------------------------
def study_name(policy: str, scenarios: list[str], episodes: int, seed: int) -> str:
    return f"{policy}:{'+'.join(scenarios)}:seeds{seed}-{seed + episodes - 1}"


def _storage(url: str):
    import optuna
    from optuna.storages import RetryHeartbeatStaleTrialCallback

    # Several processes may share a SQLite study (--backend ray on one machine): wait for a lock, do not fail.
    engine = {"connect_args": {"timeout": 60}} if url.startswith("sqlite") else None
    # The heartbeat lets a rerun (or another machine) fail a trial whose process died, and retry its values once.
    # Optuna flags the heartbeat as experimental (since 2.8); the warning says nothing to a user of bimp.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        return optuna.storages.RDBStorage(url, engine_kwargs=engine, heartbeat_interval=30, grace_period=90,
                                          heartbeat_stale_trial_callback=RetryHeartbeatStaleTrialCallback(1))


@dataclass(frozen=True)
class Study:
    """What a process needs to run trials of one study, wherever it runs (picklable: Ray sends it to workers)."""

    policy: str
    scenarios: tuple
    space: dict
    base: dict
    out: str  # absolute: the trials' evaluation folders, OUT/trials/<config hash>
    url: str
    name: str
    trials: int  # the study's total
    seeds: tuple
    rung: int
    batch: int
    workers: int
    startup_trials: int
    objective: str = "success"

    def load(self, sampler_seed: int):
        """The study from its storage (created the first time), with a TPE sampler seeded ``sampler_seed``."""
        import optuna

        return optuna.create_study(
            storage=_storage(self.url), study_name=self.name, load_if_exists=True, direction="maximize",
            sampler=optuna.samplers.TPESampler(seed=sampler_seed, n_startup_trials=self.startup_trials),
            pruner=optuna.pruners.MedianPruner(n_startup_trials=self.startup_trials))


FINISHED = ("COMPLETE", "PRUNED", "FAIL")


def _finished():
    import optuna

    return tuple(getattr(optuna.trial.TrialState, state) for state in FINISHED)


def _spent(study) -> int:
    """How many of the study's trials count against ``--trials``: the finished ones, less each trial that the
    heartbeat failed and retried with the same values (its retry, which lists it in the ``retry_history`` system
    attribute, is the one that counts). A killed process's trial must not cost the study one of its trials; a retry
    that dies too is not retried again (``RetryHeartbeatStaleTrialCallback(1)``), and the pair costs one."""
    trials = study.get_trials(deepcopy=False)
    retried = set().union(*(t.system_attrs.get("retry_history", ()) for t in trials))
    finished = _finished()
    return sum(t.state in finished and t.number not in retried for t in trials)


class _Budget:
    """A study callback that stops the study once :func:`_spent` reaches ``trials`` (optuna's ``MaxTrialsCallback``
    counts a retried trial's failure too, and ended a resumed study a trial short)."""

    def __init__(self, trials: int) -> None:
        self.trials = trials

    def __call__(self, study, trial) -> None:
        if _spent(study) >= self.trials:
            study.stop()


def objective(spec: Study, trial) -> float:
    """One trial: the sampled config evaluated on the study's seeds, in rungs (see the module docstring)."""
    import optuna

    params = {key: suggest(trial, key, dist) for key, dist in spec.space.items()}
    overrides = with_params(spec.base, params)  # complete: no default of the day (a tuned config) leaks in
    folder = Path(spec.out) / "trials" / config_hash(spec.policy, overrides)
    trial.set_user_attr("folder", str(folder.relative_to(spec.out)))  # relative to the study: no machine's path
    value, episodes = math.nan, len(spec.seeds)
    for done in range(spec.rung, episodes + spec.rung, spec.rung):
        try:
            summary = evaluate(list(spec.scenarios), [spec.policy], seeds=list(spec.seeds[:done]), out=folder,
                               traces=0, batch=spec.batch, workers=spec.workers,
                               overrides={spec.policy: overrides}, progress=False)
        except EvaluationError as err:
            trial.set_user_attr("error", str(err))
            raise TrialError(str(err)) from None
        if any(a["errors"] for a in summary.values()):
            message = _trial_error(folder)
            trial.set_user_attr("error", message)
            raise TrialError(message)
        value = objective_value(summary, spec.objective)
        trial.report(value, step=min(done, episodes))
        if done < episodes and trial.should_prune():
            raise optuna.TrialPruned()
    for name in ("success_rate", "collision_rate", "offroad_rate", "score"):
        trial.set_user_attr(name, {key: a[name]["mean"] for key, a in summary.items()})
    return value


def run_trials(spec: Study, n_trials: int, sampler_seed: int, progress: bool = False) -> None:
    """Run up to ``n_trials`` trials of the study in this process; none once :func:`_spent` reaches ``spec.trials``."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    spec.load(sampler_seed).optimize(
        functools.partial(objective, spec), n_trials=n_trials, catch=(TrialError,), show_progress_bar=progress,
        callbacks=[_Budget(spec.trials)])


def run_trials_on_ray(spec: Study, n_trials: int, sampler_seed: int, parallel: int | None = None,
                      address: str | None = None, ray_cpus: int | None = None) -> None:
    """``n_trials`` trials over a Ray cluster: ``parallel`` tasks (default: the cluster's CPUs // ``workers``),
    each a :func:`run_trials` on its share of the trials against the one storage, with its own sampler seed.
    A task whose worker dies is rerun once by Ray; its trial left running is failed and retried by the
    heartbeat, and :class:`_Budget` keeps the study's total."""
    ray = connect_ray(address, ray_cpus)
    n = parallel or max(1, int(ray.cluster_resources().get("CPU", 1)) // spec.workers)
    n = min(n, n_trials)
    shares = [n_trials // n + (i < n_trials % n) for i in range(n)]
    # Task 0 keeps the local run's seed; the others get independent ones (the same seed would draw the same trials).
    seeds = [sampler_seed] + [int(s) for s in np.random.SeedSequence(sampler_seed).generate_state(n - 1)]
    task = ray.remote(in_worker).options(**{**ray_options(), "num_cpus": spec.workers})
    pending = [task.remote(run_trials, spec, share, s) for share, s in zip(shares, seeds)]
    try:
        while pending:
            (ref,), pending = ray.wait(pending, num_returns=1)
            ray.get(ref)  # a worker's failure ends the run (the study keeps its finished trials; rerun to go on)
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)


def tune(policy: str, scenarios: list[str], trials: int, episodes: int, seed: int = 100, *,
         out: str | Path = "runs/tune", storage: str | None = None, yaml_path: str | Path | None = None,
         rung: int | None = None, batch: int = 1, workers: int = 1, sampler_seed: int = 0,
         startup_trials: int = 5, progress: bool = True, backend: str = "local", address: str | None = None,
         ray_cpus: int | None = None, parallel: int | None = None, objective: str = "success"):
    """Run the study until ``trials`` of its trials are finished (:func:`_spent`); write the best config to
    ``yaml_path`` (default ``OUT/best.yaml``; ``configs/tuned/<policy>.yaml`` ships it as the policy's default) and
    return the study.
    ``backend="ray"``: the trials run in parallel on the Ray cluster at ``address`` (default: a new local instance
    of ``ray_cpus`` CPUs), ``parallel`` at a time (default: its CPUs // ``workers``), against the one storage
    (a real cluster needs a PostgreSQL or MySQL URL and ``out`` on a shared disk: ``docs/scaling.md``).
    ``objective``: what a trial maximizes (:data:`OBJECTIVES`, the module docstring). Raises :class:`TuneError`
    before any trial for an invalid request."""
    import optuna

    if objective not in OBJECTIVES:
        raise TuneError(f"objective {objective!r}: one of {', '.join(OBJECTIVES)}")

    if not scenarios:
        raise TuneError("give at least one scenario")
    if trials < 1 or episodes < 1 or workers < 1:
        raise TuneError(f"trials, episodes and workers must be >= 1, got {trials}, {episodes} and {workers}")
    if seed < 0 or seed + episodes > RESULTS_SEEDS:
        raise TuneError(f"tuning seeds {seed}..{seed + episodes - 1} must lie in 0..{RESULTS_SEEDS - 1}: seeds "
                        f"from {RESULTS_SEEDS} on are the safety, results and claims seeds, never tuned on")
    if parallel is not None and (backend != "ray" or parallel < 1):
        raise TuneError(f"--parallel {parallel}: the number of trials at once on Ray (>= 1, with --backend ray)")
    try:  # the folder and the best config's file are checked before any trial, not after the last
        check_out_dir(out, create=False)
        if yaml_path is not None:
            check_out_dir(Path(yaml_path).parent, create=False, flag=f"--yaml {yaml_path}: its folder")
            if Path(yaml_path).is_dir():
                raise EvaluationError(f"--yaml {yaml_path} is a folder, not a file")
    except EvaluationError as err:
        raise TuneError(str(err)) from None
    try:
        start_backend(backend, address, ray_cpus)
    except BackendError as err:
        raise TuneError(str(err)) from None
    rung = episodes if rung is None else max(1, min(rung, episodes))
    space = search_space(policy)
    base = check_space(policy, scenarios, space)
    try:
        out = check_out_dir(out).resolve()  # absolute for the trials, wherever they run (Ray workers too)
    except EvaluationError as err:
        raise TuneError(str(err)) from None
    url = storage or f"sqlite:///{out / 'study.db'}"
    # The name holds what the trials mean: a changed space or base config is another study, never a resumed one.
    # Another objective is another study (success's left out of the hash: the studies made before it keep their names).
    meaning = config_hash(policy, {"base": base, "space": {k: repr(v) for k, v in space.items()},
                                   **({"objective": objective} if objective != "success" else {})})[:8]
    spec = Study(policy, tuple(scenarios), space, base, str(out), url,
                 f"{study_name(policy, scenarios, episodes, seed)}:{meaning}", trials,
                 tuple(range(seed, seed + episodes)), rung, batch, workers, startup_trials, objective)
    # A resumed study's sampler is seeded past the trials it holds: the same seed again would redraw the values of
    # its first (random) trials.
    held = sum(s.n_trials for s in optuna.get_all_study_summaries(_storage(url)) if s.study_name == spec.name)
    study = spec.load(sampler_seed + held)
    if not study.trials:  # a new study starts from what users run; a resumed one keeps its first trial
        study.enqueue_trial(shipped_params(policy, scenarios[0], space), skip_if_exists=True)
    study.set_user_attr("request", {"policy": policy, "scenarios": scenarios, "episodes": episodes, "seed": seed,
                                    "objective": objective})
    remaining = trials - _spent(study)
    if remaining > 0 and backend == "ray":
        run_trials_on_ray(spec, remaining, sampler_seed + held, parallel, address, ray_cpus)
    elif remaining > 0:
        run_trials(spec, remaining, sampler_seed + held, progress)
    if any(t.state == optuna.trial.TrialState.COMPLETE for t in study.get_trials(deepcopy=False)):
        write_best(study, policy, base, space, Path(yaml_path) if yaml_path else out / "best.yaml")
    return study


def write_best(study, policy: str, base: dict, space: dict, path: Path) -> Path:
    """The best trial's config (factory kwargs) as a YAML of overrides that ``make_policy(policy, env,
    config=path)`` loads, and beside it (:func:`bimp.configs.tuned_files`) the policy and the tuning (the study, its
    budget and the chosen values)."""
    best = study.best_trial
    request = study.user_attrs.get("request", {})
    params = {k: best.params[k] for k in space if k in best.params}
    config = with_params(base, params)
    counts: dict[str, int] = {}
    for t in study.get_trials(deepcopy=False):
        counts[t.state.name.lower()] = counts.get(t.state.name.lower(), 0) + 1
    tuning = {"study": study.study_name, "trial": best.number, "objective": best.value,
              "objective_of": request.get("objective", "success"), "trials": counts,
              "scenarios": request.get("scenarios"), "episodes_per_scenario": request.get("episodes"),
              "first_seed": request.get("seed"), "params": params,
              "success_rate": best.user_attrs.get("success_rate"), "score": best.user_attrs.get("score"),
              "written": datetime.now(timezone.utc).isoformat(timespec="seconds")}
    path.parent.mkdir(parents=True, exist_ok=True)
    for file, text in tuned_files(path, config, policy, tuning).items():
        write_atomic(file, text)
    return path


__all__ = ["Study", "TrialError", "TuneError", "check_space", "objective_value", "search_space", "tune"]
