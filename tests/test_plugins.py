"""The plugin system, driven through the real `physint` command as a user would."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ROOT, run_cli

EXAMPLE = ROOT / "examples" / "physint-freefall"


@pytest.fixture(scope="session")
def freefall_env(tmp_path_factory):
    """The example plugin pip-installed (into a target directory on PYTHONPATH) for subprocesses."""
    target = tmp_path_factory.mktemp("site")
    build = tmp_path_factory.mktemp("build")
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
                    "--target", str(target), str(EXAMPLE)], check=True, cwd=build, capture_output=True)
    return {"PYTHONPATH": os.pathsep.join([str(target), os.environ.get("PYTHONPATH", "")])}


def broken_plugin_dir(tmp_path: Path) -> Path:
    """A fake installed distribution whose plugin module fails to import."""
    site = tmp_path / "broken_site"
    dist = site / "physint_broken-0.1.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: physint-broken\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[physint]\nbroken = physint_broken_plugin\n")
    (site / "physint_broken_plugin.py").write_text("import a_module_that_does_not_exist\n")
    return site


def test_plugins_lists_builtins_and_example(freefall_env, tmp_path):
    result = run_cli("plugins", "--json", env=freefall_env)
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout)
    plugins = {p["name"]: p for p in data["plugins"]}
    assert set(plugins["backends"]["provides"]["backends"]) == {"mujoco", "pybullet", "robosuite"}
    assert plugins["backends"]["distribution"] == "physint"
    ff = plugins["freefall"]
    assert ff["distribution"] == "physint-freefall" and ff["version"] == "0.1.0" and ff["error"] is None
    assert ff["provides"]["methods"] == ["freefall"] and "pixel-mlp" in ff["provides"]["models"]
    method = next(m for m in data["methods"] if m["name"] == "freefall")
    assert method["models"] == ["mlp"] and method["scenes"] == ["drop"] and "pybullet" in method["backends"]
    assert method["presets"] == ["tiny", "small", "paper"]


def test_broken_plugin_is_reported_and_breaks_nothing(freefall_env, tmp_path):
    env = {"PYTHONPATH": os.pathsep.join([str(broken_plugin_dir(tmp_path)), freefall_env["PYTHONPATH"]])}
    result = run_cli("plugins", "--json", env=env)
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout)
    assert data["broken"][0]["name"] == "broken"
    assert "ModuleNotFoundError" in data["broken"][0]["error"] and "a_module_that_does_not_exist" in data["broken"][0]["error"]
    assert any(m["name"] == "freefall" for m in data["methods"])  # the others still load
    text = run_cli("plugins", env=env)
    assert text.returncode == 0 and "broken" in text.stdout
    result = run_cli("dataset", "freefall", "--preset", "tiny", "--set", "data.train=4", "--set", "data.val=2",
                     "--set", "data.test=2", "--out", str(tmp_path / "ds"), "--json", env=env)
    assert result.returncode == 0, result.stderr


def test_freefall_pipeline_end_to_end(freefall_env, tmp_path):
    """dataset -> train -> eval -> deploy on the MuJoCo backend: the MLP beats the mean baseline."""
    env = {**freefall_env, "PHYSINT_HOME": str(tmp_path / "home")}
    result = run_cli("pipeline", "freefall", "--preset", "tiny", "--json", env=env)
    assert result.returncode == 0, result.stderr
    out = json.loads(result.stdout)  # exactly one JSON object on stdout
    ev = out["eval"]["metrics"]
    assert ev["drops"] == 16
    assert ev["sim_vs_analytic_mae_s"] < 0.01  # MuJoCo's fall time agrees with sqrt(2h/g)
    assert ev["mae_vs_sim_s"] < 0.5 * ev["baseline_mae_vs_sim_s"]  # learned, not guessed
    de = out["deploy"]["metrics"]
    assert de["predicted_s"] == pytest.approx(de["analytic_s"], abs=0.05)
    deploy_dir = Path(out["deploy"]["run"])
    for name in ("drop.gif", "drop.mp4", "drop.rrd", "first_frame.png"):
        assert (deploy_dir / "artifacts" / name).stat().st_size > 0, name
    assert (Path(out["eval"]["run"]) / "artifacts" / "predictions.png").exists()
    # the runs land under the home and `view --save` turns one into a rerun recording
    saved = tmp_path / "train.rrd"
    view = run_cli("view", out["train"]["run"], "--save", str(saved), "--json", env=env)
    assert view.returncode == 0, view.stderr
    assert json.loads(view.stdout)["curve_points"] == 40 and saved.stat().st_size > 0
    view = run_cli("view", out["dataset"]["path"], "--save", str(tmp_path / "ds.rrd"), "--limit", "4", "--json", env=env)
    assert view.returncode == 0 and json.loads(view.stdout)["records_shown"] == 12
    # deploy for a new height; a bad height is one line and exit 2
    result = run_cli("deploy", "freefall", "--target", "1.5", "--json", env=env)
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["metrics"]["simulated_s"] == pytest.approx(0.553, abs=0.01)
    result = run_cli("deploy", "freefall", "--target", "high", env=env)
    assert result.returncode == 2 and result.stderr.strip() == "error: --target for freefall is a drop height in metres, got 'high'"


def test_cli_basics(freefall_env):
    assert run_cli("--version").stdout.startswith("physint ")
    result = run_cli("train", "--help")
    assert result.returncode == 0 and "--set" in result.stdout and "--resume" in result.stdout
    result = run_cli("train", "freefal", env=freefall_env)
    assert result.returncode == 2 and "did you mean 'freefall'" in result.stderr
    result = run_cli("freefall-table", "1", "2", env=freefall_env)  # a command added by register_commands
    assert result.returncode == 0 and result.stdout.splitlines() == ["1 m -> 0.4515 s", "2 m -> 0.6386 s"]
    result = run_cli("train", "freefall", "--bogus", env=freefall_env)
    assert result.returncode == 2 and "No such option" in result.stderr
    result = run_cli("backends", "--json")
    assert result.returncode == 0, result.stderr
    rows = {r["name"]: r for r in json.loads(result.stdout)["backends"]}
    assert set(rows) == {"mujoco", "pybullet", "robosuite"}
    for name, row in rows.items():
        assert row["can_render"] is True, (name, row["detail"])
        assert row["version"][0].isdigit()
