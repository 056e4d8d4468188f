"""Vehicle dynamics models the planners run on: ``f(x: (N, 4), u: (N, 2)) -> (N, 4)``.

State ``x = [x m, y m, heading rad, speed m/s]``, input ``u = [acceleration m/s^2, steering rad]``, one step of
``dt = 0.1`` s, rows are particles. Two models share that contract (both are plain callables, as the planners
expect):

- :class:`BicycleModel`: the exact kinematic bicycle of :class:`bimp.envs.scenarios.EgoVehicle` (highway-env's
  ``Vehicle.step`` with the speed clamped at >= 0). Ground truth for tests and a stand-in for the learned model.
- :class:`LearnedDynamics`: the paper's feedforward MLP (section V; two hidden layers of 128), trained on
  transitions of that same vehicle model by ``bimp train-dynamics`` (:mod:`bimp.planners.dynamics_train`), shipped as
  ``planners/weights/mlp.pt`` and loaded with :func:`load_model`.

The MLP does not see the pose. The bicycle model is invariant to translation *and* rotation, so the network maps
``[speed, acceleration, steering]`` to the step's change in the body frame ``[d_lon, d_lat, d_heading, d_speed]``
and the position change is rotated back by the heading. Learning that 3 -> 4 map is easy and the symmetry holds by
construction, not approximately. What the network need not learn is applied exactly around it, because it is a
hard limit of the env rather than physics: inputs are clipped to the actuator ranges (the env clips the action),
highway-env's acceleration cap above ``max_speed`` is applied to the input, and the next speed is clamped at 0.
"""

from __future__ import annotations

import functools
import pickle
import re
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from bimp.configs import ConfigError, file_sha256

# The env's vehicle and actuators, from the module that defines them without loading highway-env and pygame.
from bimp.envs.scene import ACTUATOR_ACCEL, ACTUATOR_STEER, DT, MAX_SPEED, VEHICLE_LENGTH, Scene, scene_batch

WEIGHTS_PATH = Path(__file__).resolve().parent / "weights" / "mlp.pt"
CHECKPOINT_FORMAT = "bimp-dynamics-mlp"
CHECKPOINT_VERSION = 1

STATE_DIM, INPUT_DIM = 4, 2
N_FEATURES, N_OUTPUTS = 3, 4


def _check_batch(x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(x, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != STATE_DIM or u.shape != (x.shape[0], INPUT_DIM):
        raise ValueError(f"expected x (N, {STATE_DIM}) and u (N, {INPUT_DIM}), got {x.shape} and {u.shape}")
    return x, u


def _validate_limits(dt: float, max_speed: float, accel_range: tuple[float, float],
                     steer_range: tuple[float, float]) -> None:
    if not dt > 0:
        raise ValueError(f"dt must be > 0, got {dt}")
    if not max_speed > 0:
        raise ValueError(f"max_speed must be > 0, got {max_speed}")
    for name, (lo, hi) in (("accel_range", accel_range), ("steer_range", steer_range)):
        if not lo < hi:
            raise ValueError(f"{name} must be (lo, hi) with lo < hi, got {(lo, hi)}")


@dataclass(frozen=True)
class BicycleModel:
    """Exact one-step model of :class:`bimp.envs.scenarios.EgoVehicle` (highway-env ``Vehicle.step``), batched.

    ``beta = arctan(tan(delta) / 2)``; ``x += v cos(h + beta) dt``; ``y += v sin(h + beta) dt``;
    ``h += v sin(beta) / (L / 2) dt``; ``v = max(v + a dt, 0)``, where highway-env first caps the acceleration at
    ``max_speed - v`` when ``v > max_speed`` (so speeds overshoot 40 m/s by at most one step's worth).

    dt [s], length L [m], max_speed [m/s]; accel_range [m/s^2] and steer_range [rad] are the actuator ranges.
    ``clip_inputs``: clip ``u`` to them first, as the env does to every action; ``False`` gives the bare
    ``Vehicle.step``. Not modelled: the post-crash override and collision impulses of highway-env.
    """

    dt: float = DT
    length: float = VEHICLE_LENGTH
    max_speed: float = MAX_SPEED
    accel_range: tuple[float, float] = ACTUATOR_ACCEL
    steer_range: tuple[float, float] = ACTUATOR_STEER
    clip_inputs: bool = True

    def __post_init__(self) -> None:
        _validate_limits(self.dt, self.max_speed, self.accel_range, self.steer_range)
        if not self.length > 0:
            raise ValueError(f"length must be > 0, got {self.length}")

    def predict(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Next states ``(N, 4)`` float64 for states ``x (N, 4)`` and physical inputs ``u (N, 2)``."""
        x, u = _check_batch(x, u)
        h, v = x[:, 2], x[:, 3]
        a, delta = u[:, 0], u[:, 1]
        if self.clip_inputs:
            a = np.clip(a, *self.accel_range)
            delta = np.clip(delta, *self.steer_range)
        # Vehicle.clip_actions with EgoVehicle.MIN_SPEED = 0.
        a = np.where(v > self.max_speed, np.minimum(a, self.max_speed - v), np.where(v < 0.0, np.maximum(a, -v), a))
        beta = np.arctan(0.5 * np.tan(delta))
        out = np.empty_like(x)
        out[:, 0] = x[:, 0] + v * np.cos(h + beta) * self.dt
        out[:, 1] = x[:, 1] + v * np.sin(h + beta) * self.dt
        out[:, 2] = h + v * np.sin(beta) / (self.length / 2) * self.dt
        out[:, 3] = np.maximum(v + a * self.dt, 0.0)
        return out

    __call__ = predict


class MLP(nn.Module):
    """Feedforward net ``[v m/s, a m/s^2, delta rad] (N, 3) -> [d_lon m, d_lat m, d_heading rad, d_speed m/s]
    (N, 4)``: the one-step change in the body frame at the step's start, in physical units.

    Two tanh hidden layers of ``hidden`` units (paper V: 128). Input and output normalization are buffers
    (``in_mean``, ``in_std``, ``out_mean``, ``out_std``), set from the training data with :meth:`set_normalization`,
    so the state dict is the whole model. ``generator`` seeds the initial weights without the global RNG.
    """

    def __init__(self, hidden: int = 128, generator: torch.Generator | None = None) -> None:
        super().__init__()
        if hidden < 1:
            raise ValueError(f"hidden must be >= 1, got {hidden}")
        self.hidden = hidden
        self.net = nn.Sequential(
            nn.Linear(N_FEATURES, hidden), nn.Tanh(),
            nn.Linear(hidden, hidden), nn.Tanh(),
            nn.Linear(hidden, N_OUTPUTS),
        )
        for layer in self.net:
            if isinstance(layer, nn.Linear):
                # PyTorch's default Linear init, drawn from our generator.
                bound = 1.0 / np.sqrt(layer.in_features)
                nn.init.uniform_(layer.weight, -bound, bound, generator=generator)
                nn.init.uniform_(layer.bias, -bound, bound, generator=generator)
        self.register_buffer("in_mean", torch.zeros(N_FEATURES))
        self.register_buffer("in_std", torch.ones(N_FEATURES))
        self.register_buffer("out_mean", torch.zeros(N_OUTPUTS))
        self.register_buffer("out_std", torch.ones(N_OUTPUTS))

    def set_normalization(self, features: torch.Tensor, targets: torch.Tensor) -> None:
        """Standardize by the training data: ``features (M, 3)``, ``targets (M, 4)``, physical units."""
        with torch.no_grad():
            self.in_mean.copy_(features.mean(0))
            self.in_std.copy_(features.std(0).clamp_min(1e-6))
            self.out_mean.copy_(targets.mean(0))
            self.out_std.copy_(targets.std(0).clamp_min(1e-6))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """``[v, a, delta] (N, 3)`` -> ``[d_lon, d_lat, d_heading, d_speed] (N, 4)``, physical units."""
        return self.net((features - self.in_mean) / self.in_std) * self.out_std + self.out_mean


def features(x: np.ndarray | torch.Tensor, u: np.ndarray | torch.Tensor, max_speed: float,
             accel_range: tuple[float, float], steer_range: tuple[float, float]):
    """Network input ``[v, a, delta] (N, 3)`` from ``x (N, 4)``, ``u (N, 2)``, numpy or torch alike.

    The inputs are clipped to the actuator ranges (the env clips every action, and the net was trained on those
    ranges only: beyond them it would extrapolate) and highway-env's acceleration cap above ``max_speed`` is applied.
    """
    xp = torch if isinstance(x, torch.Tensor) else np
    v = x[:, 3]
    a = xp.clip(u[:, 0], *accel_range)
    delta = xp.clip(u[:, 1], *steer_range)
    a = xp.where(v > max_speed, xp.minimum(a, max_speed - v), a)
    return xp.stack([v, a, delta], 1)


def apply_change(x, change, xp=np):
    """Next state ``(N, 4)`` from ``x (N, 4)`` and the body-frame change ``(N, 4)``; numpy (``xp=np``) or torch.

    Rotates ``[d_lon, d_lat]`` by the heading at the step's start and clamps the next speed at 0.
    """
    h = x[:, 2]
    c, s = xp.cos(h), xp.sin(h)
    d_lon, d_lat = change[:, 0], change[:, 1]
    return xp.stack([
        x[:, 0] + c * d_lon - s * d_lat,
        x[:, 1] + s * d_lon + c * d_lat,
        h + change[:, 2],
        xp.clip(x[:, 3] + change[:, 3], 0.0, None),
    ], 1)


class LearnedDynamics:
    """The trained :class:`MLP` as a batched dynamics model ``f(x (N, 4), u (N, 2)) -> (N, 4)``.

    :meth:`predict` (also ``__call__``) is pure numpy with the normalization folded into the first and last layers;
    :meth:`predict_torch` runs the module itself on tensors. Both evaluate the network in float32 and the pose update
    in float64 (numpy) or the dtype of ``x`` (torch), so they agree to float32 rounding (~1e-6 relative). float32
    is ample here: the network's own error is ~1e-3 of its outputs, and numpy's float64 products are 2-4x slower.
    ``benchmarks/bench_dynamics.py`` times both paths. For N in the thousands numpy's BLAS goes multi-threaded;
    on a busy machine that is several times slower than one thread (``OPENBLAS_NUM_THREADS=1``).

    ``dt`` [s] is the step the model was trained for (check it against the scene's); max_speed [m/s], accel_range
    [m/s^2], steer_range [rad] as in :class:`BicycleModel`: inputs are clipped to the actuator ranges, the net has
    never seen anything beyond them. States are expected to have speed >= 0, as the env's do.
    """

    def __init__(self, net: MLP, dt: float = DT, max_speed: float = MAX_SPEED,
                 accel_range: tuple[float, float] = ACTUATOR_ACCEL,
                 steer_range: tuple[float, float] = ACTUATOR_STEER) -> None:
        _validate_limits(dt, max_speed, accel_range, steer_range)
        self.net = net.to(torch.float32).eval()
        self.dt, self.max_speed = float(dt), float(max_speed)
        self.accel_range = (float(accel_range[0]), float(accel_range[1]))
        self.steer_range = (float(steer_range[0]), float(steer_range[1]))
        self._nets_on: dict[torch.device, MLP] = {torch.device("cpu"): self.net}
        self._fold_weights()

    def _fold_weights(self) -> None:
        """float32 numpy weights, transposed for ``rows @ W``, with ``(f - in_mean) / in_std`` folded into layer 1
        and ``* out_std + out_mean`` into layer 3: the numpy path is three affine maps and two tanh. Folded in
        float64, then rounded once."""
        sd = {k: t.detach().to(torch.float64).numpy() for k, t in self.net.state_dict().items()}
        w1 = sd["net.0.weight"] / sd["in_std"]
        b1 = sd["net.0.bias"] - w1 @ sd["in_mean"]
        w3 = sd["net.4.weight"] * sd["out_std"][:, None]
        b3 = sd["net.4.bias"] * sd["out_std"] + sd["out_mean"]
        f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
        self._w = [f32(w1.T), f32(sd["net.2.weight"].T), f32(w3.T)]
        self._b = [f32(b1), f32(sd["net.2.bias"]), f32(b3)]

    def change(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Body-frame one-step change ``[d_lon m, d_lat m, d_heading rad, d_speed m/s] (N, 4)`` float32, before the
        speed clamp, for ``x (N, 4)``, ``u (N, 2)``."""
        return self._change(*_check_batch(x, u))

    def _change(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        # The planner calls this once per horizon step: every numpy call here costs microseconds at N = 50.
        v = x[:, 3]
        f = np.empty((x.shape[0], N_FEATURES), dtype=np.float32)
        f[:, 0] = v
        # minimum/maximum rather than np.clip, which costs several microseconds more on small arrays.
        a = np.minimum(np.maximum(u[:, 0], self.accel_range[0]), self.accel_range[1])
        if v.size and v.max() > self.max_speed:
            a = np.where(v > self.max_speed, np.minimum(a, self.max_speed - v), a)
        f[:, 1] = a
        f[:, 2] = np.minimum(np.maximum(u[:, 1], self.steer_range[0]), self.steer_range[1])
        h = f @ self._w[0]
        h += self._b[0]
        np.tanh(h, out=h)
        h = h @ self._w[1]
        h += self._b[1]
        np.tanh(h, out=h)
        out = h @ self._w[2]
        out += self._b[2]
        return out

    def predict(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Next states ``(N, 4)`` float64 for states ``x (N, 4)`` and physical inputs ``u (N, 2)``."""
        x, u = _check_batch(x, u)
        d = self._change(x, u)
        h = x[:, 2]
        c, s = np.cos(h), np.sin(h)
        out = np.empty_like(x)
        out[:, 0] = x[:, 0] + c * d[:, 0] - s * d[:, 1]
        out[:, 1] = x[:, 1] + s * d[:, 0] + c * d[:, 1]
        out[:, 2] = h + d[:, 2]
        out[:, 3] = np.maximum(x[:, 3] + d[:, 3], 0.0)
        return out

    __call__ = predict

    def predict_torch(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """:meth:`predict` on tensors ``x (N, 4)``, ``u (N, 2)``: returns ``(N, 4)`` in the dtype and on the device
        of ``x``. Differentiable (autograd flows through the network) though the planners need no gradient."""
        if x.ndim != 2 or x.shape[1] != STATE_DIM or tuple(u.shape) != (x.shape[0], INPUT_DIM):
            raise ValueError(f"expected x (N, {STATE_DIM}) and u (N, {INPUT_DIM}), got {tuple(x.shape)} and "
                             f"{tuple(u.shape)}")
        net = self._net_on(x.device)
        f = features(x, u.to(dtype=x.dtype, device=x.device), self.max_speed, self.accel_range, self.steer_range)
        change = net(f.to(torch.float32)).to(x.dtype)
        return apply_change(x, change, xp=torch)

    def _net_on(self, device: torch.device) -> MLP:
        if device not in self._nets_on:
            self._nets_on[device] = MLP(self.net.hidden).to(device)
            self._nets_on[device].load_state_dict(self.net.state_dict())
            self._nets_on[device].eval()
        return self._nets_on[device]

    def metadata(self) -> dict[str, Any]:
        """What a checkpoint stores beside the weights."""
        return {"dt": self.dt, "max_speed": self.max_speed, "accel_range": list(self.accel_range),
                "steer_range": list(self.steer_range), "hidden": self.net.hidden}


def save_model(model: LearnedDynamics, path: str | Path, extra: dict[str, Any] | None = None) -> Path:
    """Write ``model`` as a weights-only checkpoint (float32 state dict + plain metadata) to ``path``.

    ``extra``: plain data (numbers, strings, lists, dicts) stored under ``"training"``, e.g. the training config.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().to(torch.float32).cpu().clone() for k, v in model.net.state_dict().items()}
    torch.save({"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "state_dict": state,
                "meta": model.metadata(), "training": extra or {}}, path)
    return path


def _load_failure(err: Exception) -> str:
    """What a failed weights-only load met, in a few words: the code a pickled object would have called, else the
    error's type."""
    found = re.search(r"GLOBAL (\S+)", str(err))  # "Trying to load unsupported GLOBAL posix.system whose module..."
    if found:
        return f"a pickled object that calls {found.group(1)}"
    if isinstance(err, EOFError):
        return "empty or cut short"
    return "not a torch weights file" if isinstance(err, pickle.UnpicklingError) else type(err).__name__


def load_model(path: str | Path | None = None) -> LearnedDynamics:
    """Load the learned model from ``path`` (default: the shipped ``planners/weights/mlp.pt``). No network access.

    Raises ``FileNotFoundError`` if the file is missing and ``ValueError`` naming the file if it is not a
    checkpoint written by :func:`save_model` (corrupt, truncated, or of another format).
    """
    path = Path(WEIGHTS_PATH if path is None else path)
    if not path.is_file():
        raise FileNotFoundError(f"dynamics model weights not found: {path} "
                                f"(run `bimp train-dynamics --out {path}` to create them)")
    try:
        with warnings.catch_warnings():  # torch warns of a pickle protocol it did not write: the refusal says enough
            warnings.simplefilter("ignore", UserWarning)
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises several types for a bad file (UnpicklingError, RuntimeError, EOF...)
        # torch's own message is paragraphs long and advises weights_only=False, which would run whatever a
        # pickled object in the file says: one line instead, and `from None` so no traceback repeats that advice.
        raise ValueError(f"refused {path}: it holds something other than model weights ({_load_failure(err)}); "
                         "give a file written by `bimp train-dynamics`") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path} is not a bimp dynamics checkpoint (format {CHECKPOINT_FORMAT!r} expected)")
    if ckpt.get("version") != CHECKPOINT_VERSION:
        raise ValueError(f"{path} has checkpoint version {ckpt.get('version')!r}, expected {CHECKPOINT_VERSION}")
    try:
        meta = ckpt["meta"]
        net = MLP(int(meta["hidden"]))
        net.load_state_dict(ckpt["state_dict"])
        model = LearnedDynamics(net, dt=meta["dt"], max_speed=meta["max_speed"],
                                accel_range=tuple(meta["accel_range"]), steer_range=tuple(meta["steer_range"]))
    except (KeyError, TypeError, RuntimeError, ValueError) as err:
        raise ValueError(f"malformed dynamics checkpoint {path}: {type(err).__name__}: {err}") from err
    if not all(np.all(np.isfinite(w)) for w in model._w + model._b):
        raise ValueError(f"dynamics checkpoint {path} holds non-finite weights")
    return model


DYNAMICS_NAMES = ("mlp", "bicycle")


def check_dynamics(name: str, key: str = "dynamics") -> None:
    """Raise :class:`bimp.configs.ConfigError` unless ``name`` is ``"mlp"``, ``"bicycle"`` or the path of a readable
    weights file written by ``bimp train-dynamics`` (the file is loaded once here, so a bad path fails when the
    config is built, not at the first action)."""
    if name in DYNAMICS_NAMES:
        return
    requirement = "'mlp', 'bicycle' or the path of a weights file written by `bimp train-dynamics`"
    try:
        load_model(name)
    except FileNotFoundError:
        raise ConfigError(key, requirement, name, f"no such file: {Path(name).resolve()}") from None
    except ValueError as err:
        raise ConfigError(key, requirement, name, str(err)) from None


# The shipped learned models, narrowest envelope first: "mlp" is the first whose steering range covers the road's
# planning bound (the paper's ±0.3 rad model on the straight roads and the 0.3 rad curves, the ±0.8 rad one on the
# racetrack's and the intersection's tighter curves), so a road's planners never plan past what their model knows.
SHIPPED_WEIGHTS = (WEIGHTS_PATH, WEIGHTS_PATH.with_name("mlp-wide.pt"))


def _steer_cover(path: Path) -> float:
    """The steering [rad] either way that the weights at ``path`` cover (read once per file version)."""
    return _cover(str(Path(path).resolve()), Path(path).stat().st_mtime_ns if Path(path).is_file() else 0)


@functools.lru_cache(maxsize=None)
def _cover(path: str, _version: int) -> float:
    low, high = load_model(path).steer_range
    return min(-low, high)


def weights_for(name: str, steer_bound: float = 0.0) -> Path | None:
    """The weights file a config's ``dynamics`` names on a road whose planning steering bound is ``steer_bound``
    [rad] (None for the exact bicycle): for ``"mlp"`` the first of :data:`SHIPPED_WEIGHTS` whose steering range
    covers it; for a path, that file. ``ValueError`` naming both when the model's range does not cover the bound: a
    planner would plan steering its model clips (a road whose curves need more than any model covers is refused)."""
    if name == "bicycle":
        return None
    if name == "mlp":
        for path in SHIPPED_WEIGHTS:
            if _steer_cover(path) >= steer_bound - 1e-9:
                return path
        raise ValueError(f"no shipped dynamics model covers this road's steering bound of {steer_bound:g} rad (the "
                         f"widest covers {_steer_cover(SHIPPED_WEIGHTS[-1]):g}): train one with `bimp train-dynamics "
                         "--steer-limit RAD` and name it in problem.dynamics")
    cover = _steer_cover(Path(name))
    if cover < steer_bound - 1e-9:
        raise ValueError(f"dynamics {name} covers steering up to {cover:g} rad, but this road's planning bound is "
                         f"{steer_bound:g} rad: use problem.dynamics=mlp (the shipped model that covers it) or a model "
                         f"trained with `bimp train-dynamics --steer-limit {steer_bound:g}` or more")
    return Path(name)


def dynamics_files(name: str, steer_bound: float = 0.0) -> tuple[dict[str, str], dict[str, str]]:
    """``(files, artifacts)`` of the model a planner config's ``problem.dynamics`` names on a road with planning
    steering bound ``steer_bound`` (:func:`weights_for`), keyed by that config key: ``files`` its weights file by
    content, ``{"problem.dynamics": sha256}`` (``{}`` for the exact bicycle, which loads no file), so a policy's
    config hash follows the weights, not where they lie (:func:`bimp.agents.evaluation.provenance.config_hash`);
    ``artifacts`` the file by name (``bimp:planners/weights/mlp.pt`` for shipped weights, else the path as given), shown
    apart, not hashed."""
    path = weights_for(name, steer_bound)
    if path is None:
        return {}, {}
    shown = f"bimp:planners/weights/{path.name}" if name == "mlp" else name
    return {"problem.dynamics": file_sha256(path)}, {"problem.dynamics": shown}


def model_from_name(name: str, steer_bound: float = 0.0) -> BicycleModel | LearnedDynamics:
    """The model a planner config's ``dynamics`` names on a road with planning steering bound ``steer_bound``:
    ``"mlp"`` the shipped weights that cover it (:func:`weights_for`), ``"bicycle"`` the exact
    :class:`BicycleModel` (its steering clipped at the paper's actuator range or the bound, the wider), anything else
    the path of a weights file written by ``bimp train-dynamics`` (relative to the working directory; errors of
    :func:`load_model` name the file, and one whose range does not cover the bound is refused naming both)."""
    path = weights_for(name, steer_bound)
    if path is None:
        reach = max(ACTUATOR_STEER[1], steer_bound)
        return BicycleModel() if reach == ACTUATOR_STEER[1] else BicycleModel(steer_range=(-reach, reach))
    return load_model(path)


def steer_bound(scenes: Scene | Sequence[Scene]) -> float:
    """The widest planning steering bound [rad] of a scene or scenes (what the planner's model must cover)."""
    return max(float(scene.bounds.steer) for scene in scene_batch(scenes))


__all__ = ["BicycleModel", "LearnedDynamics", "MLP", "SHIPPED_WEIGHTS", "WEIGHTS_PATH", "apply_change",
           "dynamics_files", "features", "load_model", "model_from_name", "save_model", "steer_bound", "weights_for"]
