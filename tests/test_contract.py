"""The plugin contract: what train leaves in a run, what eval and deploy receive, registries that
refuse a taken name, scenes and metrics that other plugins reach, and config ranges."""

from __future__ import annotations

import json
import types
from pathlib import Path

from conftest import call

from physint_cli import hookimpl


def one_json(out: str) -> dict:
    lines = [line for line in out.splitlines() if line.strip()]
    assert len(lines) == 1, out
    return json.loads(lines[0])


def test_a_method_that_trains_without_fit_runs_the_pipeline_and_beats_the_mean(toy_plugins, tmp_path):
    code, out, err = call("pipeline", "lsq", "--preset", "tiny", "--out", str(tmp_path / "p"), "--json", "--quiet")
    assert code == 0, err
    result = one_json(out)
    checkpoint = Path(result["train"]["checkpoint"])
    assert checkpoint.is_file() and checkpoint.name == "best.pt"  # the JSON names a file that exists
    metrics = result["eval"]["metrics"]
    # least squares on y = 2x + 1 with noise 0.01: far better than predicting the mean
    assert metrics["test_mse"] < 0.01 * metrics["baseline_mse"]
    assert abs(result["deploy"]["metrics"]["y"] - 1.0) < 0.05  # deploy at x = 0 (no --target)
    # eval and deploy without --run find this run as the latest trained one (it has no last.pt)
    assert not (checkpoint.parent / "last.pt").exists()
    code, out, err = call("train", "lsq", "--preset", "tiny", "--json", "--quiet")
    assert code == 0, err
    trained = one_json(out)["run"]
    code, out, err = call("eval", "lsq", "--json", "--quiet")
    assert code == 0, err
    assert one_json(out)["source_run"] == trained


def test_a_train_that_saves_nothing_is_a_clear_failure_naming_the_contract(toy_plugins, tmp_path):
    code, out, err = call("train", "lsq", "--preset", "tiny", "--set", "train.model=forget", "--out",
                          str(tmp_path / "run"))
    assert code == 1 and out == ""
    assert "without saving a trained model" in err and "save_trained" in err and "Traceback" not in err


def test_a_name_taken_by_another_plugin_is_refused_and_reported(toy_plugins):
    from toy_plugin import Toy

    from physint_cli.registry import ModelInfo, SceneInfo

    class Impostor(Toy):
        description = "another plugin's method of the same name"

    impostor = types.SimpleNamespace(
        register_methods=hookimpl(lambda register: register(Impostor())),
        register_models=hookimpl(lambda register: (register(ModelInfo("linear", method="toy", build=dict)),
                                                   register(ModelInfo("linear", method="lsq", build=dict)))),
        register_scenes=hookimpl(lambda register: register(SceneInfo("line", method="toy"))),
    )
    toy_plugins.add(impostor, "impostor")
    assert toy_plugins.registry.methods["toy"].description == "y = 2x + 1"  # the first stays
    assert toy_plugins.models_for("toy")["linear"].plugin == "toy"
    assert toy_plugins.models_for("lsq")["linear"].plugin == "impostor"  # another method's name is free
    refused = "\n".join(toy_plugins.conflicts)
    assert len(toy_plugins.conflicts) == 3, refused
    assert "method 'toy' registered by plugin 'impostor' is refused: plugin 'toy' registered it first" in refused
    assert "model 'linear' of method 'toy'" in refused and "scene 'line' of method 'toy'" in refused
    code, out, _ = call("plugins", "--json")
    assert code == 0 and one_json(out)["conflicts"] == toy_plugins.conflicts
    code, out, _ = call("plugins")
    assert "conflict:" in out and "impostor" in out


def test_scene_choices_come_from_the_registry_and_scenes_are_reachable(toy_plugins):
    toy = toy_plugins.method("toy")
    assert toy.scenes == ("line", "curve")  # registered by the plugin, in order
    assert toy_plugins.method("lsq").scenes == ("line",)  # registers none: its own tuple
    code, _, err = call("dataset", "toy", "--preset", "tiny", "--scene", "circle")
    assert code == 2 and "unknown scene 'circle'" in err and "curve, line" in err
    assert toy_plugins.scene("toy", "curve").description == "the same line, by another name"
    code, out, _ = call("plugins", "--json")
    listed = {m["name"]: m for m in one_json(out)["methods"]}
    assert code == 0 and listed["toy"]["scenes"] == ["line", "curve"]


def test_registered_scenes_build_backend_neutral_scenes_for_other_plugins():
    import physint_freefall  # the example plugin (make install installs it)

    from physint_backends import Scene
    from physint_cli.plugins import Plugins

    plugins = Plugins(load_entry_points=False)
    plugins.add(physint_freefall, "freefall")
    drop = plugins.scene("freefall", "drop")
    scene = drop.build(seed=3, image_size=16)
    assert isinstance(scene, Scene) and scene.cameras[0].width == 16
    assert drop.build(seed=3).bodies[0].pos == scene.bodies[0].pos  # the seed fixes the scenario


def test_stability_stacks_are_built_through_the_registry_and_unstable_ones_fall():
    # what relate does: reuse ShapeStacks scenarios without importing the stability plugin
    import numpy as np

    from physint_backends import Scene, make
    from physint_cli.plugins import get_plugins

    ccs = get_plugins().scene("stability", "ccs")
    scene, scenario = ccs.build(seed=5, height=4, kind="VCOM", cameras=1, resolution=32)
    assert isinstance(scene, Scene) and len(scene.bodies) == 4 == scenario.height
    assert [b.name for b in scene.bodies] == ["obj0", "obj1", "obj2", "obj3"]
    again, _ = ccs.build(seed=5, height=4, kind="VCOM", cameras=1, resolution=32)
    assert [b.pos for b in again.bodies] == [b.pos for b in scene.bodies]  # the seed fixes the stack

    def falls(built) -> bool:  # some object moves more than 2 cm in 1.5 simulated seconds
        sim = make("mujoco", built)
        names = [b.name for b in built.bodies]
        start = [sim.get_pose(n)[0] for n in names]
        sim.step(int(1.5 / built.timestep))
        return max(float(np.linalg.norm(sim.get_pose(n)[0] - p)) for n, p in zip(names, start)) > 0.02

    seeds = range(6)
    vcom = sum(falls(ccs.build(seed=s, height=3, kind="VCOM", cameras=1, resolution=32)[0]) for s in seeds)
    stable = sum(falls(ccs.build(seed=s, height=3, kind="stable", cameras=1, resolution=32)[0]) for s in seeds)
    assert vcom >= 5 and stable <= 1, (vcom, stable)  # Lemma 1's violations fall, its stable stacks stand


def test_metrics_are_found_by_name_and_method(toy_plugins):
    mse = toy_plugins.metric("mse")
    assert mse.fn([1.0, 3.0], [1.0, 1.0]) == 2.0
    assert toy_plugins.metric("mse", method="lsq") is mse  # method-independent metrics serve every method
    code, _, err = call("eval", "lsq", "--preset", "tiny")  # no trained run yet: one line, exit 2
    assert code == 2 and "no trained lsq run" in err


def test_config_ranges_and_rules_between_fields_exit_2_naming_the_key(toy_plugins):
    code, out, err = call("train", "toy", "--preset", "tiny", "--set", "train.epochs=0")
    assert code == 2 and out == ""
    assert err.strip().splitlines() == ["error: --set train.epochs: must be >= 1, got 0"]
    code, _, err = call("train", "toy", "--preset", "tiny", "--set", "train.lr=11")
    assert code == 2 and "train.lr: must be in (0, 10], got 11.0" in err
    code, _, err = call("dataset", "toy", "--preset", "tiny", "--set", "data.per_shard=40")
    assert code == 2 and "data.per_shard must be at most data.train" in err
    code, out, _ = call("train", "toy", "--preset", "tiny", "--help-config")
    assert code == 0 and "int >= 1" in out


def test_verb_options_are_typed_context_fields_recorded_in_run_json(toy_plugins, tmp_path):
    code, out, err = call("train", "toy", "--preset", "tiny", "--model", "mlp", "--out", str(tmp_path / "run"),
                          "--json", "--quiet")
    assert code == 0, err
    info = json.loads((tmp_path / "run" / "run.json").read_text())
    assert info["options"] == {"model": "mlp"}
    code, out, err = call("deploy", "toy", "--run", str(tmp_path / "run"), "--target", "north", "--json", "--quiet")
    assert code == 0, err
    assert one_json(out)["metrics"] == {"target": "north"}
    code, _, err = call("eval", "toy", "--run", str(tmp_path / "run"), "--episodes", "0")
    assert code == 2 and "--episodes must be >= 1, got 0" in err
