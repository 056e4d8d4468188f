"""bimp.planners.dynamics: the exact bicycle model against the env's vehicle, the shipped MLP's accuracy on fresh
scenario runs, batching, numpy/torch agreement, the loader's errors, a short training run, weights files named by a
planner config, and where ``bimp train-dynamics`` writes."""

from __future__ import annotations

import hashlib
import os
import pickle
import shlex
from pathlib import Path

import numpy as np
import pytest
import torch

from bimp.agents.commands import train_dynamics
from bimp.configs import load_config
from bimp.planners import dynamics
from bimp.planners.dynamics import BicycleModel, LearnedDynamics, load_model, model_from_name, save_model
from bimp.planners.dynamics_train import (
    DataConfig,
    TrainConfig,
    generate_data,
    open_loop_errors,
    rollout_scenarios,
    simulate_vehicle,
    train,
)
from bimp.planners.enkts import EnKTSConfig


@pytest.fixture(scope="module")
def model() -> LearnedDynamics:
    return load_model()


def random_rows(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """States over the envelope (speeds 0..42, some exactly 0) and inputs partly beyond the actuator ranges."""
    x = np.column_stack([rng.uniform(-300, 300, n), rng.uniform(-10, 10, n), rng.uniform(-4, 4, n),
                         rng.uniform(0, 42, n)])
    x[::7, 3] = 0.0
    u = np.column_stack([rng.uniform(-12, 12, n), rng.uniform(-0.4, 0.4, n)])
    return x, u


def test_the_models_default_to_the_envs_vehicle():
    """One definition of the vehicle (bimp.envs.scene), pinned to highway-env's in tests/envs/test_scenarios.py."""
    from bimp.envs.scenarios import EgoVehicle
    from bimp.envs.scene import ACTUATOR_ACCEL, ACTUATOR_STEER, DT

    for model in (BicycleModel(), load_model()):  # the shipped weights were trained on that vehicle
        limits = (model.dt, model.max_speed, model.accel_range, model.steer_range)
        assert limits == (DT, EgoVehicle.MAX_SPEED, ACTUATOR_ACCEL, ACTUATOR_STEER)
    assert BicycleModel().length == EgoVehicle.LENGTH


@pytest.mark.parametrize("v0, a, steer", [
    (20.0, -8.0, 0.1),    # brakes to a stop after 25 steps, then must stay at 0
    (3.0, -10.0, -0.3),   # stops within the first step
    (0.0, -5.0, 0.2),     # at rest, braking
    (35.0, 4.0, -0.05),   # passes 40 m/s: highway-env's acceleration cap
    (12.0, 2.0, 0.3),     # full steering lock
])
def test_bicycle_matches_ego_vehicle(v0, a, steer):
    x0 = np.array([[12.0, -3.0, 0.7, v0]])
    inputs = np.tile([a, steer], (1, 50, 1))
    truth = simulate_vehicle(x0, inputs)[0]   # EgoVehicle(road=None) stepped 50 times
    x, bicycle = x0, BicycleModel()
    for t in range(50):
        x = bicycle(x, inputs[:, t])
        np.testing.assert_allclose(x[0], truth[t + 1], rtol=0, atol=1e-9)
    if a < 0:
        assert truth[-1, 3] == 0.0 and x[0, 3] == 0.0


def test_bicycle_validates_config():
    with pytest.raises(ValueError, match="dt"):
        BicycleModel(dt=0.0)
    with pytest.raises(ValueError, match="steer_range"):
        BicycleModel(steer_range=(0.3, -0.3))


def test_shipped_model_open_loop_accuracy(model):
    # Fresh runs (a seed the report of train-dynamics does not use), 20 steps = 2 s open loop from every window.
    trajectories = rollout_scenarios(np.random.default_rng(20240611), episodes=3)
    assert {t.scenario for t in trajectories} == {"bimp/Overtaking-v0", "bimp/EmergencyBrake-v0"}
    err = open_loop_errors(model, trajectories, horizon=20)
    assert err["position"].size >= 30
    assert np.median(err["position"]) < 0.5
    assert np.median(err["heading"]) < 0.02
    # The exact model reproduces the env's recorded runs (so the windows hold no collision impulses).
    exact = open_loop_errors(BicycleModel(), trajectories, horizon=20)
    assert exact["position"].max() < 1e-9


def test_predict_is_batched(model):
    x, u = random_rows(np.random.default_rng(0), 64)
    out = model.predict(x, u)
    assert out.shape == (64, 4) and out.dtype == np.float64
    for i in range(0, 64, 7):
        np.testing.assert_allclose(model.predict(x[i:i + 1], u[i:i + 1])[0], out[i], rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(BicycleModel()(x, u)[5], BicycleModel()(x[5:6], u[5:6])[0])
    with pytest.raises(ValueError, match="expected x"):
        model.predict(x[0], u[0])
    with pytest.raises(ValueError, match="expected x"):
        model.predict(x, u[:-1])


def test_learned_model_keeps_the_env_limits(model):
    x = np.array([[0.0, 0.0, 0.3, 0.0], [0.0, 0.0, 0.3, 0.4], [0.0, 0.0, 0.3, 20.0]])
    u = np.array([[-7.0, 0.05], [-10.0, 0.1], [3.0, 0.02]])
    out = model(x, u)
    assert out[0, 3] == 0.0 and out[1, 3] == 0.0  # the speed clamp at 0
    # At rest the vehicle only creeps by the net's own error (nothing forces it to exactly 0).
    assert np.hypot(*(out[0, :2] - x[0, :2])) < 5e-3 and abs(out[0, 2] - x[0, 2]) < 1e-3
    # Inputs beyond the actuator ranges act like the range's end, as the env clips the action.
    np.testing.assert_array_equal(model(x, u * 5), model(x, np.clip(u * 5, [-10, -0.3], [10, 0.3])))
    # The position change is rotated with the heading (rotation invariance by construction).
    turned = x.copy()
    turned[:, 2] += 1.0
    d0, d1 = out[:, :2] - x[:, :2], model(turned, u)[:, :2] - x[:, :2]
    c, s = np.cos(1.0), np.sin(1.0)
    np.testing.assert_allclose(d1, d0 @ np.array([[c, s], [-s, c]]), atol=1e-9)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_numpy_and_torch_paths_agree(model, dtype):
    x, u = random_rows(np.random.default_rng(1), 300)
    expected = model.predict(x, u)
    got = model.predict_torch(torch.as_tensor(x, dtype=dtype), torch.as_tensor(u, dtype=dtype))
    assert got.dtype == dtype and got.shape == (300, 4)
    # float32 positions of a few hundred metres carry ~3e-5 m of rounding on their own.
    atol = 1e-4 if dtype == torch.float32 else 1e-5
    np.testing.assert_allclose(got.detach().double().numpy(), expected, rtol=0, atol=atol)


def test_loader_errors_name_the_file(tmp_path):
    missing = tmp_path / "nope.pt"
    with pytest.raises(FileNotFoundError, match="nope.pt"):
        load_model(missing)
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(np.random.default_rng(0).bytes(2000))
    with pytest.raises(ValueError, match="garbage.pt"):
        load_model(garbage)
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(3)}, other)
    with pytest.raises(ValueError, match="other.pt"):
        load_model(other)


class Touch:
    """A pickled object that, unpickled, creates ``marker``: what a weights file must never get to do."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {shlex.quote(str(self.marker))}",)


def test_a_file_that_is_not_weights_is_refused_in_one_line_and_never_unpickled(tmp_path):
    control = tmp_path / "control"
    pickle.loads(pickle.dumps(Touch(control)))
    assert control.exists()  # the payload works: only the loader keeps it from running
    marker = tmp_path / "marker"
    files = {"object.pt": lambda p: torch.save(Touch(marker), p),  # torch's zip format, a pickled object inside
             "pickle.pt": lambda p: p.write_bytes(pickle.dumps(Touch(marker))),
             "nested.pt": lambda p: torch.save({"format": "bimp-dynamics-mlp", "meta": Touch(marker)}, p),
             "garbage.pt": lambda p: p.write_bytes(np.random.default_rng(1).bytes(3000)),
             "empty.pt": lambda p: p.write_bytes(b"")}
    messages = {}
    for name, write in files.items():
        path = tmp_path / name
        write(path)
        with pytest.raises(ValueError) as refused:
            load_model(path)
        message = messages[name] = str(refused.value)
        assert "\n" not in message and str(path) in message and "something other than model weights" in message
        assert "weights_only" not in message
        assert refused.value.__suppress_context__  # no chained traceback repeating torch's advice either
        assert not marker.exists(), name
    assert "a pickled object that calls" in messages["object.pt"] and "empty" in messages["empty.pt"]


def test_save_load_round_trip(model, tmp_path):
    path = save_model(model, tmp_path / "copy.pt")
    assert path.stat().st_size < 200_000
    x, u = random_rows(np.random.default_rng(2), 20)
    np.testing.assert_array_equal(load_model(path)(x, u), model(x, u))


def test_short_training_lowers_the_loss_and_is_seeded():
    x, u, y = generate_data(np.random.default_rng(3), DataConfig(n_sequences=20, sequence_steps=20,
                                                                 n_uniform=600, n_stop=100))
    assert len(x) == 20 * 20 + 600 + 100 and np.all(y[:, 3] >= 0)
    config = TrainConfig(seed=5, steps=300, batch_size=128, lr=3e-3, lr_final=1e-4, hidden=32)
    trained, losses = train(x, u, y, config)
    assert losses[-50:].mean() < 0.1 * losses[:50].mean()
    _, again = train(x, u, y, config)
    np.testing.assert_array_equal(losses, again)
    assert isinstance(trained, LearnedDynamics) and trained(x[:5], u[:5]).shape == (5, 4)


# --- weights files in planner configs; where `bimp train-dynamics` writes ---------------------------------------
def test_model_from_name(model, tmp_path):
    assert isinstance(model_from_name("bicycle"), BicycleModel)
    copy = save_model(model, tmp_path / "copy.pt")
    x, u = random_rows(np.random.default_rng(4), 50)
    for name in ("mlp", str(copy)):
        np.testing.assert_array_equal(model_from_name(name)(x, u), model(x, u))
    with pytest.raises(FileNotFoundError, match="nope.pt"):
        model_from_name(str(tmp_path / "nope.pt"))


def test_planner_config_rejects_a_bad_weights_file_when_built(tmp_path):
    missing = tmp_path / "nope.pt"
    with pytest.raises(ValueError, match=r"dynamics must be .*nope\.pt.*no such file"):
        EnKTSConfig(problem={"dynamics": str(missing)})
    (tmp_path / "p.yaml").write_text(f"problem: {{dynamics: {missing}}}\n")
    with pytest.raises(ValueError, match=r"dynamics .*nope\.pt"):
        load_config(EnKTSConfig, tmp_path / "p.yaml")
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a model")
    with pytest.raises(ValueError, match=r"dynamics .*garbage\.pt"):
        EnKTSConfig(problem={"dynamics": str(garbage)})
    with pytest.raises(ValueError, match="dynamics"):
        EnKTSConfig(problem={"dynamics": ""})


def test_train_dynamics_writes_under_runs_by_default_not_the_shipped_file():
    out = train_dynamics.parser().parse_args([]).out
    assert out == train_dynamics.DEFAULT_OUT and Path(out).parts[0] == "runs"
    assert Path(out).resolve() != dynamics.WEIGHTS_PATH.resolve()
    shipped = Path("planners/weights/mlp.pt")
    assert train_dynamics.parser().parse_args(["--out", str(shipped)]).out == shipped


def test_train_dynamics_main_writes_the_default_path_and_leaves_the_shipped_weights(tmp_path, monkeypatch, capsys):
    """The whole command with a toy data set and two Adam steps (the data and the report are stubbed out)."""
    shipped = hashlib.sha256(dynamics.WEIGHTS_PATH.read_bytes()).hexdigest()
    small = generate_data(np.random.default_rng(0), DataConfig(n_sequences=2, sequence_steps=5, n_uniform=50,
                                                               n_stop=10))
    monkeypatch.setattr(train_dynamics, "generate_data", lambda rng, config: small)
    monkeypatch.setattr(train_dynamics, "accuracy_report", lambda model, rng, episodes: "(report)")
    monkeypatch.chdir(tmp_path)
    assert train_dynamics.main(["--steps", "2", "--batch-size", "8"]) == 0
    written = tmp_path / "runs" / "dynamics" / "mlp.pt"
    assert isinstance(load_model(written), LearnedDynamics)
    assert capsys.readouterr().out.rstrip().splitlines()[-1].startswith(
        f"weights: {written.relative_to(tmp_path)}")
    assert train_dynamics.main(["--steps", "2", "--batch-size", "8", "--out", "elsewhere/m.pt"]) == 0
    assert (tmp_path / "elsewhere" / "m.pt").is_file()
    assert hashlib.sha256(dynamics.WEIGHTS_PATH.read_bytes()).hexdigest() == shipped
