"""How well the push expert can be imitated from positions alone, and what an error in the cube's
position costs: perception and control of a GEECO push controller apart.

    python benchmarks/geeco_state_policy.py --data PUSH [--episodes 100] [--epochs 30]
                                            [--cube-error 0,0.01,0.02,0.04] [--vision RUN]

An MLP (three layers of 256) learns u_dEE (MSE, as Eq. 6.3) from the true positions of the hand and
the cube over the last K = 4 steps and the target pad's, on the dataset's training demonstrations
(nothing is rendered for it). It then drives the robot from the test split's start states (200
steps, MuJoCo) with

* the simulator's true positions; with ``--cube-error S``: the cube's shifted by a constant error
  per episode drawn from N(0, S^2) per horizontal axis (a perception that is off, not noisy);
* ``--vision RUN``: the cube's position as a trained GEECO controller's q_OBJ head estimates it from
  the camera frames (that controller runs beside the MLP only to see; the MLP drives), with the
  true hand and target positions.

Prints REACH and PUSH per row. Nothing here is a product path: ``physint train geeco --set
train.command=positions`` is the controller built on what this measures (docs/geeco.md).
"""

from __future__ import annotations

import argparse
import time
from collections import deque
from pathlib import Path

import numpy as np
import torch

from physint_cli.datasets import ShardedDataset
from physint_cli.plugins import get_plugins
from physint_plugins.geeco import scenes as S
from physint_plugins.geeco.checkpoint import episodes_of, load_controller
from physint_plugins.geeco.control import DEE_SCALE, Policy, run_episode
from physint_plugins.geeco.train import load_split

K = 4  # the controllers' buffer


def features(hand: np.ndarray, cube: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(T, 3) hand and cube positions and the target's (2,) -> (T, 6K + 2): per step of the buffer
    (left-padded with the first) the hand's and the cube's, then the target's; decimetres."""
    steps, table = len(hand), np.array([0.0, 0.0, S.TABLE_Z])
    out = []
    for k in range(K):
        idx = np.maximum(np.arange(steps) - (K - 1 - k), 0)
        out += [(hand[idx] - table) / 0.1, (cube[idx] - table) / 0.1]
    out.append(np.repeat(target[None] / 0.1, steps, 0))
    return np.concatenate(out, 1).astype(np.float32)


def split(data: Path, name: str):
    arrays = ShardedDataset(data, name, ["ee", "obj", "dee", "layout", "task", "seed"], method="geeco",
                            in_memory=True).arrays
    return arrays, episodes_of(arrays, "goal2cube2", "push")


def train_mlp(data: Path, epochs: int, seed: int = 0) -> torch.nn.Module:
    demos, eps = split(data, "train")
    x = torch.from_numpy(np.concatenate([features(demos["ee"][i], demos["obj"][i], ep.xy(ep.target))
                                         for i, ep in enumerate(eps)]))
    y = torch.from_numpy(np.concatenate([demos["dee"][i] / DEE_SCALE for i in range(len(eps))]).astype(np.float32))
    torch.manual_seed(seed)
    net = torch.nn.Sequential(torch.nn.Linear(x.shape[1], 256), torch.nn.ReLU(), torch.nn.Linear(256, 256),
                              torch.nn.ReLU(), torch.nn.Linear(256, 256), torch.nn.ReLU(), torch.nn.Linear(256, 3))
    opt = torch.optim.Adam(net.parameters(), 1e-3)
    batches = len(x) // 256
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(1, epochs * batches))
    t0 = time.time()
    for epoch in range(epochs):
        order, total = torch.randperm(len(x)), 0.0
        for b in range(batches):
            i = order[b * 256:(b + 1) * 256]
            loss = ((net(x[i]) - y[i]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            schedule.step()
            total += float(loss)
        print(f"epoch {epoch + 1}/{epochs}: loss {total / batches:.4f} ({time.time() - t0:.0f} s)", flush=True)
    return net.eval()


class PositionsPolicy:
    """The MLP driving the robot from positions (``run_episode``'s policy interface)."""

    def __init__(self, net, sim, ep: S.Episode, cube_error: np.ndarray, vision: Policy | None, target_rgb):
        self.net, self.sim, self.ep, self.cube_error, self.vision = net, sim, ep, cube_error, vision
        self.target_rgb, self.history, self.t, self.last = target_rgb, deque(maxlen=K), 0, {}

    def reset(self, target_rgb) -> None:
        self.history.clear()
        self.t = 0
        if self.vision is not None:
            self.vision.reset(self.target_rgb)

    def act(self, rgb, joints, hand=None, truth=None) -> np.ndarray:
        hand = np.asarray(self.sim.robot.state().ee_pos, dtype=float)
        cube = self.sim.get_pose(self.ep.object)[0] + self.cube_error
        if self.vision is not None:
            self.vision.act(rgb, joints)
            cube = self.vision.last["obj"]
        if not self.history:
            self.history.extend([(hand, cube)] * (K - 1))
        self.history.append((hand, cube))
        x = features(np.array([h for h, _ in self.history]), np.array([c for _, c in self.history]),
                     self.ep.xy(self.ep.target))[-1]
        with torch.no_grad():
            dee = self.net(torch.from_numpy(x)[None])[0].numpy() * DEE_SCALE
        self.t += 1
        return np.array([*dee, 1.0 if self.t <= 3 else 0.0])  # the expert closes the fingers first


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="a GOAL2CUBE2 push dataset")
    parser.add_argument("--episodes", type=int, default=100, help="test start states per row")
    parser.add_argument("--epochs", type=int, default=30)
    parser.add_argument("--cube-error", default="0", help="comma-separated std (m) of a constant cube position error")
    parser.add_argument("--vision", type=Path, help="a trained GEECO push run whose q_OBJ estimates the cube")
    args = parser.parse_args()
    torch.set_num_threads(1)
    net = train_mlp(args.data, args.epochs)
    test, eps = split(args.data, "test")
    frames = load_split(args.data, "test")["rgb"] if args.vision else None
    vision_model = load_controller(args.vision)[0] if args.vision else None
    rows = [("vision", 0.0)] if args.vision else [("true", float(s)) for s in args.cube_error.split(",")]
    sim = None
    print("| cube position | REACH | PUSH | episodes |\n|---|---|---|---|")
    for kind, sigma in rows:
        rng = np.random.default_rng(1)
        reach = push = 0
        n = min(args.episodes, len(eps))
        for i in range(n):
            ep = eps[i]
            if sim is None:
                sim = get_plugins().backend("mujoco").make(S.build_scene(ep, 64))
            error = np.r_[rng.normal(0, sigma, 2), 0.0]
            policy = PositionsPolicy(net, sim, ep, error, Policy(vision_model) if vision_model else None,
                                     frames[i, -1] if frames is not None else None)
            r = run_episode(sim, ep, policy, None, 200, 64)
            reach, push = reach + r["reach"], push + r["success"]
        label = f"q_OBJ of {args.vision}" if kind == "vision" else f"true, constant error N(0, {100 * sigma:g} cm)"
        print(f"| {label} | {100 * reach / n:.1f} % | {100 * push / n:.1f} % | {n} |", flush=True)


if __name__ == "__main__":
    main()
