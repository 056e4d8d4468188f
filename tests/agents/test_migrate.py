"""``bimp migrate`` (issue 28, item 4): records of older code become records the current code resumes.

The fixture is real records from results/ (trimmed: fewer metrics, no scenario draws, a shorter seeding note), made
in the flat config shape before issue 25 and, for PPO, with the absolute model path of the machine they were made on
(two machines: one arm).

Since issue 26 (commit 3cc2d46) every planner plans on a polyline road, ``problem.road_points`` and
``problem.road_spacing``: plain fields no value of which reproduces the closed-form road the real planner records
were made on. Those records (EnKTS, EnKS, MPPI, NMPC) are therefore left in place, inline, as history, and the
current code refuses to count them (``real``); PPO's carry no planning problem and still migrate and resume. The flat
-> nested shape migration of planner configs is kept under test on *synthetic* variants of the same records
(``synthetic_records``): each flat config given the two issue-26 fields at the values the current code uses, as the
flat shape would have written it with today's fields. No such record was ever made; they exist so that the shape
migration (and the rules riding on it: MPPI's seeding, fields without a neutral value, dropped traces) still has
planner records it applies to."""

import copy
import json
import shutil

import pytest

from bimp.agents.cli import EvaluationError, main
from bimp.agents.evaluation import migrate
from bimp.agents.evaluation.evaluate import evaluate
from bimp.agents.evaluation.records import ARMS_FILE, EPISODES_FILE, read_arms, read_records
from bimp.planners.problem import ProblemConfig

AFTER_MPPI_SEEDING = "667c57cfab7668693560ca8390a734d82705bc03"  # MPPI's records from here are the current code's
# The checkouts the two PPO records were made in (spelled in pieces: no committed file names a machine's folder).
MACHINES = {"{HERE}": "/" + "work/main", "{THERE}": "/" + "home/someone/study"}

# The requests that made them (results/safety, results/peers, results/rl): each must find its episode done.
REQUESTS = {
    "enkts": dict(scenarios=["emergency-brake"], policies=["enkts"], seeds=[1000]),
    "enks": dict(scenarios=["overtaking"], policies=["enks"], seeds=[1000]),
    "mppi": dict(scenarios=["emergency-brake"], policies=["mppi"], seeds=[1000]),
    "nmpc": dict(scenarios=["emergency-brake"], policies=["nmpc"], seeds=[1000]),
    "ppo": dict(scenarios=["emergency-brake"], policies=["ppo"], seeds=[1000, 1001],
                overrides={"ppo": {"training_seed": 1}}, labels={"ppo": "ppo-s1"}),
}

OLD = {'enkts': {'scenario': 'emergency-brake',
                 'label': 'enkts',
                 'policy': 'enkts',
                 'seed': 1000,
                 'config_hash': '164760d5591ef385',
                 'config': {'config': {'adapt_spread': True,
                                       'barrier': {'bound_margin': 0.05,
                                                   'brake_decel': 6.0,
                                                   'edge_margin': 0.3,
                                                   'headway': 0.6,
                                                   'lateral_clearance': 1.0,
                                                   'sharpness': 8.0,
                                                   'widths': [0.1, 0.5, 1.0, 0.01, 0.5, 0.002]},
                                       'dynamics': 'mlp',
                                       'grow_nu': True,
                                       'horizon': 20,
                                       'iterations': 1,
                                       'lane_change_rate': 2.0,
                                       'max_innovation': 2.0,
                                       'max_spread': 25.0,
                                       'n_particles': 100,
                                       'nu': 4.0,
                                       'relaxation': 0.5,
                                       'seed': 0,
                                       'sigma_barrier': 0.1,
                                       'sigma_du': [0.5, 0.0015],
                                       'sigma_input': [3.0, 0.02],
                                       'sigma_ref': [1.0, 0.05, 1.0]},
                            'scenario': {'brake_decel': [5.0, 7.0],
                                         'brake_onset': [0.8, 1.2],
                                         'ev_speed': [23.0, 27.0],
                                         'ov1_gap': [50.0, 60.0],
                                         'ov2_gap': [35.0, 55.0],
                                         'ov_speed': [20.0, 24.0],
                                         'ref_hold': 3.0,
                                         'ref_zero_step': 80}},
                 'overrides': {},
                 'seeding': 'np.random.SeedSequence(seed).spawn(2) -> (env, policy)',
                 'bimp_version': '0.1.0',
                 'git_commit': 'a251b89088672207b278b487824857a20c9be49f',
                 'git_dirty': True,
                 'env_seed': 298458674005815454,
                 'policy_seed': 8562138667189027890,
                 'status': 'ok',
                 'steps': 120,
                 'truncated': True,
                 'metrics': {'success_rate': 1.0, 'collision_rate': 0.0, 'offroad_rate': 0.0}},
       'enks': {'scenario': 'overtaking',
                'label': 'enks',
                'policy': 'enks',
                'seed': 1000,
                'config_hash': 'd6aa715d853b5241',
                'config': {'config': {'adapt_spread': True,
                                      'barrier': {'bound_margin': 0.05,
                                                  'brake_decel': 6.0,
                                                  'edge_margin': 0.3,
                                                  'headway': 0.6,
                                                  'lateral_clearance': 1.0,
                                                  'sharpness': 8.0,
                                                  'widths': [0.1, 0.5, 1.0, 0.01, 0.5, 0.002]},
                                      'dynamics': 'mlp',
                                      'grow_nu': True,
                                      'horizon': 20,
                                      'iterations': 1,
                                      'lane_change_rate': 2.0,
                                      'max_innovation': 2.0,
                                      'max_spread': 25.0,
                                      'n_particles': 100,
                                      'nu': None,
                                      'relaxation': 0.5,
                                      'seed': 0,
                                      'sigma_barrier': 0.1,
                                      'sigma_du': [0.5, 0.0015],
                                      'sigma_input': [3.0, 0.02],
                                      'sigma_ref': [1.0, 0.05, 1.0]},
                           'scenario': {'arc_angle_deg': [50.0, 70.0],
                                        'behaviour': {'consider_s': 4.0,
                                                      'headway_s': 1.5,
                                                      'lane_change_s': 2.0,
                                                      'pass_s': 6.0,
                                                      'return_s': 0.5},
                                        'ev_speed': [23.0, 27.0],
                                        'ov1_gap': [25.0, 35.0],
                                        'ov1_speed': [15.0, 17.0],
                                        'ov2_gap': [100.0, 130.0],
                                        'ov2_speed': [18.0, 20.0],
                                        'radius': [180.0, 220.0],
                                        'reference': 'behaviour'}},
                'overrides': {},
                'seeding': 'np.random.SeedSequence(seed).spawn(2) -> (env, policy)',
                'bimp_version': '0.1.0',
                'git_commit': 'dc4efc265a0169364432f57071da6a33aa284f32',
                'git_dirty': False,
                'env_seed': 298458674005815454,
                'policy_seed': 8562138667189027890,
                'status': 'ok',
                'steps': 150,
                'truncated': True,
                'metrics': {'success_rate': 1.0, 'collision_rate': 0.0, 'offroad_rate': 0.0}},
       'mppi': {'scenario': 'emergency-brake',
                'label': 'mppi',
                'policy': 'mppi',
                'seed': 1000,
                'config_hash': '53875ca1e7a74105',
                'config': {'config': {'control_cost': 0.26403651263343025,
                                      'horizon': None,
                                      'n_particles': 50,
                                      'noise_gain': 2.1624849553408434,
                                      'sample': 'increments',
                                      'seed': 0,
                                      'temperature': 1.7832296111318195},
                           'scenario': {'brake_decel': [5.0, 7.0],
                                        'brake_onset': [0.8, 1.2],
                                        'ev_speed': [23.0, 27.0],
                                        'ov1_gap': [50.0, 60.0],
                                        'ov2_gap': [35.0, 55.0],
                                        'ov_speed': [20.0, 24.0],
                                        'ref_hold': 3.0,
                                        'ref_zero_step': 80},
                           'tuning': {'barrier': {'bound_margin': 0.05,
                                                  'brake_decel': 6.0,
                                                  'edge_margin': 0.5421183334242939,
                                                  'headway': 0.5559190030990193,
                                                  'lateral_clearance': 1.0,
                                                  'sharpness': 8.0,
                                                  'widths': [0.1, 0.5, 1.0, 0.01, 0.5, 0.002]},
                                      'dynamics': 'mlp',
                                      'horizon': 20,
                                      'lane_change_rate': 2.0,
                                      'nu': 4.0,
                                      'sigma_barrier': 0.09163017788378915,
                                      'sigma_du': [0.5, 0.0015],
                                      'sigma_input': [3.0, 0.02],
                                      'sigma_ref': [2.285894960493878, 0.05, 1.050435220966566]}},
                'overrides': {},
                'seeding': 'np.random.SeedSequence(seed).spawn(2) -> (env, policy)',
                'bimp_version': '0.1.0',
                'git_commit': '90f584cd9d8a4eda3bf5df4fa6c699096338c38f',
                'git_dirty': False,
                'env_seed': 298458674005815454,
                'policy_seed': 8562138667189027890,
                'status': 'ok',
                'steps': 120,
                'truncated': True,
                'metrics': {'success_rate': 1.0, 'collision_rate': 0.0, 'offroad_rate': 0.0}},
       'nmpc': {'scenario': 'emergency-brake',
                'label': 'nmpc',
                'policy': 'nmpc',
                'seed': 1000,
                'config_hash': 'dbe43b90909b687f',
                'config': {'config': {'bound_tightening': 0.001,
                                      'cold_max_cpu_time': 5.0,
                                      'cold_max_iter': 200,
                                      'feasibility_tol': 0.0001,
                                      'hessian': 'exact',
                                      'horizon': None,
                                      'keep_out_power': 4,
                                      'max_cpu_time': 1.0,
                                      'max_iter': 30,
                                      'nu': None,
                                      'slack_penalty': 10000.0,
                                      'tol': 1e-06},
                           'scenario': {'brake_decel': [5.0, 7.0],
                                        'brake_onset': [0.8, 1.2],
                                        'ev_speed': [23.0, 27.0],
                                        'ov1_gap': [50.0, 60.0],
                                        'ov2_gap': [35.0, 55.0],
                                        'ov_speed': [20.0, 24.0],
                                        'ref_hold': 3.0,
                                        'ref_zero_step': 80},
                           'tuning': {'barrier': {'bound_margin': 0.05,
                                                  'brake_decel': 6.0,
                                                  'edge_margin': 0.3,
                                                  'headway': 0.6,
                                                  'lateral_clearance': 1.0,
                                                  'sharpness': 8.0,
                                                  'widths': [0.1, 0.5, 1.0, 0.01, 0.5, 0.002]},
                                      'dynamics': 'mlp',
                                      'horizon': 20,
                                      'lane_change_rate': 2.0,
                                      'nu': 4.0,
                                      'sigma_barrier': 0.1,
                                      'sigma_du': [0.5, 0.0015],
                                      'sigma_input': [3.0, 0.02],
                                      'sigma_ref': [1.0, 0.05, 1.0]}},
                'overrides': {},
                'seeding': 'np.random.SeedSequence(seed).spawn(2) -> (env, policy)',
                'bimp_version': '0.1.0',
                'git_commit': '5da45f64a68e5dead2f78495f7c4f6fabf1fafe6',
                'git_dirty': False,
                'env_seed': 298458674005815454,
                'policy_seed': 8562138667189027890,
                'status': 'ok',
                'steps': 120,
                'truncated': True,
                'metrics': {'success_rate': 1.0, 'collision_rate': 0.0, 'offroad_rate': 0.0}},
       'ppo': {'scenario': 'emergency-brake',
               'label': 'ppo-s1',
               'policy': 'ppo',
               'seed': 1000,
               'config_hash': 'e6952698a955f938',
               'config': {'config': {'algo': 'ppo',
                                     'model_path': '{HERE}/agents/models/ppo_emergency-brake_s1.zip',
                                     'model_sha256':
                                         'fde20022c3e4b3275044075f9ad4a442f0d2fd1c012479efffccda92861de923'},
                          'scenario': {'brake_decel': [5.0, 7.0],
                                       'brake_onset': [0.8, 1.2],
                                       'ev_speed': [23.0, 27.0],
                                       'ov1_gap': [50.0, 60.0],
                                       'ov2_gap': [35.0, 55.0],
                                       'ov_speed': [20.0, 24.0],
                                       'ref_hold': 3.0,
                                       'ref_zero_step': 80}},
               'overrides': {'training_seed': 1},
               'seeding': 'np.random.SeedSequence(seed).spawn(2) -> (env, policy)',
               'bimp_version': '0.1.0',
               'git_commit': '715d4c9a524f2902474824430425e67f3ee8a789',
               'git_dirty': True,
               'env_seed': 298458674005815454,
               'policy_seed': 8562138667189027890,
               'status': 'ok',
               'steps': 120,
               'truncated': True,
               'metrics': {'success_rate': 1.0, 'collision_rate': 0.0, 'offroad_rate': 0.0}},
       'ppo-elsewhere': {'scenario': 'emergency-brake',
                         'label': 'ppo-s1',
                         'policy': 'ppo',
                         'seed': 1001,
                         'config_hash': '834232a4cfcab8dc',
                         'config': {'config': {'algo': 'ppo',
                                               'model_path': '{THERE}/agents/models/ppo_emergency-brake_s1.zip',
                                               'model_sha256':
                                                   'fde20022c3e4b3275044075f9ad4a442f0d2fd1c012479efffccda92861de923'},
                                    'scenario': {'brake_decel': [5.0, 7.0],
                                                 'brake_onset': [0.8, 1.2],
                                                 'ev_speed': [23.0, 27.0],
                                                 'ov1_gap': [50.0, 60.0],
                                                 'ov2_gap': [35.0, 55.0],
                                                 'ov_speed': [20.0, 24.0],
                                                 'ref_hold': 3.0,
                                                 'ref_zero_step': 80}},
                         'overrides': {'training_seed': 1},
                         'seeding': 'np.random.SeedSequence(seed).spawn(2) -> (env, policy)',
                         'bimp_version': '0.1.0',
                         'git_commit': 'c711b58f0a1319ba84d31e3135c473e68a06ac34',
                         'git_dirty': False,
                         'env_seed': 4015908867499960593,
                         'policy_seed': 4619074960470009795,
                         'status': 'ok',
                         'steps': 120,
                         'truncated': True,
                         'metrics': {'success_rate': 1.0, 'collision_rate': 0.0, 'offroad_rate': 0.0}}}


PLANNERS = ("enkts", "enks", "mppi", "nmpc")
# Issue 26's fields at the values the current code uses (ProblemConfig's defaults, configs/tuned/*.yaml): what the
# synthetic records add to the real ones' flat configs.
ROAD = {"road_points": 160, "road_spacing": 1.0}
# Why the current code leaves the real planner records in place: rebuilt, their config resolves with the road.
ROAD_REFUSAL = "config.problem.road_points: None -> 160; config.problem.road_spacing: None -> 1.0"


def write(folder, records) -> bytes:
    folder.mkdir(parents=True, exist_ok=True)
    data = "".join(json.dumps(r) + "\n" for r in records).encode()
    (folder / EPISODES_FILE).write_bytes(data)
    return data


def old_records() -> list[dict]:
    """The real records, as they are in results/ (the machines' folders filled in)."""
    records = copy.deepcopy(list(OLD.values()))
    for r in records:
        if r["policy"] == "mppi":
            r["git_commit"] = AFTER_MPPI_SEEDING
        if "model_path" in r["config"]["config"]:
            for placeholder, root in MACHINES.items():
                r["config"]["config"]["model_path"] = r["config"]["config"]["model_path"].replace(placeholder, root)
    return records


def synthetic_records() -> list[dict]:
    """SYNTHETIC: the real records with issue 26's road fields (``ROAD``) added to each planner's flat config where
    that shape held the problem's keys (EnKTS/EnKS: the top of ``config``; MPPI/NMPC: ``tuning``), as the flat shape
    would have written them with today's fields. No code ever wrote these (the flat shape was gone before the road
    came): they keep the flat -> nested migration of planner configs under test now that the real planner records,
    made on the closed-form road, are rightly left in place. PPO's records are the real ones."""
    records = old_records()
    for r in records:
        config = r["config"]
        if "tuning" in config:
            config["tuning"].update(ROAD)
        elif "horizon" in config["config"]:
            config["config"].update(ROAD)
    assert sum(r["config"] != o["config"] for r, o in zip(records, old_records())) == len(PLANNERS)
    return records


def index(records, policy) -> int:
    (number,) = [i for i, r in enumerate(records) if r["policy"] == policy]
    return number


def tree(folder) -> dict:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.name != ".lock"}


@pytest.fixture(scope="module")
def real(tmp_path_factory):
    """The real records, migrated: PPO's (two records, one arm) rewritten, the planners' left in place."""
    folder = tmp_path_factory.mktemp("migrate") / "real"
    write(folder, old_records())
    report = migrate.migrate_folder(folder)
    assert report.problem is None and report.changed == 2 and report.arms == 1, report.line()
    assert len(report.left) == len(PLANNERS), report.line()
    for policy, reason in zip(PLANNERS, report.left):
        assert reason.startswith(f"'{policy}' ({policy}) on ") and "the current code does not reproduce" in reason
        assert ROAD_REFUSAL in reason, reason  # issue 26's refusal, nothing else
    return folder


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """The synthetic records (``synthetic_records``), migrated: every one rewritten, nothing left."""
    defaults = ProblemConfig()
    assert ROAD == {key: getattr(defaults, key) for key in ROAD}  # the values the current code uses
    folder = tmp_path_factory.mktemp("migrate") / "synthetic"
    write(folder, synthetic_records())
    report = migrate.migrate_folder(folder)
    assert report.problem is None and report.changed == len(OLD) and not report.left, report.line()
    return folder


def test_real_planner_records_are_left_in_place_and_refused_by_the_current_code(real):
    lines = (real / EPISODES_FILE).read_text().splitlines()
    records = old_records()
    arms = read_arms(real)
    for policy in PLANNERS:
        number = index(records, policy)
        assert json.loads(lines[number]) == records[number]  # as it was, config inline: history
        assert records[number]["config_hash"] not in arms
        # Its request does not take it for its own episode (nor silently runs beside it): another config.
        with pytest.raises(EvaluationError, match=f"made with another config \\(hash {OLD[policy]['config_hash']}"):
            evaluate(out=real, episodes=1, progress=False, dry_run=True, **REQUESTS[policy])


def test_real_ppo_records_are_migrated_and_found_done(real):
    plan = evaluate(out=real, episodes=1, progress=False, dry_run=True, **REQUESTS["ppo"])
    assert plan.to_run == [] and plan.done == len(REQUESTS["ppo"]["seeds"])
    (ppo,) = read_arms(real).values()
    assert ppo["policy"] == "ppo" and ppo["artifacts"] == {"model": "bimp:agents/models/ppo_emergency-brake_s1.zip"}
    assert not any({"config", "overrides", "seeding"} & set(r) for r in read_records(real) if r["policy"] == "ppo")


@pytest.mark.parametrize("name", REQUESTS)
def test_migrated_records_are_found_done_by_the_request_that_made_them(synthetic, name):
    plan = evaluate(out=synthetic, episodes=1, progress=False, dry_run=True, **REQUESTS[name])
    assert plan.to_run == [] and plan.done == len(REQUESTS[name]["seeds"])


def test_records_are_compact_and_their_configs_in_the_new_shape(synthetic):
    arms, records = read_arms(synthetic), read_records(synthetic)
    assert len(arms) == 5 and {r["config_hash"] for r in records} == set(arms)  # both PPO records: one arm
    assert not any({"config", "overrides", "seeding"} & set(r) for r in records)
    for key, entry in arms.items():
        assert migrate.config_hash(entry["policy"], entry["config"]) == key
    by_policy = {entry["policy"]: entry for entry in arms.values()}
    for policy in PLANNERS:  # the road's fields moved with the rest of the problem
        own = by_policy[policy]["config"]["config"]
        assert {key: own["problem"][key] for key in ROAD} == ROAD and not set(ROAD) & set(own)
    assert by_policy["enkts"]["config"]["config"]["problem"]["horizon"] == 20
    assert "horizon" not in by_policy["enkts"]["config"]["config"]
    assert by_policy["mppi"]["config"]["config"]["problem"]["nu"] == 4.0 and "tuning" not in by_policy["mppi"]["config"]
    nmpc = by_policy["nmpc"]["config"]["config"]
    assert not {"nu", "bound_tightening", "horizon"} & set(nmpc)
    assert nmpc["problem"]["barrier"]["bound_margin"] == OLD["nmpc"]["config"]["config"]["bound_tightening"]
    ppo = by_policy["ppo"]
    assert ppo["config"]["config"] == {"algo": "ppo", "model_sha256": OLD["ppo"]["config"]["config"]["model_sha256"]}
    assert ppo["artifacts"] == {"model": "bimp:agents/models/ppo_emergency-brake_s1.zip"}
    assert ppo["overrides"] == {"training_seed": 1}
    # Labels, seeds, metrics and the code version stay as they were.
    assert [(r["label"], r["seed"], r["metrics"], r["git_commit"]) for r in records] == [
        (r["label"], r["seed"], r["metrics"], r["git_commit"]) for r in synthetic_records()]


@pytest.mark.parametrize("which", ["real", "synthetic"])
def test_no_absolute_path_is_left_so_a_copy_elsewhere_resumes_the_same_config(which, request, tmp_path):
    migrated = request.getfixturevalue(which)
    for name in (EPISODES_FILE, ARMS_FILE):
        text = (migrated / name).read_text()
        assert not any(root in text for root in MACHINES.values()) and '"model_path"' not in text
    copy_ = tmp_path / "elsewhere" / "old"
    shutil.copytree(migrated, copy_)
    plan = evaluate(out=copy_, episodes=1, progress=False, dry_run=True, **REQUESTS["ppo"])
    assert plan.to_run == []


@pytest.mark.parametrize("which, left", [("real", len(PLANNERS)), ("synthetic", 0)])
def test_a_second_migration_changes_nothing(which, left, request, capsys):
    migrated = request.getfixturevalue(which)
    before = tree(migrated)
    assert main(["migrate", str(migrated)]) == 0
    out = capsys.readouterr().out
    assert "nothing to change" in out and out.count("left in place:") == left
    assert tree(migrated) == before


@pytest.mark.parametrize("records, changed, left", [(old_records, 2, len(PLANNERS)), (synthetic_records, len(OLD), 0)])
def test_a_dry_run_reports_and_writes_nothing(tmp_path, capsys, records, changed, left):
    data = write(tmp_path / "old", records())
    assert main(["migrate", str(tmp_path / "old"), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert f"{changed} of {len(OLD)} record(s) rewritten" in out
    assert out.count("left in place:") == left and out.count(ROAD_REFUSAL) == left
    assert tree(tmp_path / "old") == {EPISODES_FILE: data}


def test_mppi_records_made_before_its_seeding_changed_are_left_in_place(tmp_path):
    records = synthetic_records()  # the real MPPI record would be left anyway, for the road
    number = index(records, "mppi")
    records[number]["git_commit"] = OLD["mppi"]["git_commit"]  # made before 667c57c
    write(tmp_path, records)
    report = migrate.migrate_folder(tmp_path)
    assert report.problem is None and len(report.left) == 1 and "mppi" in report.left[0]
    assert "MPPI's seeding changed there" in report.left[0]
    lines = (tmp_path / EPISODES_FILE).read_text().splitlines()
    assert json.loads(lines[number]) == records[number]  # as it was, config inline
    assert len(read_arms(tmp_path)) == 4


def test_an_arm_made_before_a_field_without_neutral_value_is_left_in_place_not_adopted(tmp_path):
    """The first wave's NMPC had hard constraints; ``slack_penalty`` came with the soft ones and has no neutral
    value. Filling it with its default would take those records for the current NMPC's: they stay as they were.
    (On the synthetic records, which carry today's road: the real ones are left for the road as well.)"""
    records = synthetic_records()
    number = index(records, "nmpc")
    del records[number]["config"]["config"]["slack_penalty"]
    write(tmp_path, records)
    report = migrate.migrate_folder(tmp_path)
    assert report.problem is None and len(report.left) == 1 and "slack_penalty" in report.left[0]
    assert "road_" not in report.left[0]  # slack_penalty alone keeps it out
    lines = (tmp_path / EPISODES_FILE).read_text().splitlines()
    assert json.loads(lines[number]) == records[number]  # as it was, config inline: history, not a current result
    (done,) = [r for r in read_records(tmp_path) if r["policy"] == "nmpc"]
    assert done["config_hash"] not in read_arms(tmp_path)


def test_an_arm_the_current_code_cannot_rebuild_is_refused_and_its_folder_left_alone(tmp_path, capsys):
    records = old_records()
    records[0]["config"]["config"]["bogus_switch"] = True  # a config the current code does not know
    data = write(tmp_path / "old", records)
    assert main(["migrate", str(tmp_path / "old")]) == 1
    out = capsys.readouterr().out
    assert "not migrated: arm 'enkts' (enkts) on emergency-brake" in out and "bogus_switch" in out
    assert tree(tmp_path / "old") == {EPISODES_FILE: data}


def test_records_without_any_config_are_reported_and_left_alone(tmp_path, capsys):
    record = {k: v for k, v in OLD["enkts"].items() if k not in ("config", "config_hash", "label", "overrides")}
    data = write(tmp_path / "N10", [record])
    assert main(["migrate", str(tmp_path / "N10")]) == 1
    assert "carries no config" in capsys.readouterr().out
    assert tree(tmp_path / "N10") == {EPISODES_FILE: data}


def test_a_folder_without_records_is_refused(tmp_path, capsys):
    assert main(["migrate", str(tmp_path)]) == 2
    assert "no episodes.jsonl" in capsys.readouterr().err


# A record's per-step trace, as the current code writes it with --traces (a route where the env has no closed-form
# road) and as older code did (the closed form's road).
TRACES = dict(trace={"s": [0.0, 1.0]}, road={"lanes": 2}, route={"xy": [[0.0, 0.0], [1.0, 0.0]]},
              bounds={"a": [-1, 1]})


def test_drop_traces_leaves_records_that_still_summarize(tmp_path):
    records = synthetic_records()
    records[0].update(TRACES)
    write(tmp_path, records)
    assert migrate.migrate_folder(tmp_path, drop_traces=True).problem is None
    assert not any(set(TRACES) & set(r) for r in read_records(tmp_path))
    summary = evaluate(out=tmp_path, episodes=1, progress=False, **REQUESTS["enkts"])  # nothing runs: all done
    assert summary["enkts/emergency-brake"]["episodes"] == 1


def test_drop_traces_touches_only_what_is_migrated(tmp_path):
    """A record left in place is history, kept as it was, trace and all; the migrated PPO records lose theirs."""
    records = old_records()
    enkts, ppo = index(records, "enkts"), next(i for i, r in enumerate(records) if r["policy"] == "ppo")
    records[enkts].update(TRACES)
    records[ppo].update(TRACES)
    write(tmp_path, records)
    report = migrate.migrate_folder(tmp_path, drop_traces=True)
    assert report.problem is None and report.changed == 2 and len(report.left) == len(PLANNERS)
    lines = (tmp_path / EPISODES_FILE).read_text().splitlines()
    assert json.loads(lines[enkts]) == records[enkts]
    assert not set(TRACES) & set(json.loads(lines[ppo]))


def missed(record: dict, score: float = 0.72) -> dict:
    """``record`` as an episode that ran to its time limit without its env's goal (two-way-overtake's waiting
    behind the slow vehicle), scored before the goal gate existed."""
    record["truncated"] = True
    record["metrics"] = {"success_rate": 0.0, "collision_rate": 0.0, "offroad_rate": 0.0, "score": score,
                         "score_progress": 0.5}
    return record


@pytest.mark.parametrize("make, policy", [(synthetic_records, "enkts"), (old_records, "enks")])
def test_a_score_that_missed_its_goal_is_zeroed_whether_its_arm_migrates_or_stays(tmp_path, capsys, make, policy):
    records = make()  # enkts of the synthetic records migrates; enks of the real ones stays in place (the road)
    number = index(records, policy)
    missed(records[number])
    crashed = [r["policy"] for r in records].index("ppo")
    records[crashed]["truncated"] = True  # a collision at the time limit: judged by the collision gate alone
    records[crashed]["metrics"] = {"success_rate": 0.0, "collision_rate": 1.0, "offroad_rate": 0.0, "score": 0.6}
    write(tmp_path, records)
    assert main(["migrate", str(tmp_path), "--dry-run"]) == 0
    assert "(1 score(s) zeroed by the goal gate)" in capsys.readouterr().out
    report = migrate.migrate_folder(tmp_path)
    assert report.problem is None and report.gated == 1
    after = {(r["policy"], r["seed"]): r for r in read_records(tmp_path)}
    gated = after[(policy, records[number]["seed"])]
    assert gated["metrics"]["score"] == 0.0 and gated["metrics"]["score_progress"] == 0.5  # the parts as they were
    assert [r["metrics"].get("score") for r in read_records(tmp_path) if r["policy"] == "ppo"].count(0.6) == 1
    assert (policy in " ".join(report.left)) == (make is old_records)  # the case the parametrization means
    before = tree(tmp_path)
    assert migrate.migrate_folder(tmp_path).gated == 0 and tree(tmp_path) == before  # a second run: nothing


def test_renamed_settings_take_their_new_name_and_verifications_follow_the_new_hashes(tmp_path):
    folder = tmp_path / "renamed"
    records = synthetic_records()
    write(folder, records)
    old = {r["scenario"] + "|" + r["label"] + "|" + r["config_hash"]: r for r in records if r["policy"] in PLANNERS}
    verified = {key: {"commit": AFTER_MPPI_SEEDING, "outcome": "same", "seeds": [1000]} for key in old}
    (folder / "verified.json").write_text(json.dumps(verified))
    assert migrate.migrate_folder(folder).problem is None
    arms = read_arms(folder)
    for entry in arms.values():
        barrier = entry["config"]["config"].get("problem", {}).get("barrier")
        if barrier is not None:  # the barrier's brake_decel is follower_decel, its value kept
            assert "brake_decel" not in barrier and barrier["follower_decel"] == 6.0
    carried = json.loads((folder / "verified.json").read_text())
    assert len(carried) == len(verified) and set(carried).isdisjoint(verified)
    assert {key.rsplit("|", 1)[1] for key in carried} <= set(arms)  # each under its arm's new hash
    assert sorted(carried.values(), key=json.dumps) == sorted(verified.values(), key=json.dumps)


def test_a_folder_with_a_planner_on_a_curved_road_migrates_to_itself(tmp_path, capsys):
    """A planner's arm on a curved road records what the road changes in its problem (``"road"``): a current
    record, which ``bimp migrate`` finds unchanged, and rebuilds to the same config."""
    evaluate(scenarios=["u-turn-v0"], policies=["enkts"], seeds=[1000], episodes=1, out=tmp_path, progress=False)
    (arm,) = read_arms(tmp_path).values()
    assert arm["config"]["road"]["track_course"] is True
    before = tree(tmp_path)
    assert main(["migrate", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "nothing to change" in out and "left in place:" not in out and "not migrated" not in out
    assert tree(tmp_path) == before
