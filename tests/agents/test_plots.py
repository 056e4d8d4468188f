"""``bimp plot`` skips a record whose trace it cannot draw, with one warning naming the record and the field at fault,
and draws the rest: a malformed trace in a shared folder is never a traceback."""

import copy
import json
import math

import pytest

from bimp.agents.commands import plot as plot_command
from bimp.agents.evaluation import plots
from bimp.agents.evaluation.evaluate import evaluate
from bimp.agents.evaluation.records import EPISODES_FILE
from bimp.envs.road import RoadGeometry


def _set(path: str, value):
    """A change setting ``record[k1][k2]...`` (keys split on dots, list indices as ints) to ``value``."""
    keys = [int(k) if k.isdigit() else k for k in path.split(".")]

    def change(r):
        node = r
        for k in keys[:-1]:
            node = node[k]
        node[keys[-1]] = value
    return change


def _drop(path: str):
    *parents, last = path.split(".")

    def change(r):
        node = r
        for k in parents:
            node = node[k]
        del node[last]
    return change


def _each(name: str, edit):
    """A change applying ``edit`` to the trace series ``name``."""
    def change(r):
        r["trace"][name] = edit(r["trace"][name])
    return change


def _route(r):
    r["route"] = {"xy": [[0.0, 0.0]], "left": [-4.0], "right": [4.0]}
    del r["road"]


# name -> (change to a good record, what the warning must name)
MALFORMED = {
    "trace-a-string": (_set("trace", "x y"), "trace is 'x y', not an object"),
    "trace-a-list": (_set("trace", [1.0, 2.0]), "trace is [1.0, 2.0], not an object"),
    "missing-key": (_drop("trace.ov_xy"), "trace lacks ov_xy"),
    "no-steps": (_each("x", lambda v: []), "trace.x is not a list of at least one step"),
    "lengths-differ": (_each("y", lambda v: v[:-1]), "trace.y has"),
    "string-in-numbers": (_set("trace.speed.3", "fast"), "trace.speed[3] is 'fast', not a finite number"),
    "bool-in-numbers": (_set("trace.edge_distance.0", True), "trace.edge_distance[0] is True"),
    "nan": (_set("trace.x.2", math.nan), "trace.x[2] is nan"),
    "huge": (_set("trace.y.0", 1e300), "trace.y[0] is 1e+300"),
    "nested-wrongly": (_each("ov_xy", lambda v: [[c for ov in step for c in ov] for step in v]), "trace.ov_xy[0][0]"),
    "ragged-rows": (_each("ov_distance", lambda v: [v[0], v[1][:-1], *v[2:]]), "trace.ov_distance[1] has"),
    "input-not-pairs": (_set("trace.input.0", 0.5), "trace.input[0] is 0.5, not a list"),
    "reference-without-lane": (_each("reference", lambda v: [ref[:2] for ref in v]), "trace.reference[0]"),
    "road-a-string": (_set("road", "straight"), "road is 'straight'"),
    "road-unknown-key": (_set("road.banking", 0.1), "road is {"),
    "road-invalid": (_set("road.radius", -5.0), "road: radius and lane_width must be > 0"),
    "no-road": (_drop("road"), "neither road nor route"),
    "route-one-point": (_route, "route.xy is not a list of at least two points"),
    "bounds-missing-key": (_drop("bounds.d_min"), "bounds.d_min is None"),
    "bounds-accel-a-number": (_set("bounds.accel", 3.0), "bounds.accel is 3.0, not a list"),
}


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> dict:
    """One traced record, as ``bimp evaluate --traces`` writes it."""
    out = tmp_path_factory.mktemp("plots")
    evaluate(out=out, scenarios=["emergency-brake"], policies=["lane-keep"], episodes=1, seed=5, workers=1,
             traces=1, progress=False)
    (record,) = [json.loads(line) for line in (out / EPISODES_FILE).read_text().splitlines()]
    assert plots.trace_problem(record) is None and "road" in record
    return record


def test_a_malformed_trace_is_skipped_by_name_and_the_rest_drawn(good, tmp_path, capsys, monkeypatch):
    # A highway-env record keeps the EV's route instead of a closed-form road: drawn too.
    on_route = {**copy.deepcopy(good), "label": "good-route"}
    route = RoadGeometry(**on_route.pop("road")).route(spacing=5.0)
    on_route["route"] = {"xy": route.xy.tolist(), "left": route.left.tolist(), "right": route.right.tolist()}
    lines = [good, on_route]
    for name, (change, _) in MALFORMED.items():
        bad = {**copy.deepcopy(good), "label": f"bad-{name}"}
        change(bad)
        lines.append(bad)
    (tmp_path / EPISODES_FILE).write_text("".join(json.dumps(r) + "\n" for r in lines))
    drawn = []
    original = plots.plot_trajectories
    monkeypatch.setattr(plots, "plot_trajectories", lambda s, runs, out: drawn.append(set(runs)) or original(s, runs,
                                                                                                            out))
    written = plots.plot_all(tmp_path)
    assert [p.name for p in written] == [f"{kind}_emergency-brake.png" for kind in ("trajectories", "controls",
                                                                                    "safety")]
    assert all(p.stat().st_size > 0 for p in written)
    assert drawn == [{"lane-keep", "good-route"}]
    err = capsys.readouterr().err
    assert "Traceback" not in err
    warnings = err.strip().splitlines()
    assert len(warnings) == len(MALFORMED)  # one each, nothing for the good ones
    for number, (warning, (name, (_, fault))) in enumerate(zip(warnings, MALFORMED.items()), start=3):
        assert warning.startswith(f"bimp plot: warning: {tmp_path / EPISODES_FILE} line {number}: skipped the trace "
                                  f"of emergency-brake, bad-{name} (policy lane-keep), seed 5: ")
        assert fault in warning, (name, warning)
    assert plot_command.main([str(tmp_path)]) == 0
    captured = capsys.readouterr()
    assert len(captured.err.strip().splitlines()) == len(MALFORMED) and "Traceback" not in captured.err
    assert captured.out.split() == [str(p) for p in written]


def test_only_malformed_traces_is_nothing_to_draw_not_a_traceback(good, tmp_path, capsys):
    bad = {**copy.deepcopy(good), "trace": "x"}
    (tmp_path / EPISODES_FILE).write_text(json.dumps(bad) + "\n")
    assert plot_command.main([str(tmp_path)]) == 1
    captured = capsys.readouterr()
    assert "no traced episodes" in captured.out and "trace is 'x', not an object" in captured.err
    assert "Traceback" not in captured.err


def test_records_of_one_scenario_with_different_numbers_of_ovs_are_drawn(good, tmp_path):
    fewer = {**copy.deepcopy(good), "label": "fewer-ovs"}
    fewer["trace"]["ov_xy"] = [step[:1] for step in fewer["trace"]["ov_xy"]]
    fewer["trace"]["ov_distance"] = [step[:1] for step in fewer["trace"]["ov_distance"]]
    (tmp_path / EPISODES_FILE).write_text(json.dumps(fewer) + "\n" + json.dumps(good) + "\n")
    assert len(plots.plot_all(tmp_path)) == 3
