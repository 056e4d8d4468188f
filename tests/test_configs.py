"""configs: check_fields rejects values of the wrong type, length or finiteness with the key and the value in the
message, for every config of the planners and the dynamics training; YAML loading; reconstruction of a config
from its resolved dict (``dataclasses.asdict``), through YAML and JSON."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import typing
from dataclasses import dataclass

import numpy as np
import pytest
import yaml

from bimp.configs import CONFIG_DIR, ConfigError, check_fields, load_config
from bimp.planners.dynamics_train import DataConfig, TrainConfig
from bimp.planners.enkts import EnKTSConfig
from bimp.planners.mppi import MPPIConfig
from bimp.planners.nmpc import NMPCConfig
from bimp.planners.problem import BarrierShape, ProblemConfig

CONFIGS = (EnKTSConfig, ProblemConfig, BarrierShape, MPPIConfig, NMPCConfig, DataConfig, TrainConfig)


def raises_naming(key: str, value: str):
    """pytest.raises(ValueError) whose message names ``key`` and then ``value``."""
    return pytest.raises(ValueError, match=re.escape(key) + ".*" + re.escape(value))


def yaml_file(tmp_path, text: str):
    path = tmp_path / "planner.yaml"
    path.write_text(text)
    return path


# --- the three reported cases, from YAML as users wrote them -------------------------------------------------
def test_one_entry_sigma_du_is_rejected_not_applied_to_steering(tmp_path):
    with raises_naming("sigma_du", "(0.5,)"):
        load_config(EnKTSConfig, yaml_file(tmp_path, "problem: {sigma_du: [0.5]}\n"))


def test_fractional_particle_count_is_rejected_at_load(tmp_path):
    with raises_naming("n_particles", "50.7"):
        load_config(EnKTSConfig, yaml_file(tmp_path, "n_particles: 50.7\n"))
    with raises_naming("n_particles", "50.0"):  # integral floats too: an int field takes ints only
        load_config(EnKTSConfig, yaml_file(tmp_path, "n_particles: 50.0\n"))


def test_string_no_is_not_true(tmp_path):
    with raises_naming("adapt_spread", "'no'"):
        load_config(EnKTSConfig, yaml_file(tmp_path, 'adapt_spread: "no"\n'))
    assert load_config(EnKTSConfig, yaml_file(tmp_path, "adapt_spread: no\n")).adapt_spread is False  # YAML bool


def test_errors_are_config_errors_carrying_key_and_value():
    with pytest.raises(ConfigError) as info:
        EnKTSConfig(n_particles=50.7)
    assert (info.value.key, info.value.value) == ("n_particles", 50.7)
    assert str(info.value) == "n_particles must be an int, got 50.7"
    with pytest.raises(ConfigError, match=r"^n_particles must be an int >= 2, got 1$"):
        EnKTSConfig(n_particles=1)


# --- tuples ---------------------------------------------------------------------------------------------------
def tuple_fields(cls) -> list[tuple[str, int]]:
    hints = typing.get_type_hints(cls)
    return [(f.name, len(typing.get_args(hints[f.name]))) for f in dataclasses.fields(cls)
            if typing.get_origin(hints[f.name]) is tuple]


@pytest.mark.parametrize("key,length", tuple_fields(ProblemConfig))
@pytest.mark.parametrize("delta", [-1, 1])
def test_every_tuple_field_of_the_problem_rejects_a_wrong_length(key, length, delta):
    value = [0.1] * (length + delta)
    with raises_naming(key, repr(tuple(value))):
        load_config(ProblemConfig, None, **{key: value})
    assert getattr(load_config(ProblemConfig, None, **{key: [0.1] * length}), key) == (0.1,) * length


def test_tuple_fields_found():
    assert dict(tuple_fields(ProblemConfig)) == {"sigma_du": 2, "sigma_ref": 3, "sigma_input": 2}


@pytest.mark.parametrize("bad,key", [((0.5, "x"), "sigma_du[1]"), ((0.5, True), "sigma_du[1]"),
                                     ((0.5, math.inf), "sigma_du[1]"), ((math.nan, 0.1), "sigma_du[0]"),
                                     ("0.5 0.1", "sigma_du"), (0.5, "sigma_du")])
def test_tuple_entries_are_checked(bad, key):
    with raises_naming(key, "got"):
        ProblemConfig(sigma_du=bad)


def test_lists_become_tuples_and_ints_floats():
    cfg = EnKTSConfig(problem={"sigma_du": [1, np.float32(0.5)]}, max_spread=np.int64(10), n_particles=np.int64(30))
    assert cfg.problem.sigma_du == (1.0, 0.5) and all(type(v) is float for v in cfg.problem.sigma_du)
    assert type(cfg.max_spread) is float and type(cfg.n_particles) is int
    hash(cfg)


# --- nested ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("barrier,named", [({"bogus": 1}, "bogus"), ({"width": "x"}, "width"),
                                           ({"widths": "x"}, "barrier.widths"), ({"headway": "x"}, "barrier.headway"),
                                           ({"widths": [0.1] * 5}, "barrier.widths"),
                                           ({"widths": [0.1, 0.5, 1.0, 0.01, 0.5, -1.0]}, "barrier.widths"),
                                           ({"sharpness": 0.0}, "barrier.sharpness")])
def test_nested_barrier_errors_name_barrier(tmp_path, barrier, named):
    text = yaml.safe_dump({"barrier": barrier})
    with pytest.raises(ValueError, match=r"barrier") as info:
        load_config(ProblemConfig, yaml_file(tmp_path, text))
    assert named in str(info.value)
    with pytest.raises(ValueError, match=r"barrier"):
        ProblemConfig(barrier=barrier)
    with pytest.raises(ValueError, match=r"problem.*barrier"):  # two levels down: both named
        EnKTSConfig(problem={"barrier": barrier})


def test_nested_barrier_from_mapping_and_wrong_kind():
    cfg = EnKTSConfig(problem={"barrier": {"headway": 1}})
    assert cfg.problem.barrier == BarrierShape(headway=1.0) and isinstance(cfg.problem.barrier, BarrierShape)
    with raises_naming("problem.barrier", "'tight'"):
        EnKTSConfig(problem={"barrier": "tight"})


# --- every config: types checked, defaults and the shipped file load -------------------------------------------
@pytest.mark.parametrize("cls", CONFIGS)
def test_defaults_load(cls):
    assert load_config(cls) == cls()


def test_shipped_planner_yaml_loads():
    cfg = load_config(EnKTSConfig, "planner.yaml")
    data = yaml.safe_load((CONFIG_DIR / "planner.yaml").read_text())
    assert {k: getattr(cfg, k) for k in data} == {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}


@pytest.mark.parametrize("cls", CONFIGS)
def test_every_field_of_every_config_is_type_checked(cls):
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        bad = "x" if hint is not str else 3
        with raises_naming(f.name, repr(bad)):
            cls(**{f.name: bad})
        if hint is int or int in typing.get_args(hint):
            with raises_naming(f.name, "True"):
                cls(**{f.name: True})
            with raises_naming(f.name, "2.5"):
                cls(**{f.name: 2.5})
        if hint is float:
            with raises_naming(f.name, "nan"):
                cls(**{f.name: math.nan})


def test_inf_only_where_documented():
    assert math.isinf(ProblemConfig(nu=math.inf).nu) and math.isinf(NMPCConfig(problem={"nu": math.inf}).problem.nu)
    assert math.isinf(EnKTSConfig(max_spread=math.inf).max_spread)
    for cls, key in ((ProblemConfig, "sigma_barrier"), (EnKTSConfig, "relaxation"), (MPPIConfig, "temperature"),
                     (NMPCConfig, "tol"), (TrainConfig, "lr"), (BarrierShape, "headway")):
        with raises_naming(key, "inf"):
            cls(**{key: math.inf})


@pytest.mark.parametrize("cls,key,value", [
    (EnKTSConfig, "n_particles", 1), (ProblemConfig, "horizon", 0), (ProblemConfig, "nu", 2.0),
    (EnKTSConfig, "iterations", 0), (EnKTSConfig, "max_spread", 0.5), (EnKTSConfig, "max_innovation", 0.0),
    (EnKTSConfig, "relaxation", 1.0), (ProblemConfig, "sigma_ref", (1.0, 0.0, 1.0)),
    (ProblemConfig, "sigma_barrier", -0.1), (BarrierShape, "bound_margin", 1.0), (BarrierShape, "follower_decel", 0.0),
    (MPPIConfig, "n_particles", 1), (MPPIConfig, "temperature", 0.0), (MPPIConfig, "control_cost", -1.0),
    (NMPCConfig, "keep_out_power", 3), (NMPCConfig, "hessian", "bfgs"), (NMPCConfig, "max_iter", -1),
    (ProblemConfig, "nu", 0.0), (DataConfig, "sequence_steps", 0), (DataConfig, "n_stop", -1),
    (TrainConfig, "steps", 0), (TrainConfig, "lr_final", 0.0), (TrainConfig, "lr", 1e-6)])
def test_range_errors_name_key_and_value(cls, key, value):
    with pytest.raises(ConfigError, match=f"^{re.escape(key)} must be .*, got {re.escape(repr(value))}"):
        cls(**{key: value})


# --- reconstruction from the resolved dict -----------------------------------------------------------------------
def sample_configs():
    return [EnKTSConfig(), load_config(EnKTSConfig, "planner.yaml"),
            load_config(EnKTSConfig, "planner.yaml",
                        problem={"nu": math.inf, "barrier": {"widths": [0.2] * 6}, "dynamics": "bicycle"}),
            BarrierShape(headway=1), MPPIConfig(), MPPIConfig(n_particles=20, temperature=2), NMPCConfig(),
            NMPCConfig(problem={"horizon": 7, "nu": 4.0}, hessian="limited-memory"), DataConfig(n_uniform=10),
            TrainConfig(lr=1e-3)]


@pytest.mark.parametrize("config", sample_configs(), ids=lambda c: type(c).__name__)
def test_yaml_round_trip_of_asdict_rebuilds_an_equal_config(config, tmp_path):
    path = tmp_path / "resolved.yaml"
    path.write_text(yaml.safe_dump(dataclasses.asdict(config)))
    again = load_config(type(config), path)
    assert again == config and hash(again) == hash(config)
    assert type(config)(**yaml.safe_load(path.read_text())) == config  # direct construction too


@pytest.mark.parametrize("config", sample_configs(), ids=lambda c: type(c).__name__)
def test_json_round_trip_of_asdict_rebuilds_an_equal_config(config):
    assert type(config)(**json.loads(json.dumps(dataclasses.asdict(config)))) == config


# --- the helper on a config of another module (the RLConfig case) ------------------------------------------------
@dataclass(frozen=True)
class _Other:
    name: str = "ppo"
    net_arch: tuple[int, ...] = (64, 64)
    batch_size: int | None = None
    rate: float = 3e-4
    flag: bool = False

    def __post_init__(self) -> None:
        check_fields(self)


def test_check_fields_on_any_dataclass():
    assert _Other(net_arch=[32], batch_size=np.int64(8)) == _Other(net_arch=(32,), batch_size=8)
    assert _Other(net_arch=[]).net_arch == ()
    for key, bad, shown in (("net_arch", (64, 2.5), "net_arch[1]"), ("batch_size", 2.5, "batch_size"),
                            ("flag", 1, "flag"), ("name", None, "name"), ("rate", "3e-4", "rate")):
        with raises_naming(shown, "got"):
            _Other(**{key: bad})
    with pytest.raises(ConfigError, match=r"^batch_size must be an int or None, got 2.5$"):
        _Other(batch_size=2.5)


def test_check_fields_misuse_is_a_type_error():
    with pytest.raises(TypeError):
        check_fields(_Other)
    with pytest.raises(TypeError, match="nope"):
        check_fields(_Other(), allow_inf=("nope",))


# --- a config file that is not a YAML mapping: one ValueError naming the file (issue 24) ------------------------
@pytest.mark.parametrize("content, problem", [
    (b"n_particles: [1\n", "line 2, column 1: not valid YAML"),
    (b"!!python/object/apply:os.system ['echo pwned']\n", "line 1, column 1: not valid YAML: could not determine"),
    (b"n_particles: 10\n\x00\n", "character 17: not valid YAML: special characters are not allowed"),
    (bytes(range(256)), "not a UTF-8 text file"),
])
def test_a_config_file_that_is_not_yaml_text_is_a_value_error_naming_it(tmp_path, content, problem):
    path = tmp_path / "odd.yaml"
    path.write_bytes(content)
    with pytest.raises(ValueError) as err:
        load_config(EnKTSConfig, path)
    message = str(err.value)
    assert message.startswith(f"{path}") and problem in message and "\n" not in message
    assert "<unicode string>" not in message


def test_a_config_path_that_is_a_folder_is_a_value_error_naming_it(tmp_path):
    with pytest.raises(ValueError, match=re.escape(str(tmp_path)) + ".*cannot be read"):
        load_config(EnKTSConfig, tmp_path)
