"""Data, training and the accuracy report of the learned model in :mod:`bimp.planners.dynamics` (the command:
``bimp train-dynamics``, :mod:`bimp.agents.commands.train_dynamics`).

Training data come from the env's own vehicle (:class:`bimp.envs.scenarios.EgoVehicle`, stepped directly) over the whole
envelope: speeds 0-40 m/s, the full actuator ranges, random smooth input sequences (piecewise linear between random
knots), independent uniform transitions, and rows at speed 0 or braking through 0 (the speed clamp). Half of the
sequences keep their inputs near the planning bounds, where the planners spend their time.

The report tests on data the model never saw: a fresh envelope sample (one-step RMSE per state component) and
trajectories of the two scenarios driven by random smooth inputs within the planning bounds (one-step RMSE and the
open-loop error after ``horizon`` steps from every window start). The exact :class:`BicycleModel` is reported beside
the MLP as a check that the env runs the model we think it does (its errors should be ~1e-12).

Weights go to ``--out`` (default ``runs/dynamics/mlp.pt``, relative to the working directory); the shipped file is
written only when named: reproduce it with ``bimp train-dynamics --seed 0 --out planners/weights/mlp.pt``. A planner
uses other weights through its config: ``dynamics: runs/dynamics/mlp.pt``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch

from bimp.configs import ConfigError, check_fields
from bimp.envs.scenarios import EgoVehicle
from bimp.envs.scene import ACTUATOR_ACCEL, ACTUATOR_STEER, DT, MAX_SPEED
from bimp.planners.dynamics import MLP, BicycleModel, LearnedDynamics, features

STATE_NAMES = ("x [m]", "y [m]", "heading [rad]", "speed [m/s]")


@dataclass(frozen=True)
class DataConfig:
    """Size of the generated training set. ``n_sequences`` input sequences of ``sequence_steps`` steps each,
    ``n_uniform`` independent transitions drawn uniformly over the envelope, ``n_stop`` transitions at speed 0
    or braking through 0; speeds up to ``max_speed`` m/s; steering over ``steer_limit`` rad either way (the model's
    envelope: it clips its steering input there), half the sequences near the straight roads' planning bounds."""

    n_sequences: int = 1200
    sequence_steps: int = 50
    n_uniform: int = 40_000
    n_stop: int = 8_000
    max_speed: float = MAX_SPEED
    steer_limit: float = ACTUATOR_STEER[1]

    def __post_init__(self) -> None:
        check_fields(self)
        if not self.steer_limit > 0:
            raise ConfigError("steer_limit", "a finite number > 0", self.steer_limit)
        for key in ("n_sequences", "n_uniform", "n_stop"):
            if getattr(self, key) < 0:
                raise ConfigError(key, "an int >= 0", getattr(self, key))
        if self.sequence_steps < 1:
            raise ConfigError("sequence_steps", "an int >= 1", self.sequence_steps)
        if not self.max_speed > 0:
            raise ConfigError("max_speed", "a finite number > 0", self.max_speed)


@dataclass(frozen=True)
class TrainConfig:
    """Adam on the mean squared error of the normalized one-step change; learning rate ``lr`` decays by a cosine
    to ``lr_final`` over ``steps`` minibatches of ``batch_size`` rows. ``hidden``: width of both hidden layers."""

    seed: int = 0
    steps: int = 6_000
    batch_size: int = 1024
    lr: float = 3e-3
    lr_final: float = 1e-5
    hidden: int = 128

    def __post_init__(self) -> None:
        check_fields(self)
        for key in ("steps", "batch_size", "hidden"):
            if getattr(self, key) < 1:
                raise ConfigError(key, "an int >= 1", getattr(self, key))
        if not self.lr_final > 0:
            raise ConfigError("lr_final", "a finite number > 0", self.lr_final)
        if not self.lr >= self.lr_final:
            raise ConfigError("lr", f"a finite number >= lr_final = {self.lr_final!r}", self.lr)


# --- data ----------------------------------------------------------------------------------------------------
def simulate_vehicle(x0: np.ndarray, inputs: np.ndarray, dt: float = DT) -> np.ndarray:
    """Step :class:`bimp.envs.scenarios.EgoVehicle` (no road) from states ``x0 (M, 4)`` under physical inputs
    ``inputs (M, T, 2)``; returns the states ``(M, T + 1, 4)``. One Python vehicle per row: this *is* the env's
    model, not a re-implementation of it."""
    m, t_steps = inputs.shape[:2]
    out = np.empty((m, t_steps + 1, 4))
    out[:, 0] = x0
    for i in range(m):
        ev = EgoVehicle(None, np.array(x0[i, :2], dtype=float), float(x0[i, 2]), float(x0[i, 3]))
        for t in range(t_steps):
            # A fresh dict each step, as the env's action type does: clip_actions edits it in place.
            ev.act({"acceleration": float(inputs[i, t, 0]), "steering": float(inputs[i, t, 1])})
            ev.step(dt)
            out[i, t + 1] = (ev.position[0], ev.position[1], ev.heading, ev.speed)
    return out


def smooth_inputs(rng: np.random.Generator, m: int, steps: int, accel: tuple[float, float],
                  steer: tuple[float, float]) -> np.ndarray:
    """``(m, steps, 2)`` physical inputs, each sequence piecewise linear between knots drawn uniformly in the given
    ranges every 2 to 25 steps (so both slow drifts and fast swings appear)."""
    out = np.empty((m, steps, 2))
    t = np.arange(steps)
    for i in range(m):
        spacing = int(rng.integers(2, 26))
        knots_t = np.arange(0, steps + spacing, spacing)
        for j, (lo, hi) in enumerate((accel, steer)):
            out[i, :, j] = np.interp(t, knots_t, rng.uniform(lo, hi, knots_t.size))
    return out


def _random_poses(rng: np.random.Generator, m: int) -> np.ndarray:
    return np.column_stack([rng.uniform(-500, 500, (m, 2)), rng.uniform(-np.pi, np.pi, m)])


def generate_data(rng: np.random.Generator, config: DataConfig = DataConfig()
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Transitions of the env's vehicle: states ``x (K, 4)``, inputs ``u (K, 2)``, next states ``(K, 4)``."""
    xs, us, ys = [], [], []
    steer = (-config.steer_limit, config.steer_limit)
    full = (ACTUATOR_ACCEL, steer)
    # Near the planning bounds (accel -7..3 m/s^2, |steer| <= 0.05 rad) with some room around them.
    near = ((-9.0, 5.0), (-0.08, 0.08))
    n_seq, t_seq = config.n_sequences, config.sequence_steps
    for ranges, m in ((full, n_seq - n_seq // 2), (near, n_seq // 2)):
        if m == 0:
            continue
        x0 = np.column_stack([_random_poses(rng, m), rng.uniform(0, config.max_speed, m)])
        u = smooth_inputs(rng, m, t_seq, *ranges)
        traj = simulate_vehicle(x0, u)
        xs.append(traj[:, :-1].reshape(-1, 4))
        us.append(u.reshape(-1, 2))
        ys.append(traj[:, 1:].reshape(-1, 4))
    singles = []
    if config.n_uniform:
        m = config.n_uniform
        singles.append((rng.uniform(0, config.max_speed, m), rng.uniform(*ACTUATOR_ACCEL, m)))
    if config.n_stop:
        m = config.n_stop
        # A third exactly at rest, the rest slow enough that braking crosses 0 within the step.
        v = np.where(rng.random(m) < 1 / 3, 0.0, rng.uniform(0, -ACTUATOR_ACCEL[0] * DT, m))
        singles.append((v, np.where(rng.random(m) < 0.75, rng.uniform(ACTUATOR_ACCEL[0], 0, m),
                                    rng.uniform(*ACTUATOR_ACCEL, m))))
    for v, a in singles:
        m = v.size
        x0 = np.column_stack([_random_poses(rng, m), v])
        u = np.column_stack([a, rng.uniform(*steer, m)])[:, None]
        traj = simulate_vehicle(x0, u)
        xs.append(x0)
        us.append(u[:, 0])
        ys.append(traj[:, 1])
    return np.concatenate(xs), np.concatenate(us), np.concatenate(ys)


def body_change(x: np.ndarray, x_next: np.ndarray) -> np.ndarray:
    """Inverse of :func:`bimp.planners.dynamics.apply_change`: ``[d_lon, d_lat, d_heading, d_speed] (K, 4)``."""
    c, s = np.cos(x[:, 2]), np.sin(x[:, 2])
    d = x_next - x
    return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2], d[:, 3]])


# --- training ------------------------------------------------------------------------------------------------
def train(x: np.ndarray, u: np.ndarray, x_next: np.ndarray, config: TrainConfig = TrainConfig(),
          log_every: int = 0, steer_range: tuple[float, float] = ACTUATOR_STEER) -> tuple[LearnedDynamics, np.ndarray]:
    """Fit an :class:`MLP` to transitions ``x (K, 4), u (K, 2) -> x_next (K, 4)``; returns the model and the loss
    per step ``(steps,)`` (normalized MSE). Same seed, same weights (single-threaded; the last bits may differ
    between CPU types)."""
    gen = torch.Generator().manual_seed(config.seed)
    model_limits = dict(max_speed=MAX_SPEED, accel_range=ACTUATOR_ACCEL, steer_range=tuple(steer_range))
    f = torch.as_tensor(features(x, u, **model_limits), dtype=torch.float32)
    y = torch.as_tensor(body_change(x, x_next), dtype=torch.float32)
    v = f[:, 0]
    net = MLP(config.hidden, generator=gen)
    net.set_normalization(f, y)
    opt = torch.optim.Adam(net.parameters(), lr=config.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, config.steps, eta_min=config.lr_final)
    losses = np.empty(config.steps)
    t0 = time.perf_counter()
    threads = torch.get_num_threads()
    # One thread: these matrices are too small to gain from more, and on a busy machine torch's spinning worker
    # threads make a step several times slower (measured on 2 shared cores: 9 ms with one, 45 ms with two).
    # It also keeps the result independent of the machine's thread count.
    torch.set_num_threads(1)
    try:
        for step in range(config.steps):
            idx = torch.randint(0, f.shape[0], (min(config.batch_size, f.shape[0]),), generator=gen)
            pred = net(f[idx])
            # Score what the model outputs after the speed clamp, so the net may predict a*dt below zero.
            dv = torch.clamp(v[idx] + pred[:, 3], min=0.0) - v[idx]
            pred = torch.cat([pred[:, :3], dv[:, None]], 1)
            loss = (((pred - y[idx]) / net.out_std) ** 2).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            losses[step] = loss.item()
            if log_every and (step + 1) % log_every == 0:
                print(f"  step {step + 1:6d}  loss {losses[step - log_every + 1:step + 1].mean():.3e}"
                      f"  ({time.perf_counter() - t0:.0f} s)", flush=True)
    finally:
        torch.set_num_threads(threads)
    return LearnedDynamics(net, dt=DT, **model_limits), losses


# --- held-out evaluation -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Trajectory:
    """One recorded EV run: ``states (T + 1, 4)`` (float64, from the simulator), ``inputs (T, 2)`` physical
    (``info["input"]``), of scenario ``scenario``."""

    scenario: str
    states: np.ndarray
    inputs: np.ndarray


def rollout_scenarios(rng: np.random.Generator, episodes: int = 6,
                      scenarios: tuple[str, ...] = ("bimp/Overtaking-v0", "bimp/EmergencyBrake-v0")
                      ) -> list[Trajectory]:
    """Drive each scenario ``episodes`` times with random smooth inputs inside the planning bounds (input and
    rate bounds of ``scene.bounds``) and record the EV. The steering carries a weak lane-keeping term so runs last
    long enough to give windows; an episode ends early on collision or leaving the road, and the transitions at a
    collision are dropped (highway-env pushes colliding vehicles apart, which no dynamics model predicts)."""
    out = []
    for env_id in scenarios:
        env = gym.make(env_id)
        for _ in range(episodes):
            env.reset(seed=int(rng.integers(2**31)))
            base = env.unwrapped
            scene, b = base.scene, base.scene.bounds
            ev = base.vehicle
            states, inputs = [[*ev.position, ev.heading, ev.speed]], []
            u = np.zeros(2)
            accel_target = rng.uniform(*b.accel)
            while True:
                if rng.random() < 0.08:
                    accel_target = rng.uniform(*b.accel)
                s_road, lat = scene.geometry.to_frenet(ev.position)
                heading_err = ev.heading - float(scene.geometry.heading_at(s_road))
                lane_lat = scene.geometry.lane_offset(base.ego_lane)
                steer_target = -0.004 * (lat - lane_lat) - 0.05 * heading_err + rng.normal(0, 0.02)
                du = np.array([accel_target - u[0], steer_target - u[1]])
                du += rng.normal(0, [0.3, 0.002])
                du = np.clip(du, [-b.accel_rate, -b.steer_rate], [b.accel_rate, b.steer_rate])
                u = np.clip(u + du, [b.accel[0], -b.steer], [b.accel[1], b.steer])
                clean = not ev.crashed and ev.impact is None
                _obs, _r, terminated, truncated, info = env.step(scene.to_normalized(u))
                if not clean or ev.crashed:
                    break
                states.append([*ev.position, ev.heading, ev.speed])
                inputs.append(info["input"])
                if terminated or truncated:
                    break
            out.append(Trajectory(env_id, np.array(states), np.array(inputs, dtype=float).reshape(-1, 2)))
        env.close()
    return out


def open_loop_errors(model, trajectories: list[Trajectory], horizon: int = 20, stride: int = 1
                     ) -> dict[str, np.ndarray]:
    """Predict ``horizon`` steps open loop from every ``stride``-th window start of each trajectory, all windows
    in one batch. Returns per window ``(W,)``: ``position`` [m] (Euclidean), ``heading`` [rad] and ``speed``
    [m/s] absolute errors at the window's end. ``model``: any batched ``f(x (N, 4), u (N, 2)) -> (N, 4)``."""
    starts = [(k, s) for k, tr in enumerate(trajectories)
              for s in range(0, len(tr.inputs) - horizon + 1, stride)]
    if not starts:
        return {"position": np.empty(0), "heading": np.empty(0), "speed": np.empty(0)}
    x = np.array([trajectories[k].states[s] for k, s in starts])
    for t in range(horizon):
        x = model(x, np.array([trajectories[k].inputs[s + t] for k, s in starts]))
    truth = np.array([trajectories[k].states[s + horizon] for k, s in starts])
    return {"position": np.linalg.norm(x[:, :2] - truth[:, :2], axis=1),
            "heading": np.abs(x[:, 2] - truth[:, 2]), "speed": np.abs(x[:, 3] - truth[:, 3])}


def one_step_rmse(model, x: np.ndarray, u: np.ndarray, x_next: np.ndarray) -> np.ndarray:
    """Root mean squared one-step error per state component ``(4,)`` [m, m, rad, m/s]."""
    return np.sqrt(np.mean((model(x, u) - x_next) ** 2, axis=0))


def _transitions(trajectories: list[Trajectory]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return (np.concatenate([t.states[:-1] for t in trajectories]), np.concatenate([t.inputs for t in trajectories]),
            np.concatenate([t.states[1:] for t in trajectories]))


def accuracy_report(model: LearnedDynamics, rng: np.random.Generator, episodes: int = 10, horizon: int = 20) -> str:
    """The text ``bimp train-dynamics`` prints: one-step RMSE on a fresh envelope sample and on scenario runs,
    and open-loop error after ``horizon`` steps on scenario runs, for the MLP and the exact bicycle model. The
    envelope sample spans the model's own steering range (:attr:`LearnedDynamics.steer_range`)."""
    bicycle = BicycleModel(steer_range=model.steer_range)
    lines = []
    x, u, y = generate_data(rng, DataConfig(n_sequences=200, n_uniform=10_000, n_stop=1_000,
                                            steer_limit=model.steer_range[1]))
    trajectories = rollout_scenarios(rng, episodes)
    xe, ue, ye = _transitions(trajectories)
    head = "| model | data | rows | " + " | ".join(STATE_NAMES) + " |"
    lines += ["One-step RMSE per state component (held out):", "", head, "|---" * (len(STATE_NAMES) + 3) + "|"]
    for name, m in (("MLP", model), ("bicycle", bicycle)):
        for data, (a, b, c) in (("envelope", (x, u, y)), ("scenarios", (xe, ue, ye))):
            r = one_step_rmse(m, a, b, c)
            lines.append(f"| {name} | {data} | {len(a)} | " + " | ".join(f"{v:.2e}" for v in r) + " |")
    lines += ["", f"Open-loop error after {horizon} steps ({horizon * DT:.1f} s), every window start of "
              f"{episodes} random-input runs per scenario:", "",
              "| model | scenario | windows | position median / p95 / max [m] | heading median / p95 / max [rad] "
              "| speed median / p95 / max [m/s] |", "|---|---|---|---|---|---|"]
    for name, m in (("MLP", model), ("bicycle", bicycle)):
        for scenario in sorted({t.scenario for t in trajectories}):
            e = open_loop_errors(m, [t for t in trajectories if t.scenario == scenario], horizon)
            cells = [" / ".join(f"{q:.3g}" for q in np.percentile(e[k], [50, 95, 100])) if e[k].size else "-"
                     for k in ("position", "heading", "speed")]
            lines.append(f"| {name} | {scenario} | {e['position'].size} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
