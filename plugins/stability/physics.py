"""The mechanics of stacking: Lemma 1 and the violation types VCOM / VPSF (thesis Section 3.3.2).

A *single-stranded stack* ``S_1 .. S_n`` (here 0-based: ``stack[0]`` rests on the ground,
``stack[-1]`` is the top) of convex objects: cuboids (three distinct orientations, by which pair of
faces is horizontal), cylinders (upright or lying on their side) and spheres. Every object is a
:class:`StackObject`; :func:`stack_up` sets each object's height ``z`` so that it rests on the one
below (no two objects at the same level, the ground at ``z = 0``).

Interfaces
    Interface ``i`` is the contact between object ``i`` and what supports it: object ``i - 1``, or
    the ground for ``i = 0``. Its *load* is the sub-stack ``i .. n-1``. So our interface ``i >= 1``
    is the thesis's ``A_i`` of Eq. 3.1 read as the contact on top of ``S_i`` (= our object
    ``i - 1``; 1-based), whose load has the centre of mass ``r_{i+1}^n`` (the lemma's prose says
    ``A_i`` lies between ``S_{i-1}`` and ``S_i``, but only this reading pairs ``A_i`` with
    ``r_{i+1}^n`` consistently). We also check interface 0, the ground contact, which Eq. 3.1 leaves
    out (for a flat base it cannot fail unless an interface above fails too).

Lemma 1 / Eq. 3.1
    The tower is stable iff, for every interface, the projection on the horizontal plane of the
    combined centre of mass of the load,

        r_{i+1}^n = sum_j m_j r_j / sum_j m_j         (Eq. 3.1, :func:`combined_com`)

    lies inside the contact surface ``A_i`` = (top face of the support) ∩ (bottom face of the
    object resting on it) (:func:`contact_surface`, Sutherland–Hodgman clipping).

Violation types (exactly as the thesis defines them)
    ``VPSF``, violation of the planar-surface criterion: an object rests on a *curved* surface (a
    sphere, or a cylinder lying on its side), whose contact area is infinitesimal. It depends on
    the shapes only, never on the positions, so it is flagged whatever the offsets (margin
    ``-inf``). The **violating object** is the curved support (``interface - 1``): "the violating,
    curved object" of the thesis's Section 3.4.2.
    ``VCOM``, violation of the centre-of-mass criterion: Eq. 3.1 fails at an interface whose
    support offers a finite planar surface. The **violating object** is again the *support*
    (``interface - 1``), the object whose top surface the load's centre of mass overhangs; the
    unsupported part above it (from object ``interface`` up to the top) is what falls (Fig. 3.4 and
    Table 3.4 separate "violating object" from "first object to fall + tower top"). For the ground
    interface (0) there is no support object, and the violating object is object 0 itself.
    So for both types: ``violating_object = max(interface - 1, 0)``.

Curved objects resting on a flat face
    A sphere or lying cylinder touches a plane along a point or line directly below its own centre
    of mass. Unloaded (at the top of the tower), Eq. 3.1 holds iff that point lies on the
    supporting face: its margin is the signed distance of its centre to the supporting face. When
    it carries a load, the load rests on its curved top, which is the VPSF reported at the
    interface above; the degenerate contact below it fails for the same reason and is part of the
    same violation (status ``"carried"``, not counted again), so a VPSF is always attributed to
    exactly one interface and one object.

Margins are signed distances in metres, positive inside (so generators can keep the centre of
mass a safe distance from the boundary); ``relative_margins`` divide them by the contact
surface's inradius.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

__all__ = [
    "DENSITY", "DISC_VERTICES", "SHAPES", "ORIENTATIONS", "StackObject", "Interface", "StackLabel",
    "stack_up", "analyse", "combined_com", "contact_surface",
    "rectangle", "disc", "polygon_area", "clip_polygon", "clip_segment", "signed_distance", "inradius",
]

DENSITY = 1000.0  # kg/m^3, uniform for every object (the masses follow from the volumes)
DISC_VERTICES = 32  # vertices of the polygon inscribed in a cylinder's circular face
SHAPES = ("box", "cylinder", "sphere")
ORIENTATIONS = {
    "box": ("z", "x", "y"),  # which of the box's own axes points up (size[0], size[1] or size[2] vertical)
    "cylinder": ("upright", "lying"),
    "sphere": ("any",),
}
_EPS = 1e-12


# --------------------------------------------------------------------------------------------
# objects
# --------------------------------------------------------------------------------------------

def _quat_mul(a, b) -> tuple[float, float, float, float]:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return (w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2)


_S = math.sqrt(0.5)
# rotations taking the named own axis to world +z (before the yaw about z)
_TILT = {
    ("box", "z"): (1.0, 0.0, 0.0, 0.0),
    ("box", "x"): (_S, 0.0, -_S, 0.0),  # -90 deg about y: own x -> +z, own z -> -x
    ("box", "y"): (_S, _S, 0.0, 0.0),  # +90 deg about x: own y -> +z, own z -> -y
    ("cylinder", "upright"): (1.0, 0.0, 0.0, 0.0),
    ("cylinder", "lying"): (_S, 0.0, _S, 0.0),  # +90 deg about y: axis -> +x (then yawed)
    ("sphere", "any"): (1.0, 0.0, 0.0, 0.0),
}


@dataclass
class StackObject:
    """One convex object of a stack.

    ``size`` uses full lengths exactly like :class:`physint_backends.spec.Geom`: box ``(x, y, z)``
    in the box's own frame, cylinder ``(radius, height)`` (height along its own axis), sphere
    ``(radius,)``. ``orientation`` says how it lies (see :data:`ORIENTATIONS`): for a box, which of
    its own axes points up; for a cylinder, ``"upright"`` (axis vertical) or ``"lying"`` (axis
    horizontal, along the direction ``yaw``). ``(x, y)`` is the centre's horizontal position,
    ``yaw`` the rotation about the vertical axis, and ``z`` the centre's height, set by
    :func:`stack_up`. The centre of mass is the geometric centre (uniform density).
    """

    shape: str
    size: tuple[float, ...]
    orientation: str = ""
    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0
    z: float = float("nan")
    density: float = DENSITY

    def __post_init__(self) -> None:
        if self.shape not in SHAPES:
            raise ValueError(f"stack object shape {self.shape!r} is not supported; allowed: {', '.join(SHAPES)}")
        if not self.orientation:
            self.orientation = ORIENTATIONS[self.shape][0]
        if self.orientation not in ORIENTATIONS[self.shape]:
            raise ValueError(f"{self.shape} orientation {self.orientation!r} is not known; allowed: "
                             f"{', '.join(ORIENTATIONS[self.shape])}")
        n = {"box": 3, "cylinder": 2, "sphere": 1}[self.shape]
        size = tuple(float(s) for s in np.atleast_1d(self.size))
        if len(size) != n or min(size) <= 0:
            raise ValueError(f"{self.shape} size must be {n} positive full length(s), got {self.size!r}")
        self.size = size

    # -- geometry ------------------------------------------------------------------------------
    @property
    def height(self) -> float:
        """Vertical extent."""
        if self.shape == "box":
            return self.size["xyz".index(self.orientation)]
        if self.shape == "cylinder":
            return self.size[1] if self.orientation == "upright" else 2 * self.size[0]
        return 2 * self.size[0]

    @property
    def extents(self) -> tuple[float, float]:
        """Horizontal extents along the object's yawed x and y axes (a box's face, a cylinder's AABB before yaw)."""
        if self.shape == "box":
            sx, sy, sz = self.size
            return {"z": (sx, sy), "x": (sz, sy), "y": (sx, sz)}[self.orientation]
        r = self.size[0]
        if self.shape == "cylinder" and self.orientation == "lying":
            return (self.size[1], 2 * r)
        return (2 * r, 2 * r)

    @property
    def volume(self) -> float:
        if self.shape == "box":
            return float(np.prod(self.size))
        if self.shape == "cylinder":
            return math.pi * self.size[0] ** 2 * self.size[1]
        return 4.0 / 3.0 * math.pi * self.size[0] ** 3

    @property
    def mass(self) -> float:
        return self.density * self.volume

    @property
    def com(self) -> np.ndarray:
        return np.array([self.x, self.y, self.z])

    @property
    def xy(self) -> np.ndarray:
        return np.array([self.x, self.y])

    @property
    def quat(self) -> tuple[float, float, float, float]:
        """World orientation (w, x, y, z): the tilt of :data:`ORIENTATIONS`, then ``yaw`` about z."""
        yaw = (math.cos(self.yaw / 2), 0.0, 0.0, math.sin(self.yaw / 2))
        return _quat_mul(yaw, _TILT[(self.shape, self.orientation)])

    @property
    def curved_top(self) -> bool:
        """A sphere or lying cylinder: no finite planar surface on top."""
        return self.shape == "sphere" or (self.shape == "cylinder" and self.orientation == "lying")

    curved_bottom = curved_top  # every shape here is symmetric top / bottom

    @property
    def axis(self) -> np.ndarray:
        """Horizontal unit vector along the yawed x axis (a lying cylinder's axis)."""
        return np.array([math.cos(self.yaw), math.sin(self.yaw)])

    def face(self) -> np.ndarray:
        """The horizontal face (top = bottom footprint) as a CCW polygon, or the contact set of a
        curved object with a plane: a point (sphere, shape (1, 2)) or a segment (lying cylinder, (2, 2))."""
        if self.shape == "box":
            return rectangle(self.xy, self.extents, self.yaw)
        if self.shape == "cylinder" and self.orientation == "upright":
            return disc(self.xy, self.size[0], DISC_VERTICES, phase=self.yaw)
        if self.shape == "sphere":
            return self.xy[None, :]
        half = 0.5 * self.size[1] * self.axis
        return np.stack([self.xy - half, self.xy + half])

    def top_face(self) -> np.ndarray | None:
        """The support polygon on top, or None for a curved top (no finite surface)."""
        return None if self.curved_top else self.face()

    def footprint(self) -> np.ndarray:
        """The bottom face (polygon), or the point / segment a curved bottom touches a plane with."""
        return self.face()

    def radius_xy(self) -> float:
        """Radius of the smallest vertical cylinder about the centre that contains the object."""
        ex, ey = self.extents
        if self.shape == "box" or (self.shape == "cylinder" and self.orientation == "lying"):
            return 0.5 * math.hypot(ex, ey)
        return self.size[0]

    def moved(self, **changes) -> StackObject:
        return replace(self, **changes)


def stack_up(objects: list[StackObject]) -> list[StackObject]:
    """Copies of ``objects`` (bottom to top) with each ``z`` set so it rests on the one below."""
    out, base = [], 0.0
    for obj in objects:
        out.append(replace(obj, z=base + obj.height / 2))
        base += obj.height
    return out


def combined_com(objects: list[StackObject]) -> np.ndarray:
    """Eq. 3.1: r = sum_j m_j r_j / sum_j m_j, the centre of mass of several objects (3,)."""
    m = np.array([o.mass for o in objects])
    r = np.stack([o.com for o in objects])
    return (m[:, None] * r).sum(0) / m.sum()


# --------------------------------------------------------------------------------------------
# convex polygons (CCW (N, 2) arrays)
# --------------------------------------------------------------------------------------------

def rectangle(center, extents, yaw: float = 0.0) -> np.ndarray:
    """A CCW rectangle of full ``extents`` (ex, ey) centred at ``center``, rotated by ``yaw``."""
    hx, hy = 0.5 * extents[0], 0.5 * extents[1]
    corners = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    c, s = math.cos(yaw), math.sin(yaw)
    return corners @ np.array([[c, s], [-s, c]]) + np.asarray(center, dtype=float)


def disc(center, radius: float, n: int = DISC_VERTICES, phase: float = 0.0) -> np.ndarray:
    """A CCW regular ``n``-gon inscribed in the circle (a conservative stand-in for a disc)."""
    t = phase + 2 * math.pi * np.arange(n) / n
    return np.asarray(center, dtype=float) + radius * np.stack([np.cos(t), np.sin(t)], axis=1)


def polygon_area(poly: np.ndarray) -> float:
    """Signed area (positive for CCW), 0 for points and segments."""
    p = np.asarray(poly, dtype=float)
    if len(p) < 3:
        return 0.0
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def _dedupe(poly: np.ndarray, tol: float = 1e-12) -> np.ndarray:
    if len(poly) < 2:
        return poly
    keep = np.linalg.norm(poly - np.roll(poly, 1, axis=0), axis=1) > tol
    if not keep.any():
        return poly[:1]
    return poly[keep]


def clip_polygon(subject: np.ndarray, clip: np.ndarray) -> np.ndarray:
    """Sutherland–Hodgman: ``subject`` ∩ ``clip`` for convex CCW polygons; (0, 2) when disjoint."""
    out = np.asarray(subject, dtype=float)
    clip = np.asarray(clip, dtype=float)
    for a, b in zip(clip, np.roll(clip, -1, axis=0)):
        if len(out) == 0:
            break
        edge = b - a
        # > 0 inside (left of the CCW edge)
        side = edge[0] * (out[:, 1] - a[1]) - edge[1] * (out[:, 0] - a[0])
        if np.all(side >= 0):
            continue
        new = []
        prev, prev_side = out[-1], side[-1]
        for cur, cur_side in zip(out, side):
            if cur_side >= 0:
                if prev_side < 0:
                    new.append(prev + (cur - prev) * (prev_side / (prev_side - cur_side)))
                new.append(cur)
            elif prev_side >= 0:
                new.append(prev + (cur - prev) * (prev_side / (prev_side - cur_side)))
            prev, prev_side = cur, cur_side
        out = _dedupe(np.array(new).reshape(-1, 2))
    return out.reshape(-1, 2)


def clip_segment(segment: np.ndarray, clip: np.ndarray) -> np.ndarray:
    """The part of a segment (2, 2) inside a convex CCW polygon (Cyrus–Beck); (0, 2) if none."""
    p0, p1 = np.asarray(segment, dtype=float)
    d = p1 - p0
    t0, t1 = 0.0, 1.0
    for a, b in zip(clip, np.roll(clip, -1, axis=0)):
        edge = b - a
        f0 = edge[0] * (p0[1] - a[1]) - edge[1] * (p0[0] - a[0])  # >= 0 inside
        df = edge[0] * d[1] - edge[1] * d[0]
        if abs(df) < _EPS:
            if f0 < 0:
                return np.zeros((0, 2))
            continue
        t = -f0 / df
        if df > 0:
            t0 = max(t0, t)
        else:
            t1 = min(t1, t)
        if t0 > t1:
            return np.zeros((0, 2))
    return np.stack([p0 + t0 * d, p0 + t1 * d])


def _point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances from ``p`` (2,) to segments a[k]-b[k] (K, 2)."""
    ab = b - a
    denom = np.maximum((ab * ab).sum(-1), _EPS)
    t = np.clip(((p - a) * ab).sum(-1) / denom, 0.0, 1.0)
    return np.linalg.norm(a + t[:, None] * ab - p, axis=-1)


def signed_distance(point, poly: np.ndarray) -> float:
    """Distance from ``point`` to the boundary of the convex CCW ``poly``: positive inside, negative
    outside. A point or segment ``poly`` (a curved contact) has no inside: ``-distance``; an empty one
    gives ``-inf``."""
    p = np.asarray(point, dtype=float)[:2]
    poly = np.asarray(poly, dtype=float).reshape(-1, 2)
    if len(poly) == 0:
        return -math.inf
    if len(poly) == 1:
        return -float(np.linalg.norm(p - poly[0]))
    nxt = np.roll(poly, -1, axis=0)
    dist = float(_point_segment_distance(p, poly, nxt).min())
    if len(poly) < 3 or polygon_area(poly) <= _EPS:
        return -dist
    edge = nxt - poly
    cross = edge[:, 0] * (p[1] - poly[:, 1]) - edge[:, 1] * (p[0] - poly[:, 0])
    return dist if np.all(cross >= 0) else -dist


def inradius(poly: np.ndarray) -> float:
    """Radius of the largest disc inside a convex CCW polygon (the maximum of its signed distance).

    The signed distance ``min_i (b_i - n_i . x)`` is concave, so a grid search that zooms in on its
    best point (8 rounds of 13x13, window shrunk 2.5x per round) finds the maximum to within 1%
    (checked against an LP solver on clipped rectangles and discs), 5x faster than the LP.
    Rectangles are exact (closed form).
    """
    poly = np.asarray(poly, dtype=float).reshape(-1, 2)
    if len(poly) < 3 or polygon_area(poly) <= _EPS:
        return 0.0
    edge = np.roll(poly, -1, axis=0) - poly
    length = np.linalg.norm(edge, axis=1)
    if len(poly) == 4 and abs(np.dot(edge[0], edge[1])) < 1e-9 * length[0] * length[1] \
            and abs(np.dot(edge[1], edge[2])) < 1e-9 * length[1] * length[2]:
        return 0.5 * float(min(length[0], length[1]))  # a rectangle
    ok = length > 1e-12
    normal = np.stack([edge[ok, 1], -edge[ok, 0]], axis=1) / length[ok, None]  # outward for CCW
    b = (normal * poly[ok]).sum(1)
    lo, hi = poly.min(0), poly.max(0)
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    best = -math.inf
    for _ in range(8):
        pts = centre + _GRID * half
        f = (b[None, :] - pts @ normal.T).min(1)
        k = int(np.argmax(f))
        best, centre, half = max(best, float(f[k])), pts[k], half / 2.5
    return max(best, 0.0)


_GRID = np.stack(np.meshgrid(np.linspace(-1, 1, 13), np.linspace(-1, 1, 13)), axis=-1).reshape(-1, 2)


# --------------------------------------------------------------------------------------------
# Lemma 1
# --------------------------------------------------------------------------------------------

def contact_surface(lower: StackObject | None, upper: StackObject) -> np.ndarray | None:
    """A_i: the lower object's top face ∩ the upper object's bottom face (``lower=None``: the ground).

    Returns a CCW polygon, a point (1, 2) or segment (2, 2) when the upper object is curved, an
    empty (0, 2) array when they do not overlap, and None when the lower object is curved (no
    finite surface: a VPSF whatever the positions).
    """
    bottom = upper.footprint()
    if lower is None:
        return bottom
    top = lower.top_face()
    if top is None:
        return None
    if len(bottom) == 1:
        return bottom if signed_distance(bottom[0], top) >= 0 else np.zeros((0, 2))
    if len(bottom) == 2:
        return clip_segment(bottom, top)
    return clip_polygon(bottom, top)


@dataclass
class Interface:
    """Eq. 3.1 at one interface: object ``index`` resting on ``index - 1`` (or on the ground)."""

    index: int
    status: str  # "ok", "VCOM", "VPSF", or "carried" (a curved object carrying a VPSF load)
    contact: np.ndarray | None  # A_i (see contact_surface)
    com: np.ndarray  # (2,) projection of the load's combined centre of mass r_{i+1}^n
    margin: float  # signed distance of com to the boundary of the support region (m), + inside
    inradius: float  # of the support region (m)
    own_margin: float  # the same for the resting object's own centre of mass alone

    @property
    def relative_margin(self) -> float:
        if math.isinf(self.margin):
            return self.margin
        if self.inradius > 0:
            return self.margin / self.inradius
        return math.inf if self.margin > 0 else -math.inf if self.margin < 0 else 0.0

    @property
    def counterbalanced(self) -> bool:
        """The object alone would tip over, but the objects above hold it in place (Fig. 3.2 B)."""
        return self.status == "ok" and self.own_margin < 0 <= self.margin


@dataclass
class StackLabel:
    """The analytic label of a stack.

    ``interface`` is the index of the object that rests badly (interface i: object i on object
    i - 1 or the ground); ``violating_object`` the object the instability is attributed to (the
    support of that interface, see the module doc); both None for a stable stack. ``violations``
    lists every violated interface as ``(interface, type)``; ``violation`` is the lowest one.
    """

    stable: bool
    violation: str | None
    interface: int | None
    violating_object: int | None
    margins: list[float]
    relative_margins: list[float]
    interfaces: list[Interface] = field(repr=False, default_factory=list)
    violations: list[tuple[int, str]] = field(default_factory=list)

    def to_dict(self) -> dict:
        def num(v: float):
            return v if math.isfinite(v) else ("inf" if v > 0 else "-inf")

        return {"stable": self.stable, "violation": self.violation, "interface": self.interface,
                "violating_object": self.violating_object, "violations": [list(v) for v in self.violations],
                "margins": [num(m) for m in self.margins], "relative_margins": [num(m) for m in self.relative_margins]}


def _interface(stack: list[StackObject], i: int, load_com: np.ndarray) -> Interface:
    upper = stack[i]
    lower = stack[i - 1] if i > 0 else None
    if lower is not None and lower.curved_top:  # VPSF: resting on a curved surface
        bottom = upper.footprint()
        contact = lower.xy[None, :] if lower.shape == "sphere" else (
            clip_segment(lower.face(), bottom) if len(bottom) >= 3 else lower.face())
        return Interface(i, "VPSF", contact, load_com, -math.inf, 0.0, -math.inf)
    if upper.curved_bottom:
        # it touches the face below at a point / along a line right under its own centre of mass
        contact = contact_surface(lower, upper)
        if lower is None:
            return Interface(i, "carried" if i < len(stack) - 1 else "ok", contact, load_com, math.inf, math.inf,
                             math.inf)
        face = lower.top_face()
        margin = signed_distance(upper.xy, face)
        status = "carried" if i < len(stack) - 1 else ("ok" if margin >= 0 else "VCOM")
        return Interface(i, status, contact, load_com, margin, inradius(face), margin)
    contact = contact_surface(lower, upper)
    if len(contact) < 3 or polygon_area(contact) <= _EPS:  # not resting on it at all
        return Interface(i, "VCOM", contact, load_com, -math.inf, 0.0, -math.inf)
    margin = signed_distance(load_com, contact)
    own = signed_distance(upper.xy, contact)
    return Interface(i, "ok" if margin >= 0 else "VCOM", contact, load_com, margin, inradius(contact), own)


def lemma1_side_view(blocks) -> dict:
    """Lemma 1 on a tower as a side-on picture shows it: ``blocks`` bottom up as (centre, width, height) along
    the picture's horizontal and vertical axes, in any one unit (pixels, say). Each block is taken as a box as
    deep as it is wide, of uniform density, so only the horizontal axis matters: a tower stable in 3D is
    stable seen from any side, so this is a necessary condition. Returns :meth:`StackLabel.to_dict`."""
    stack = [StackObject("box", (max(float(w), 1e-6), max(float(w), 1e-6), max(float(h), 1e-6)), x=float(c))
             for c, w, h in blocks]
    return analyse(stack).to_dict()


def analyse(stack: list[StackObject]) -> StackLabel:
    """Lemma 1: check Eq. 3.1 at every interface, from the top of the tower down.

    ``stack`` is bottom to top; heights are (re)computed with :func:`stack_up`, so only
    shapes, sizes, orientations and horizontal poses matter. See the module doc for the
    interface numbering, the violation types and which object is "the violating object".
    """
    stack = stack_up(list(stack))
    n = len(stack)
    if n == 0:
        raise ValueError("a stack needs at least one object")
    masses = np.array([o.mass for o in stack])
    coms = np.stack([o.xy for o in stack])
    interfaces: list[Interface] = []
    for i in range(n - 1, -1, -1):  # top to bottom, as in the thesis
        load = (masses[i:, None] * coms[i:]).sum(0) / masses[i:].sum()  # Eq. 3.1, projected on the plane
        interfaces.append(_interface(stack, i, load))
    interfaces.reverse()
    violations = [(f.index, f.status) for f in interfaces if f.status in ("VCOM", "VPSF")]
    if violations:
        where, kind = violations[0]
        return StackLabel(False, kind, where, max(where - 1, 0), [f.margin for f in interfaces],
                          [f.relative_margin for f in interfaces], interfaces, violations)
    return StackLabel(True, None, None, None, [f.margin for f in interfaces],
                      [f.relative_margin for f in interfaces], interfaces, [])
