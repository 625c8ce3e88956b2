"""Behaviour of the stability plugin's deployment tasks (thesis Section 3.5): simulated annealing,
the Lemma-1 oracle against random placement on the unstable T and on cube towers, stackability,
and the whole verb with a fake predictor (no trained network needed)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from physint_cli import config as configs
from physint_cli.errors import BadInput
from physint_cli.method import Context, Unit, unit_seed
from physint_plugins.stability import deploy as D
from physint_plugins.stability.deploy import scorers
from physint_plugins.stability.config import PRESETS, StabilityConfig
from physint_plugins.stability.physics import StackObject, stack_up


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # torch on one thread: results independent of the cores


def make_ctx(tmp_path=None, task="stackability", sets=(), agents=None) -> Context:
    sets = [*sets, f"deploy.agents={agents}"] if agents else list(sets)
    cfg = configs.resolve(StabilityConfig, PRESETS, "tiny", None, sets)
    return Context(method="stability", config=cfg, preset="tiny", backend="mujoco", scene="ccs", seed=0,
                   run=tmp_path, task=task, quiet=True)


class FakePredictor(torch.nn.Module):
    """A stand-in network whose logit is a known function of the image: brighter = less stable."""

    def forward(self, x):
        return 12.0 * (x.mean(dim=(1, 2, 3)) - 0.45)


# -- simulated annealing -------------------------------------------------------------------------

def test_annealing_climbs_a_known_landscape_from_a_poor_start():
    target = np.array([0.021, -0.013])

    def score(xy):  # a smooth hill around the target, low (but not flat) elsewhere
        return 1.0 / (1.0 + math.exp(-(0.5 - np.sum((xy - target) ** 2) / 0.01 ** 2)))

    domain = D.Disc((0.0, 0.0), 0.03)
    misses = []
    for seed in range(10):
        res = D.anneal(score, domain, 40, np.random.default_rng(seed), start=(-0.02, 0.02))
        assert res.start_score < 1e-9 and res.score > 0.3
        assert res.trace == sorted(res.trace) and len(res.trace) == 40  # best-so-far never gets worse
        assert np.linalg.norm(res.xy - domain.centre) <= 0.03 + 1e-12
        misses.append(np.linalg.norm(res.xy - target))
    assert np.median(misses) < 0.004


def test_search_regions_keep_proposals_inside():
    rng = np.random.default_rng(1)
    rect = D.Rect((0.1, 0.2), (0.2, 0.05), yaw=0.7)
    axes = np.array([[math.cos(0.7), math.sin(0.7)], [-math.sin(0.7), math.cos(0.7)]])
    for _ in range(50):
        for p in (rect.sample(rng), rect.project(rng.normal(0, 1, 2))):
            local = axes @ (p - rect.centre)
            assert abs(local[0]) <= 0.1 + 1e-9 and abs(local[1]) <= 0.025 + 1e-9


# -- counterbalancing (Section 3.5.3) ------------------------------------------------------------

def _balance(ctx, agent, kind, episodes):
    return [D.balance_episode(ctx, Unit("t", e, 1, unit_seed(0, "balance", kind, e), {"weight": kind, "agent": agent}))
            for e in range(episodes)]


def test_oracle_counterweight_makes_the_t_stand_more_often_than_random_placement():
    ctx = make_ctx(task="balance", sets=["deploy.anneal_steps=30"])
    oracle = sum(r["success"] for r in _balance(ctx, "oracle", "cube", 6))
    random = sum(r["success"] for r in _balance(ctx, "random", "cube", 6))
    alone = sum(r["success"] for r in _balance(ctx, "none", "cube", 6))
    assert alone == 0  # the frozen T really is unstable
    assert oracle >= 5
    assert oracle > random


def test_a_sphere_placed_where_lemma_1_balances_the_t_stays_there():
    # the sphere used to roll off the plank (soft contacts tilt it 0.05 deg; the scene's hard friction holds it)
    results = _balance(make_ctx(task="balance", sets=["deploy.anneal_steps=30"]), "oracle", "sphere", 4)
    assert all(r["success"] for r in results)


def test_the_t_is_a_vcom_that_a_counterweight_can_fix():
    rng = np.random.default_rng(3)
    w = D.counterweight("sphere", rng)
    t = D.unstable_t(rng, w)
    assert D.lemma1_margin(t) < -0.005
    plank = t[1]
    res = D.anneal(D.OracleScorer().placement(t, w), D.Rect(plank.xy, plank.extents, plank.yaw), 30, rng)
    assert res.score > 0.5 and res.score > res.start_score


# -- stacking (Section 3.5.2) --------------------------------------------------------------------

def test_oracle_stacks_cubes_higher_than_random_placement():
    ctx = make_ctx(task="stack", sets=["deploy.anneal_steps=20", "deploy.anneal_radius=0.05"])
    heights = {}
    for agent in ("oracle", "random"):
        heights[agent] = [D.stack_episode(ctx, Unit("t", e, 1, unit_seed(0, "stack", "cubes", e),
                                                    {"scenario": "cubes", "agent": agent, "pool": 7}))["height"]
                          for e in range(3)]
    assert np.mean(heights["oracle"]) > np.mean(heights["random"])
    assert min(heights["oracle"]) >= 5


def test_ccs_pools_hold_exactly_two_spheres():
    for seed in range(5):
        pool = D.stack_pool("ccs", 12, np.random.default_rng(seed))
        assert sum(o.shape == "sphere" for o in pool) == 2 and len(pool) == 12


# -- stackability (Section 3.5.1) ----------------------------------------------------------------

def test_oracle_stackability_ranks_spheres_last_and_large_faces_above_small_ones():
    objects = [StackObject("box", (0.10, 0.07, 0.03)), StackObject("box", (0.06, 0.06, 0.06)),
               StackObject("cylinder", (0.03, 0.07)), StackObject("sphere", (0.03,))]
    rows = D.stackability_ranking(objects, D.OracleScorer(), np.random.default_rng(0), steps=8, radius=0.03)
    assert len(rows) == 3 + 1 + 2 + 1  # cuboid 3 faces, cube 1, cylinder 2, sphere 1
    by = {(r["object"], r["orientation"]): r["score"] for r in rows}
    assert by[(3, "any")] <= min(by.values()) + 1e-9
    assert rows[-1]["shape"] in ("sphere", "cylinder") and by[(3, "any")] < 0.05
    assert by[(0, "z")] > by[(0, "x")]  # the 10x7 face up beats the 7x3 face up
    assert by[(2, "upright")] > by[(2, "lying")]
    assert D.object_class(objects[0].moved(orientation="z")) == "cuboid largest face"
    assert D.object_class(objects[0].moved(orientation="x")) == "cuboid smallest face"


# -- the predictor scorer and the verb -----------------------------------------------------------

def test_predictor_scorer_averages_the_network_over_its_cameras():
    from physint_plugins.stability.augment import EvalTransform

    ctx = make_ctx()
    appearance = D.Appearance.draw(np.random.default_rng(0), cameras=6, resolution=32, textures=4)
    net = FakePredictor().eval()
    scorer = D.PredictorScorer(net, 32, appearance, ctx.make_sim)
    trunk = stack_up([StackObject("box", (0.08, 0.08, 0.05))])
    top = StackObject("box", (0.05, 0.05, 0.05))
    with scorer:
        score = scorer.placement(trunk, top)
        s = score(np.array([0.01, 0.0]))
        images = scorer.images()
        assert images.shape == (6, 32, 32, 3)
        with torch.no_grad():
            expected = 1 - torch.sigmoid(net(EvalTransform(32)(images))).mean().item()
        assert s == pytest.approx(expected, abs=1e-5)
        assert score(np.array([-0.02, 0.01])) != s  # only the geometry changed ...
        other = scorer.placement(trunk, StackObject("sphere", (0.03,)))
        other(np.zeros(2))
        assert scorer.placement(trunk, top)(np.array([0.01, 0.0])) == s  # ... and the look stays the same
        np.testing.assert_array_equal(scorer.images(), images)
    c = appearance.colours([trunk[0], top, top])
    assert c[0] != c[1] and c[1] != c[2]  # never the colour of the object below


def test_deploy_rejects_an_unknown_task():
    with pytest.raises(BadInput, match="stackability"):
        D.deploy(make_ctx(task="juggle"))
    with pytest.raises(BadInput, match="agent"):
        D.deploy(make_ctx(task="stack", agents="oracle,psychic"))


def test_deploy_runs_every_task_with_a_fake_predictor_and_writes_its_artifacts(tmp_path, monkeypatch):
    monkeypatch.setattr(scorers, "_load_predictor", lambda ctx: (FakePredictor().eval(), 32))
    sets = ["deploy.pool=3", "deploy.stackability_pool=3", "deploy.anneal_steps=3", "deploy.cameras=2"]
    stack = D.deploy(make_ctx(tmp_path, "stack", sets, agents="predictor,oracle,random"))
    assert set(stack["scenarios"]) == {"cubes", "cuboids", "ccs"}
    for per in stack["scenarios"].values():
        for agent in ("predictor", "oracle", "random"):
            assert len(per[agent]["heights"]) == 1 and sum(per[agent]["histogram"]) == 1
    balance = D.deploy(make_ctx(tmp_path, "balance", [*sets, "deploy.episodes=2"], agents="predictor,oracle,random"))
    assert balance["episodes"] == 2 and set(balance["counterweights"]) == set(D.COUNTERWEIGHTS)
    assert balance["counterweights"]["sphere"]["none"]["episodes"] == 2
    ranked = D.deploy(make_ctx(tmp_path, "stackability", sets, agents="predictor,oracle"))
    rows = ranked["agents"]["predictor"]["ranking"]
    assert rows == sorted(rows, key=lambda r: -r["score"]) and len(rows) == ranked["bases"]
    assert ranked["objects"] == 3
    json.dumps([stack, balance, ranked])  # JSON-serialisable metrics
    files = {p.name for p in (tmp_path / "artifacts").iterdir()}
    assert {"stack_heights.png", "balance_success.png", "stackability_area.png", "stackability_strip.png",
            "stack_cubes_predictor.rrd", "balance_cube_predictor.rrd"} <= files
    assert "stack_cubes_predictor.mp4" in files or "stack_cubes_predictor.gif" in files
