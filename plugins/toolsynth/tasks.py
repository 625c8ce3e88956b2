"""The reaching tasks of thesis Appendix 4.A and their five scenario types, A-E (Fig. 4.A.1).

A task is seen from above: a green target button, three red lines that bound the workspace, and
optionally blue obstacles. The robot is fixed at its base in front of the bottom red line and may
not enter the workspace, so it reaches the target only with a tool that touches the target and
crosses the bottom line to where the robot holds it, touching no obstacle (``feasibility.py``).

Coordinates are the table's, in metres, seen from above: x to the right, y away from the robot;
a task image covers ``[-EXTENT, EXTENT]`` on both axes. The scenario types, each built so that a
different property of the tool decides (our mapping of the thesis's letters, whose figure shows
the five but does not name them):

* **A, length**: the target lies open, 7-42 cm in front of the line: any tool long enough reaches.
* **B, width**: the target lies behind a row of blocks from side line to side line with one narrow
  gap (2-5.5 cm) before it: the handle must be thin enough to pass, and long enough.
* **C, hook length**: the target lies just behind a wall open at both ends (6-12 cm each side of
  the target): no straight tool within 60 degrees passes; a hook must be long enough to reach round.
* **D, hook side**: as C, but the wall runs to one side line, so only the other end is open
  (6-8 cm beyond the target): the hook must point back towards the target from the open side.
* **E, combination**: as D, with a block beyond the open end that leaves only a narrow gap (2.5-5.5 cm)
  beside the wall: the hook's side and length and the handle's width all decide. Table 4.A.1 has
  no E in training, so E is held out: it appears only in the validation and test splits.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

TYPES = ("A", "B", "C", "D", "E")
CONSTRAINTS = {"A": "length", "B": "width (a narrow gap)", "C": "hook length (a target round a corner)",
               "D": "hook orientation (the corner opens to one side)", "E": "orientation + hook length + width"}
EXTENT = 0.3  # half the side of the square a task image shows (m)
LINE_Y = -0.22  # the bottom red line: the robot holds the tool below it
LINE_X = 0.27  # the side red lines at x = +-LINE_X
LINE_WIDTH = 0.012
TARGET_RADIUS = 0.015
WALL_THICKNESS = 0.03
MAX_OBSTACLES = 4


@dataclass
class Task:
    """One reaching task: its type, the target's centre (x, y) and the obstacles as rectangles
    ``(x0, y0, x1, y1)`` (m)."""

    type: str
    target: tuple[float, float]
    obstacles: list[tuple[float, float, float, float]] = field(default_factory=list)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Fixed-size fields for a dataset record (obstacles padded with zeros)."""
        obstacles = np.zeros((MAX_OBSTACLES, 4), np.float32)
        if self.obstacles:
            obstacles[:len(self.obstacles)] = self.obstacles
        return {"type": np.uint8(TYPES.index(self.type)), "target": np.asarray(self.target, np.float32),
                "obstacles": obstacles, "n_obstacles": np.uint8(len(self.obstacles))}

    @classmethod
    def from_record(cls, type_index, target, obstacles, n_obstacles) -> Task:
        n = int(n_obstacles)
        return cls(TYPES[int(type_index)], (float(target[0]), float(target[1])),
                   [tuple(float(v) for v in o) for o in np.asarray(obstacles)[:n]])


def tasks_of(records: dict, index) -> list[Task]:
    """The tasks of records ``index`` of a dataset's arrays (or a batch of CPU tensors)."""
    return [Task.from_record(records["type"][i], records["target"][i], records["obstacles"][i],
                             records["n_obstacles"][i]) for i in index]


def parse_types(text: str, what: str = "types") -> tuple[str, ...]:
    """``"ABCD"`` or ``"A,B,C,D"`` as a tuple of scenario types; an unknown letter exits 2."""
    from physint_cli.errors import BadInput

    letters = [c for c in str(text).upper().replace(",", " ").replace(" ", "")]
    bad = sorted({c for c in letters if c not in TYPES})
    if bad or not letters:
        raise BadInput(f"{what}: unknown scenario type {', '.join(bad) or repr(text)}; the types are "
                       f"{', '.join(f'{t} ({CONSTRAINTS[t]})' for t in TYPES)}")
    return tuple(dict.fromkeys(letters))


def sample_task(kind: str, rng: np.random.Generator) -> Task:
    """A task of scenario type ``kind`` (A-E) with its target and obstacles drawn from ``rng``."""
    if kind == "A":
        return Task("A", (rng.uniform(-0.08, 0.08), rng.uniform(-0.15, 0.2)))
    tx, ty = rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.15)
    if kind == "B":
        gap, gap_x = rng.uniform(0.02, 0.055), tx + rng.uniform(-0.005, 0.005)
        top = ty - rng.uniform(0.025, 0.045)  # the blocks' edge facing the target
        bottom = top - rng.uniform(0.04, 0.08)
        return Task("B", (tx, ty), [(-LINE_X, bottom, gap_x - gap / 2, top), (gap_x + gap / 2, bottom, LINE_X, top)])
    top = ty - rng.uniform(0.022, 0.03)  # a straight tool tilted by 60 degrees passes at most 5.2 cm aside
    bottom = top - WALL_THICKNESS
    if kind == "C":
        left, right = rng.uniform(0.06, 0.12, size=2)
        return Task("C", (tx, ty), [(tx - left, bottom, tx + right, top)])
    open_side = int(rng.choice([-1, 1]))  # the end of the wall that lets a tool through
    reach = rng.uniform(0.06, 0.08) if kind == "D" else rng.uniform(0.06, 0.1)
    if open_side > 0:
        wall = (-LINE_X, bottom, tx + reach, top)
    else:
        wall = (tx - reach, bottom, LINE_X, top)
    if kind == "D":
        return Task("D", (tx, ty), [wall])
    if kind == "E":
        gap = rng.uniform(0.025, 0.055)
        block = (tx + reach + gap, bottom, LINE_X, top) if open_side > 0 else (-LINE_X, bottom, tx - reach - gap, top)
        return Task("E", (tx, ty), [wall, block])
    raise ValueError(f"unknown scenario type {kind!r}")
