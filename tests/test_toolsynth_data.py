"""toolsynth's tasks, tools and dataset: the geometric labeller on hand-made cases, the simulator's
agreement with it, and `physint dataset toolsynth` on two backends."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from conftest import call

from physint_cli.datasets import ShardedDataset
from physint_plugins.toolsynth import feasibility, tools
from physint_plugins.toolsynth.tasks import LINE_X, LINE_Y, TYPES, Task, sample_task
from physint_plugins.toolsynth.tools import Tool

OPEN = Task("A", (0.0, 0.0))
GAP = Task("B", (0.0, 0.0), [(-LINE_X, -0.1, -0.015, -0.04), (0.015, -0.1, LINE_X, -0.04)])  # a 3 cm gap
WALL = Task("C", (0.0, 0.0), [(-0.1, -0.055, 0.1, -0.025)])  # open 10 cm beyond the target at both ends
CORNER = Task("D", (0.0, 0.0), [(-LINE_X, -0.055, 0.07, -0.025)])  # open on the right only


@pytest.mark.parametrize("task, tool, feasible", [
    (OPEN, Tool("stick", 0.30, 0.02), True),  # long enough to cross the line 22 cm below the target
    (OPEN, Tool("stick", 0.15, 0.02), False),
    (GAP, Tool("stick", 0.35, 0.015), True),
    (GAP, Tool("stick", 0.35, 0.045), False),  # wider than the gap
    (GAP, Tool("stick", 0.15, 0.015), False),  # thin but short
    (WALL, Tool("stick", 0.45, 0.02), False),  # no straight tool within 60 degrees passes a wall
    (WALL, Tool("hook", 0.40, 0.02, 0.14, 1), True),  # a hook long enough to reach round its end
    (WALL, Tool("hook", 0.40, 0.02, 0.04, 1), False),
    (CORNER, Tool("hook", 0.40, 0.02, 0.10, -1), True),  # handle beyond the open end, hook pointing back
    (CORNER, Tool("hook", 0.40, 0.02, 0.10, 1), False),  # the same hook mirrored
    (CORNER, Tool("stick", 0.45, 0.02), False),
])
def test_geometric_check_on_hand_made_cases(task, tool, feasible):
    verdict = feasibility.check(tool.footprint(), task)
    assert verdict.feasible is feasible
    if feasible:  # the witness pose crosses the line and keeps clear of every obstacle
        from shapely import affinity
        from shapely.geometry import box

        posed = affinity.rotate(affinity.translate(tool.footprint(), -verdict.point[0], -verdict.point[1]),
                                verdict.angle, origin=(0, 0), use_radians=True)
        posed = affinity.translate(posed, *task.target)
        assert posed.bounds[1] < LINE_Y and abs(np.degrees(verdict.angle)) <= 60 + 1e-6
        assert all(posed.distance(box(*o)) >= feasibility.CLEARANCE - 1e-9 for o in task.obstacles)


def test_check_judges_a_mesh_footprint_as_it_judges_the_outline():
    hook = Tool("hook", 0.40, 0.02, 0.14, 1)
    mesh = hook.mesh()
    shape = feasibility.mesh_footprint(mesh.vertices, mesh.faces)
    assert abs(shape.area - hook.footprint().area) < 1e-4
    assert feasibility.check(shape, WALL).feasible and not feasibility.check(shape, CORNER).feasible
    assert not feasibility.check(None, OPEN).feasible  # a mesh with no area from above reaches nothing


def test_footprint_of_a_folded_closed_mesh_needs_only_its_counter_clockwise_triangles():
    rng = np.random.default_rng(0)
    for _ in range(5):  # icospheres pulled about until they fold through themselves
        sphere = trimesh.creation.icosphere(subdivisions=2)
        vertices = sphere.vertices * [0.1, 0.2, 0.02] + rng.normal(0, 0.03, sphere.vertices.shape)
        half = feasibility.mesh_footprint(vertices, sphere.faces, simplify=0.0)
        every = feasibility.mesh_footprint(vertices, sphere.faces, simplify=0.0, closed=False)
        assert half.symmetric_difference(every).area < 1e-4 * every.area
    # an open mesh needs all of them: one triangle seen from below has no counter-clockwise one
    flipped = np.array([[0, 0, 0], [0, 0.1, 0], [0.1, 0, 0]])
    assert feasibility.mesh_footprint(flipped, [[0, 1, 2]]) is None
    assert feasibility.mesh_footprint(flipped, [[0, 1, 2]], closed=False).area == pytest.approx(0.005, rel=1e-3)


def test_every_type_has_feasible_and_infeasible_tools():
    rng = np.random.default_rng(0)
    for kind in TYPES:
        verdicts = [feasibility.check(tools.sample_tool(rng).footprint(), sample_task(kind, rng)).feasible
                    for _ in range(300)]
        assert 0.02 < np.mean(verdicts) < 0.98, kind


def test_tool_meshes_are_closed_and_export(tmp_path):
    for tool in (Tool("stick", 0.3, 0.02), Tool("hook", 0.3, 0.03, 0.1, -1)):
        mesh = tool.mesh()
        assert mesh.is_watertight and abs(mesh.volume - tool.footprint().area * tools.THICKNESS) < 1e-6
        for suffix in (".obj", ".stl"):
            path = tools.export_mesh(mesh, tmp_path / f"{tool.kind}{suffix}")
            assert abs(trimesh.load(path, force="mesh").volume - mesh.volume) < 1e-6


@pytest.fixture(scope="module")
def tiny_datasets(tmp_path_factory):
    out = {}
    for backend in ("mujoco", "pybullet"):
        root = tmp_path_factory.mktemp("toolsynth") / backend
        code, stdout, err = call("dataset", "toolsynth", "--preset", "tiny", "--backend", backend,
                                 "--out", str(root), "--json")
        assert code == 0, err
        out[backend] = root, json.loads(stdout)
    return out


@pytest.mark.parametrize("backend", ["mujoco", "pybullet"])
def test_tiny_dataset_is_balanced_rendered_and_labelled_by_the_check(tiny_datasets, backend):
    root, result = tiny_datasets[backend]
    stats = result["stats"]
    assert stats["records"] == 124 and stats["sim_checked"] > 0 and stats["sim_agreement"] >= 0.8
    train, test = ShardedDataset(root, "train"), ShardedDataset(root, "test")
    train_types = [TYPES[int(t)] for t in train.column("type")]
    assert sorted(set(train_types)) == ["A", "B", "C", "D"]  # E held out of training
    assert sorted({TYPES[int(t)] for t in test.column("type")}) == list(TYPES)
    for split in (train, test):
        labels, types = split.column("label"), split.column("type")
        for t in set(types.tolist()):
            assert abs(labels[types == t].mean() - 0.5) <= 0.25  # balanced per type
    for i in range(0, len(train), 7):
        r = train[i]
        assert r["task"].shape == (32, 32, 3) and r["tool_rgb"].shape == (2, 32, 32, 3)
        assert r["tool_sil"].shape == (2, 32, 32) and 0 < r["tool_sil"].mean() < 255
        task = Task.from_record(r["type"], r["target"], r["obstacles"], r["n_obstacles"])
        assert feasibility.check(Tool.from_array(r["tool"]).footprint(), task).feasible == bool(r["label"])
        green = (r["task"][..., 1] > 150) & (r["task"][..., 0] < 100)
        assert green.any()  # the target button is in the task image


def test_unknown_scenario_type_exits_2(tmp_path):
    code, _, err = call("dataset", "toolsynth", "--preset", "tiny", "--set", "data.train_types=ABX",
                        "--out", str(tmp_path / "d"))
    assert code == 2 and "unknown scenario type X" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "d").exists()
