"""ShapeStacks scenario generation (thesis Section 3.3.1, Table 3.1), backend-neutral.

A *scenario* is a single-stranded stack whose analytic label (Lemma 1, :mod:`.physics`) is
chosen up front: ``"stable"``, or unstable with exactly ONE violated interface of type ``"VCOM"``
(centre of mass outside the contact surface) or ``"VPSF"`` (an object resting on a curved
surface). Margins keep the simulator in agreement with the label:

* stable: at every interface the load's centre of mass lies at least :data:`STABLE_MARGIN` of the
  contact surface's inradius (and :data:`STABLE_MARGIN_ABS` metres) inside it;
* VCOM: at the violated interface it lies at least :data:`VCOM_MARGIN` of the inradius (and
  :data:`VCOM_MARGIN_ABS` metres) outside, every other interface keeps the stable margins;
* VPSF: the object on the curved support has the support's top point (or line) well inside its
  footprint and its load's centre of mass at least :data:`VPSF_OFFSET_ABS` metres off it (so it
  tips at once instead of balancing); every other interface keeps the stable margins.

No object carries more than :data:`MAX_LOAD_RATIO` times its own mass (the simulators' contacts
are too soft for heavier loads). Offsets are random in direction and size: rectified towers, wild
ones, zig-zags, and (a :data:`COUNTERBALANCE` share of stable towers) towers with an object that
overhangs its support and only stands because the ones above counterbalance it (Fig. 3.2 B).

Subsets (Table 3.1): ``cubes`` (regular cubes only), ``ccs`` (cuboids, cylinders, spheres) and
``all`` (each scenario draws one of the two in proportion to Table 3.1's totals). Heights 2..6 are
drawn with Table 3.1's counts as weights. A stack of cubes cannot violate the planar-surface
criterion, so for ``cubes`` every unstable scenario is a VCOM; ``ccs`` splits its unstable
scenarios evenly between VCOM and VPSF (the thesis's even split holds per CCS; Table 3.4 reports
both types on CCS).

Spheres and lying cylinders only appear at the top of a short tower (see :data:`CURVED_TOP`), or as
the curved support of a VPSF.

:func:`to_scene` turns a scenario into a :class:`physint_backends.Scene` (objects ``obj0`` ..
bottom to top, one of 6 colours, one of 25 ground textures, one of 5 lighting conditions, 16
cameras orbiting the tower); :func:`simulate` runs it and reports whether it stood.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from physint_backends.randomize import PALETTE, jitter_camera, orbit_cameras, random_lights, texture_bank
from physint_backends.spec import Body, Geom, Ground, Scene, Texture
from physint_cli.errors import BadInput

from .physics import StackLabel, StackObject, analyse, clip_segment, inradius, signed_distance, stack_up

__all__ = [
    "SUBSETS", "KINDS", "HEIGHTS", "HEIGHT_WEIGHTS", "SUBSET_WEIGHTS", "STABLE_MARGIN", "STABLE_MARGIN_ABS",
    "VCOM_MARGIN", "VCOM_MARGIN_ABS", "VPSF_OFFSET_ABS", "MAX_LOAD_RATIO", "CURVED_TOP", "CURVED_TOP_MAX_HEIGHT",
    "COUNTERBALANCE", "CROP_PROB", "CUBOID_EDGE", "CUBOID_MAX_ASPECT", "N_LIGHTING", "N_TEXTURES", "Scenario", "PlannedScenario",
    "Outcome", "kinds_for", "height_counts", "sample_height", "balanced_kinds", "plan_scenarios", "sample_scenario",
    "lighting_conditions", "default_textures", "to_scene", "simulate",
]

SUBSETS = ("cubes", "ccs", "all")
KINDS = ("stable", "VCOM", "VPSF")
HEIGHTS = (2, 3, 4, 5, 6)
# Table 3.1 (train + val + test scenarios per height), used as sampling weights
HEIGHT_WEIGHTS = {
    "ccs": (1340 + 286 + 286, 2464 + 528 + 528, 1716 + 368 + 368, 678 + 144 + 144, 194 + 40 + 40),
    "cubes": (1680 + 360 + 360, 1680 + 360 + 360, 1558 + 332 + 332, 1274 + 272 + 272, 1030 + 220 + 220),
}
SUBSET_WEIGHTS = {"ccs": 6392 + 1366 + 1366, "cubes": 7222 + 1544 + 1544}

STABLE_MARGIN = 0.15  # load COM at least this fraction of the contact's inradius inside it ...
STABLE_MARGIN_ABS = 0.002  # ... and at least this many metres
VCOM_MARGIN = 0.2  # the violating load COM at least this fraction of the inradius outside ...
VCOM_MARGIN_ABS = 0.005  # ... and at least this many metres
VCOM_MIN_CONTACT = 0.004  # inradius (m) of the violated contact: the object really rests on its support
VPSF_OFFSET_ABS = 0.005  # load COM this far (m) from the curved support's top point / line
VPSF_REST_MARGIN = 0.25  # the top point of the curved support this fraction of the footprint's inradius inside it

# Largest mass resting on any object, in multiples of its own mass. Both simulators' contacts are
# soft in proportion to the lighter body, so a light object under a heavy load sinks and leans: with
# the load above 10x, towers Lemma 1 calls stable fell in 5-15% (MuJoCo) and 3-70% (PyBullet) of runs,
# below it in 0-3% (measured on 300 towers per subset).
MAX_LOAD_RATIO = 10.0

CUBE_EDGE = (0.04, 0.10)  # m, cubes subset
CUBOID_EDGE = (0.03, 0.11)  # m, each edge of a CCS cuboid
CUBOID_MAX_ASPECT = 3.5
CYLINDER_RADIUS = (0.02, 0.05)
CYLINDER_HEIGHT = (0.03, 0.11)
SPHERE_RADIUS = (0.02, 0.05)
# Probability that the top object of a CCS tower of height <= CURVED_TOP_MAX_HEIGHT is a sphere (80%)
# or a lying cylinder (20%). Resting on a flat face in neutral equilibrium, such objects roll off
# in simulation at the slightest lean of the tower (nothing holds them back but a tiny rolling
# friction; PyBullet even lets a sphere centred on a box drift). Measured over 30 stable towers
# per height: a top sphere stayed put in 93/63/50/30/13% (MuJoCo) and 50/67/33/20/10% (PyBullet)
# of towers of height 2/3/4/5/6. So they only crown short towers, and the dataset builder discards
# the disagreeing runs (thesis footnote 2).
CURVED_TOP = 0.15
CURVED_TOP_MAX_HEIGHT = 3

COUNTERBALANCE = 0.25  # share of stable towers (height >= 3) built around a counterbalanced object
CROP_PROB = 0.15  # share of scenes whose cameras come close enough to crop the tower
GROUND_HALF = 2.0  # m, half extent of the (visual) ground plane
N_TEXTURES = 25  # background textures (Table 3.1)
N_LIGHTING = 5  # lighting conditions (Table 3.1)
LIGHTING_SEED = 5_000
TEXTURE_SEED = 25


# --------------------------------------------------------------------------------------------
# data
# --------------------------------------------------------------------------------------------

@dataclass
class Scenario:
    """One stack: its objects (bottom to top, heights set), the Lemma-1 label, and the seed that rebuilds it."""

    subset: str  # "cubes" or "ccs" (never "all": that chooses one of the two)
    kind: str  # the requested kind: "stable", "VCOM" or "VPSF" (== label.violation or "stable")
    objects: list[StackObject]
    label: StackLabel
    seed: int

    @property
    def height(self) -> int:
        return len(self.objects)

    @property
    def stable(self) -> bool:
        return self.label.stable

    def to_dict(self) -> dict:
        return {"subset": self.subset, "kind": self.kind, "seed": self.seed, "height": self.height,
                "objects": [{"shape": o.shape, "size": list(o.size), "orientation": o.orientation,
                             "pos": [o.x, o.y, o.z], "yaw": o.yaw, "quat": list(o.quat), "mass": o.mass}
                            for o in self.objects],
                "label": self.label.to_dict()}

    @classmethod
    def from_dict(cls, d: dict) -> Scenario:
        """Inverse of :meth:`to_dict` (the label is recomputed with :func:`analyse`)."""
        objs = [StackObject(o["shape"], tuple(o["size"]), o["orientation"], x=o["pos"][0], y=o["pos"][1],
                            yaw=o["yaw"], z=o["pos"][2]) for o in d["objects"]]
        return cls(d["subset"], d["kind"], objs, analyse(objs), int(d["seed"]))


@dataclass
class PlannedScenario:
    subset: str
    height: int
    kind: str
    seed: int


@dataclass
class Outcome:
    """What the simulator did: did every object stay put, which one moved first, how far the farthest moved."""

    stable: bool
    first_to_fall: int | None
    max_displacement: float  # m, largest displacement of any object over the run
    fall_time: float | None = None  # s, when first_to_fall crossed the threshold


# --------------------------------------------------------------------------------------------
# plans: which (subset, height, kind) to generate
# --------------------------------------------------------------------------------------------

def _check_subset(subset: str, allow_all: bool = True) -> None:
    allowed = SUBSETS if allow_all else SUBSETS[:2]
    if subset not in allowed:
        raise BadInput(f"stack subset {subset!r} is not known; allowed: {', '.join(allowed)}")


def kinds_for(subset: str) -> tuple[str, ...]:
    """Violation kinds a subset can have: cubes cannot rest on a curved surface, so no VPSF."""
    _check_subset(subset, allow_all=False)
    return ("stable", "VCOM") if subset == "cubes" else KINDS


def _largest_remainder(n: int, weights) -> list[int]:
    w = np.asarray(weights, dtype=float)
    exact = n * w / w.sum()
    counts = np.floor(exact).astype(int)
    for i in np.argsort(-(exact - counts), kind="stable")[: n - counts.sum()]:
        counts[i] += 1
    return counts.tolist()


def height_counts(n: int, subset: str) -> dict[int, int]:
    """``n`` scenarios spread over heights 2..6 in Table 3.1's proportions (largest remainder)."""
    _check_subset(subset, allow_all=False)
    return dict(zip(HEIGHTS, _largest_remainder(n, HEIGHT_WEIGHTS[subset])))


def sample_height(rng: np.random.Generator, subset: str) -> int:
    """A stack height drawn with Table 3.1's counts as weights."""
    _check_subset(subset, allow_all=False)
    w = np.asarray(HEIGHT_WEIGHTS[subset], dtype=float)
    return int(rng.choice(HEIGHTS, p=w / w.sum()))


def balanced_kinds(n: int, rng: np.random.Generator, subset: str = "ccs") -> list[str]:
    """``n`` kinds for one stack height: half stable, half unstable, the unstable ones split evenly
    between VCOM and VPSF (ccs) or all VCOM (cubes); odd remainders go either way at random; shuffled."""
    _check_subset(subset, allow_all=False)
    n_stable = n // 2 + (int(rng.integers(2)) if n % 2 else 0)
    unstable = n - n_stable
    if subset == "cubes":
        kinds = ["stable"] * n_stable + ["VCOM"] * unstable
    else:
        n_vcom = unstable // 2 + (int(rng.integers(2)) if unstable % 2 else 0)
        kinds = ["stable"] * n_stable + ["VCOM"] * n_vcom + ["VPSF"] * (unstable - n_vcom)
    return [kinds[i] for i in rng.permutation(n)]


def plan_scenarios(n: int, rng: np.random.Generator, subset: str = "all") -> list[PlannedScenario]:
    """``n`` scenarios to generate: subsets and heights in Table 3.1's proportions, kinds balanced per
    (subset, height), each with its own seed. Deterministic given ``rng``."""
    _check_subset(subset)
    subsets = ["ccs", "cubes"] if subset == "all" else [subset]
    per_subset = _largest_remainder(n, [SUBSET_WEIGHTS[s] for s in subsets])
    plan = []
    for s, m in zip(subsets, per_subset):
        for h, k in height_counts(m, s).items():
            for kind in balanced_kinds(k, rng, s):
                plan.append(PlannedScenario(s, h, kind, int(rng.integers(2**31 - 1))))
    return [plan[i] for i in rng.permutation(len(plan))]


# --------------------------------------------------------------------------------------------
# objects
# --------------------------------------------------------------------------------------------

def sample_cube(rng) -> StackObject:
    a = rng.uniform(*CUBE_EDGE)
    return StackObject("box", (a, a, a), "z")


def sample_cuboid(rng) -> StackObject:
    while True:
        size = rng.uniform(*CUBOID_EDGE, 3)
        if size.max() / size.min() <= CUBOID_MAX_ASPECT:
            return StackObject("box", tuple(size), ("z", "x", "y")[rng.integers(3)])


def sample_cylinder(rng, lying: bool = False) -> StackObject:
    return StackObject("cylinder", (rng.uniform(*CYLINDER_RADIUS), rng.uniform(*CYLINDER_HEIGHT)),
                       "lying" if lying else "upright")


def sample_sphere(rng) -> StackObject:
    return StackObject("sphere", (rng.uniform(*SPHERE_RADIUS),))


def _flat(rng, subset: str) -> StackObject:
    """An object with flat top and bottom: a cube (cubes), or a cuboid / upright cylinder (ccs)."""
    if subset == "cubes":
        return sample_cube(rng)
    return sample_cuboid(rng) if rng.random() < 0.6 else sample_cylinder(rng)


def _curved(rng) -> StackObject:
    return sample_sphere(rng) if rng.random() < 0.5 else sample_cylinder(rng, lying=True)


def _top(rng, subset: str, height: int) -> StackObject:
    """The top object: may also be curved in short ccs towers (nothing rests on it), see :data:`CURVED_TOP`."""
    if subset == "ccs" and height <= CURVED_TOP_MAX_HEIGHT and rng.random() < CURVED_TOP:
        return sample_sphere(rng) if rng.random() < 0.8 else sample_cylinder(rng, lying=True)
    return _flat(rng, subset)


def _shapes(rng, subset: str, height: int, kind: str) -> tuple[list[StackObject], int | None]:
    """Objects bottom to top, and for VPSF the index of the curved support."""
    if kind == "VPSF":
        k = int(rng.integers(height - 1))  # the curved object, with at least one object on it
        objs = [_flat(rng, subset) for _ in range(height)]
        objs[k] = _curved(rng)
        if height - 1 > k + 1:  # the top (if it is not the one resting on the curved support)
            objs[-1] = _top(rng, subset, height)
        return objs, k
    return [_flat(rng, subset) for _ in range(height - 1)] + [_top(rng, subset, height)], None


def _max_load_ratio(objs: list[StackObject]) -> float:
    """The largest (mass resting on an object) / (its own mass) in the tower."""
    m = np.array([o.mass for o in objs])
    load = np.cumsum(m[::-1])[::-1] - m  # mass above each object
    return float((load / m).max())


def _half_width(obj: StackObject) -> float:
    """Half the smaller horizontal extent of a flat face (a reach scale for offsets)."""
    return 0.5 * min(obj.extents) if obj.shape == "box" else obj.size[0]


def _reach(lower: StackObject, upper: StackObject) -> float:
    """Offset at which the upper object's centre reaches the edge of the smaller face."""
    if upper.curved_bottom:
        return _half_width(lower)
    return min(_half_width(lower), _half_width(upper))


def _ray_to_boundary(poly: np.ndarray, origin: np.ndarray, u: np.ndarray) -> float:
    """Distance from ``origin`` (inside the convex CCW ``poly``) to its boundary along unit ``u``."""
    edge = np.roll(poly, -1, axis=0) - poly
    normal = np.stack([edge[:, 1], -edge[:, 0]], axis=1)
    num = ((poly - origin) * normal).sum(1)
    den = normal @ u
    t = num[den > 1e-12] / den[den > 1e-12]
    return float(t.min()) if len(t) else 0.0


def _unit(theta: float) -> np.ndarray:
    return np.array([math.cos(theta), math.sin(theta)])


# --------------------------------------------------------------------------------------------
# positions and acceptance
# --------------------------------------------------------------------------------------------

def _stable_ok(label: StackLabel, i: int) -> bool:
    f = label.interfaces[i]
    if f.status not in ("ok", "carried"):
        return False
    return f.margin >= STABLE_MARGIN_ABS and f.relative_margin >= STABLE_MARGIN


def _vpsf_ok(objs: list[StackObject], k: int) -> bool:
    """The object above the curved support ``k`` rests on its top point / line and tips at once."""
    support, rest = objs[k], objs[k + 1]
    foot = rest.footprint()
    load = objs[k + 1:]
    m = np.array([o.mass for o in load])
    com = (m[:, None] * np.stack([o.xy for o in load])).sum(0) / m.sum()
    r_in = inradius(foot)
    if support.shape == "sphere":
        if signed_distance(support.xy, foot) < VPSF_REST_MARGIN * r_in:
            return False
        offset = float(np.linalg.norm(com - support.xy))
    else:  # lying cylinder: a line contact along its axis
        chord = clip_segment(support.face(), foot)
        if len(chord) < 2 or np.linalg.norm(chord[1] - chord[0]) < 0.5 * min(rest.extents):
            return False
        mid = chord.mean(0)
        if signed_distance(mid, foot) < VPSF_REST_MARGIN * r_in:
            return False
        a = support.axis
        d = com - support.xy
        offset = abs(d[0] * a[1] - d[1] * a[0])  # perpendicular to the axis
    return offset >= max(VPSF_OFFSET_ABS, 0.1 * r_in)


def _accept(objs: list[StackObject], kind: str, k: int | None) -> StackLabel | None:
    label = analyse(objs)
    n = len(objs)
    if kind == "stable":
        if label.stable and all(_stable_ok(label, i) for i in range(n)):
            return label
        return None
    where = k if kind == "VCOM" else k + 1  # VPSF: the object on the curved support k rests badly
    if label.violations != [(where, kind)]:
        return None
    if kind == "VCOM":
        f = label.interfaces[k]
        if not (f.margin <= -VCOM_MARGIN_ABS and f.relative_margin <= -VCOM_MARGIN and f.inradius >= VCOM_MIN_CONTACT):
            return None
        others = [i for i in range(n) if i != k]
    else:
        if not _vpsf_ok(objs, k):
            return None
        others = [i for i in range(n) if i != k + 1]
    return label if all(_stable_ok(label, i) for i in others) else None


def _place(objs: list[StackObject], rng, kind: str, k: int | None, scale: float, zigzag: bool,
           counter: int | None = None) -> list[StackObject]:
    """Random horizontal poses, bottom up; for VCOM the violating offset is aimed past the support's
    edge; with ``counter`` = j, object j overhangs its support and the objects above hold it."""
    out: list[StackObject] = []
    aligned = rng.random() < 0.4
    theta = rng.uniform(0, 2 * math.pi)
    for i, obj in enumerate(objs):
        yaw = rng.normal(0, 0.05) if aligned else rng.uniform(0, math.pi)
        if i == 0:
            out.append(obj.moved(x=0.0, y=0.0, yaw=yaw))
            continue
        lower = out[-1]
        theta = theta + math.pi + rng.normal(0, 0.4) if zigzag else rng.uniform(0, 2 * math.pi)
        if kind == "VPSF" and i == k + 1:  # resting on the curved support: off its top point / line
            r = _half_width(obj) * rng.uniform(0.15, 0.6)
        else:
            r = _reach(lower, obj) * scale * rng.uniform(0, 1) ** 0.7
        p = lower.xy + r * _unit(theta)
        out.append(obj.moved(x=float(p[0]), y=float(p[1]), yaw=yaw))
    if kind == "VCOM":
        out = _overhang(out, rng, k)
    if counter is not None:
        out = _counterbalance(out, rng, counter)
    return stack_up(out)


def _shift(objs: list[StackObject], delta: np.ndarray) -> list[StackObject]:
    return [o.moved(x=o.x + float(delta[0]), y=o.y + float(delta[1])) for o in objs]


def _xy_com(objs: list[StackObject]) -> np.ndarray:
    m = np.array([o.mass for o in objs])
    return (m[:, None] * np.stack([o.xy for o in objs])).sum(0) / m.sum()


def _counterbalance(objs: list[StackObject], rng, j: int) -> list[StackObject]:
    """Fig. 3.2 B: object j's own centre of mass beyond the edge of object j-1's top, the objects
    above it shifted back so that the centre of mass of j..top lies inside the contact."""
    support, obj, above = objs[j - 1], objs[j], objs[j + 1:]
    u = _unit(rng.uniform(0, 2 * math.pi))
    edge = _ray_to_boundary(support.top_face(), support.xy, u)
    p_j = support.xy + (edge + _half_width(obj) * rng.uniform(0.1, 0.5)) * u
    target = support.xy + (edge - _reach(support, obj) * rng.uniform(0.3, 0.8)) * u  # COM of j..top
    m_j, m_up = obj.mass, sum(o.mass for o in above)
    c_up = (target * (m_j + m_up) - m_j * p_j) / m_up  # where the COM of the objects above must go
    moved = obj.moved(x=float(p_j[0]), y=float(p_j[1]))
    return objs[:j] + [moved] + _shift(above, c_up - _xy_com(above))


def _overhang(objs: list[StackObject], rng, k: int) -> list[StackObject]:
    """Shift objects k.. rigidly so that their combined COM lands beyond the edge of object k-1's top."""
    support = objs[k - 1]
    load = objs[k:]
    m = np.array([o.mass for o in load])
    com = (m[:, None] * np.stack([o.xy for o in load])).sum(0) / m.sum()
    u = _unit(rng.uniform(0, 2 * math.pi))
    edge = _ray_to_boundary(support.top_face(), support.xy, u)
    beyond = max(VCOM_MARGIN_ABS * 1.2, _reach(support, load[0]) * rng.uniform(0.25, 0.8))
    target = support.xy + (edge + beyond) * u
    return objs[:k] + _shift(load, target - com)


def sample_scenario(rng: np.random.Generator | int, subset: str = "ccs", height: int = 3, kind: str = "stable",
                    max_tries: int = 2000) -> Scenario:
    """A stack of ``height`` objects of ``subset`` whose Lemma-1 label is exactly ``kind``.

    ``rng`` (or an int seed) only draws the scenario's seed; everything else is drawn from
    ``np.random.default_rng(seed)``, so ``sample_scenario(scenario.seed, ...)`` rebuilds it.
    For ``subset="all"`` the subset is drawn first (Table 3.1 proportions; VPSF forces ``ccs``).
    """
    if isinstance(rng, (int, np.integer)):
        seed = int(rng)
    else:
        seed = int(rng.integers(2**31 - 1))
    _check_subset(subset)
    if kind not in KINDS:
        raise BadInput(f"scenario kind {kind!r} is not known; allowed: {', '.join(KINDS)}")
    if height not in HEIGHTS:
        raise BadInput(f"stack height must be one of {', '.join(map(str, HEIGHTS))}, got {height!r}")
    r = np.random.default_rng(seed)
    if subset == "all":
        if kind == "VPSF":
            subset = "ccs"
        else:
            p = SUBSET_WEIGHTS["ccs"] / (SUBSET_WEIGHTS["ccs"] + SUBSET_WEIGHTS["cubes"])
            subset = "ccs" if r.random() < p else "cubes"
    if kind not in kinds_for(subset):
        raise BadInput(f"a {subset} stack cannot have a {kind} violation (only cuboids, cylinders and spheres can "
                       f"rest on a curved surface); kinds for {subset}: {', '.join(kinds_for(subset))}")
    for attempt in range(max_tries):
        if attempt % 25 == 0:  # fresh shapes every 25 placements
            shapes, k = _shapes(r, subset, height, kind)
            while _max_load_ratio(shapes) > MAX_LOAD_RATIO:
                shapes, k = _shapes(r, subset, height, kind)
            if kind == "VCOM":  # the object resting beyond its support's edge: flat
                k = int(r.integers(1, height))
                if shapes[k].curved_bottom:
                    shapes[k] = _flat(r, subset)
            scale = r.uniform(0.1, 1.3)
            zigzag = r.random() < 0.3
            counter = None
            if kind == "stable" and height >= 3 and not shapes[-1].curved_top and r.random() < COUNTERBALANCE:
                counter = int(r.integers(1, height - 1))
        else:
            scale *= 0.93  # shrink the offsets until the margins hold
        objs = _place(shapes, r, kind, k, scale, zigzag, counter)
        label = _accept(objs, kind, k)
        if label is not None and (counter is None or label.interfaces[counter].counterbalanced):
            return Scenario(subset, kind, objs, label, seed)
    raise RuntimeError(f"no {kind} {subset} stack of height {height} found in {max_tries} tries (seed {seed})")


# --------------------------------------------------------------------------------------------
# scenes
# --------------------------------------------------------------------------------------------

_LIGHTING: list | None = None
_TEXTURES: list[Texture] | None = None


def lighting_conditions() -> list[list]:
    """The 5 fixed lighting conditions (seeded draws of :func:`random_lights`)."""
    global _LIGHTING
    if _LIGHTING is None:
        _LIGHTING = [random_lights(np.random.default_rng(LIGHTING_SEED + i), n=1, lookat=(0.0, 0.0, 0.1))
                     for i in range(N_LIGHTING)]
    return _LIGHTING


def default_textures() -> list[Texture]:
    """The 25 background textures (a seeded :func:`texture_bank`)."""
    global _TEXTURES
    if _TEXTURES is None:
        _TEXTURES = texture_bank(N_TEXTURES, seed=TEXTURE_SEED)
    return _TEXTURES


def _colours(n: int, rng, randomise: bool) -> list[tuple]:
    """One of the 6 palette colours per object, never the same as the object below."""
    out: list[tuple] = []
    for i in range(n):
        if not randomise:
            out.append(PALETTE[i % len(PALETTE)])
            continue
        choices = [c for c in PALETTE if not out or c != out[-1]]
        out.append(choices[rng.integers(len(choices))])
    return out


def to_scene(scenario: Scenario, rng: np.random.Generator | None = None, cameras: int = 16, resolution: int = 224,
             textures: list[Texture] | None = None, randomise: bool = True, camera_jitter: float = 0.02,
             fovy: float = 45.0, timestep: float = 0.002, ground_tile: float = 0.5) -> Scene:
    """A :class:`~physint_backends.Scene` of the scenario: bodies ``obj0`` (bottom) .. ``obj{n-1}`` (top).

    With ``randomise`` the colours (6-colour palette), the ground texture (of ``textures``, default
    the 25 of :func:`default_textures`), the lighting condition (of 5), the camera ring's azimuth,
    elevation and distance, and per-camera jitter are drawn from ``rng``; without it everything
    takes its first / middle value. The ``cameras`` cameras orbit the tower looking at its middle,
    far enough that a sphere around the whole tower fits the field of view (times 1.0..1.3; with
    probability :data:`CROP_PROB` times 0.8..1.0, which crops the view, as in the thesis, Fig. 3.2 B).
    """
    rng = rng if rng is not None else np.random.default_rng(scenario.seed)
    textures = default_textures() if textures is None else list(textures)
    objs = scenario.objects
    colours = _colours(len(objs), rng, randomise)
    bodies = [Body(f"obj{i}", [Geom(o.shape, o.size, rgba=colours[i])], pos=(o.x, o.y, o.z), quat=o.quat,
                   mass=o.mass) for i, o in enumerate(objs)]
    texture = None
    if textures:
        texture = textures[int(rng.integers(len(textures)))] if randomise else textures[0]
        texture = dataclasses.replace(texture, repeat=(2 * GROUND_HALF / ground_tile,) * 2)  # one tile per 0.5 m
    ground = Ground(texture=texture, size=GROUND_HALF)
    lights = lighting_conditions()[int(rng.integers(N_LIGHTING)) if randomise else 0]
    # cameras: a ring around the tower's middle
    lo = np.min([o.xy - o.radius_xy() for o in objs], axis=0)
    hi = np.max([o.xy + o.radius_xy() for o in objs], axis=0)
    top = max(o.z + o.height / 2 for o in objs)
    centre = (lo + hi) / 2
    lookat = (float(centre[0]), float(centre[1]), top / 2)
    # a sphere about the lookat point holding every object's bounding cylinder
    bound = max(math.hypot(float(np.linalg.norm(o.xy - centre)) + o.radius_xy(),
                           max(abs(o.z - o.height / 2 - top / 2), abs(o.z + o.height / 2 - top / 2))) for o in objs)
    dist = bound / math.sin(math.radians(fovy) / 2)
    elevation = math.radians(rng.uniform(5, 35) if randomise else 20.0)
    if randomise:  # mostly the whole tower; now and then a closer, cropped view (Fig. 3.2 B)
        dist *= rng.uniform(0.8, 1.0) if rng.random() < CROP_PROB else rng.uniform(1.0, 1.3)
    else:
        dist *= 1.1
    start = rng.uniform(0, 2 * math.pi) if randomise else 0.0
    cams = []
    if cameras:
        cams = orbit_cameras(cameras, radius=dist * math.cos(elevation), height=lookat[2] + dist * math.sin(elevation),
                             lookat=lookat, fovy=fovy, width=resolution, height_px=resolution, start=start)
    if randomise and camera_jitter > 0:
        cams = [jitter_camera(c, rng, camera_jitter, camera_jitter / 2, 1.0) for c in cams]
    # hard friction: a stack that Lemma 1 calls stable must not creep apart on soft contacts
    return Scene(bodies=bodies, cameras=cams, lights=list(lights), ground=ground, timestep=timestep,
                 hard_friction=True)


# --------------------------------------------------------------------------------------------
# simulation
# --------------------------------------------------------------------------------------------

def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    return rot @ v


def tilt_degrees(obj: StackObject, q0: np.ndarray, q1: np.ndarray) -> float:
    """Degrees the object has visibly tipped: how far its initially vertical axis turned (for a lying
    cylinder: how far its own axis turned; rolling about it and any turn of a sphere are invisible)."""
    if obj.shape == "sphere":
        return 0.0
    if obj.shape == "cylinder" and obj.orientation == "lying":
        local = np.array([0.0, 0.0, 1.0])
    else:
        local = _rotate(np.array([q0[0], -q0[1], -q0[2], -q0[3]]), np.array([0.0, 0.0, 1.0]))
    a, b = _rotate(q0, local), _rotate(q1, local)
    return math.degrees(math.acos(float(np.clip(np.dot(a, b), -1.0, 1.0))))


def simulate(sim, scenario: Scenario, seconds: float = 2.0, move_threshold: float = 0.01, tilt_threshold: float = 10.0,
             check_every: float = 0.01, stop_early: bool = False) -> Outcome:
    """Run the live ``sim`` (built from :func:`to_scene`) and decide stability by displacement.

    An object *falls* when it moves more than ``move_threshold`` metres or tips more than
    ``tilt_threshold`` degrees from its initial pose (see :func:`tilt_degrees`: spinning about the vertical,
    a sphere turning or a lying cylinder rolling in place are not tipping);
    ``first_to_fall`` is the first object to fall (ties in one check: the one furthest beyond its
    threshold). ``stop_early`` ends the run at the first fall (``max_displacement`` then covers
    only that part of the run).
    """
    names = [f"obj{i}" for i in range(len(scenario.objects))]
    start = [sim.get_pose(n) for n in names]
    steps = max(1, int(round(check_every / sim.scene.timestep)))
    total = max(1, int(round(seconds / sim.scene.timestep)))
    first, fall_time, max_disp, done = None, None, 0.0, 0
    while done < total:
        n = min(steps, total - done)
        sim.step(n)
        done += n
        worst, worst_score = None, 1.0
        for i, name in enumerate(names):
            pos, quat = sim.get_pose(name)
            disp = float(np.linalg.norm(pos - start[i][0]))
            max_disp = max(max_disp, disp)
            score = disp / move_threshold
            score = max(score, tilt_degrees(scenario.objects[i], start[i][1], quat) / tilt_threshold)
            if first is None and score > worst_score:
                worst, worst_score = i, score
        if first is None and worst is not None:
            first, fall_time = worst, done * sim.scene.timestep
            if stop_early:
                break
    return Outcome(first is None, first, max_disp, fall_time)


def build_stack_scene(subset: str, seed: int, height: int | None = None, kind: str = "stable", cameras: int = 6,
                      resolution: int = 128, randomise: bool = True) -> tuple[Scene, Scenario]:
    """The registry's scene builder (``SceneInfo.build``) for subset ``subset``: a ShapeStacks scenario
    drawn from ``seed`` (height drawn as Table 3.1 has it unless given; ``kind`` its Lemma-1 label: stable, VCOM or VPSF)
    and its backend-neutral scene, so another method (relate) reuses the stacks without importing
    this plugin: ``plugins.scene("stability", "ccs").build(seed=3)``."""
    rng = np.random.default_rng(seed)
    if height is None:
        height = sample_height(rng, subset if subset != "all" else "ccs")
    scenario = sample_scenario(rng, subset, height, kind)
    return to_scene(scenario, rng, cameras=cameras, resolution=resolution, randomise=randomise), scenario

