"""The geometric applicability check of thesis Appendix 4.A: can this tool reach this target?

"The applicability of a tool to a task is determined by sampling 100 interior points of the tool
polygon, overlaying the sampled point with the target and rotating the tool polygon between
[-60, +60] degrees from the y-axis ... If any such pose of the tool satisfies all constraints,
i.e. touching the space behind the red line while not colliding with any obstacle, we consider
the tool applicable for the given task."

Not colliding means here keeping ``CLEARANCE`` (2 mm) from every obstacle, so that a pose the
check accepts is one a simulator accepts too (PyBullet counts surfaces within 1 mm as touching).

One function, :func:`check`, labels the dataset's tools and judges imagined ones (their decoded
mesh seen from above: :func:`mesh_footprint`). The interior points are drawn with a fixed seed,
so a polygon always gets the same verdict. The poses are tried all at once as a vectorised array
of shapely polygons. :func:`pose` turns a pose into a body pose for the simulators
(``scenes.sim_verdict`` confirms labels there).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .tasks import LINE_Y, Task

POINTS = 100  # interior points overlaid with the target
ANGLES = np.radians(np.linspace(-60.0, 60.0, 25))  # 5-degree steps from the y-axis
POINT_SEED = 0
CLEARANCE = 0.002  # m a tool keeps from obstacles: simulators count surfaces within ~1 mm as touching


@dataclass
class Verdict:
    feasible: bool
    point: np.ndarray | None = None  # the tool point on the target (tool frame, m) of a feasible pose
    angle: float | None = None  # its rotation from the y-axis (radians, counter-clockwise)
    poses_tried: int = 0


def interior_points(polygon, n: int = POINTS, seed: int = POINT_SEED) -> np.ndarray:
    """``n`` points drawn uniformly inside ``polygon`` (rejection from its bounding box), (n, 2)."""
    import shapely

    rng = np.random.default_rng(seed)
    x0, y0, x1, y1 = polygon.bounds
    found: list[np.ndarray] = []
    count = 0
    for _ in range(1000):
        cand = np.column_stack([rng.uniform(x0, x1, 4 * n), rng.uniform(y0, y1, 4 * n)])
        keep = cand[shapely.contains_xy(polygon, cand[:, 0], cand[:, 1])]
        found.append(keep)
        count += len(keep)
        if count >= n:
            break
    points = np.concatenate(found)[:n]
    if len(points) < n:  # a degenerate polygon (no area): its vertices stand in
        points = np.asarray(polygon.exterior.coords)[:n]
    return points


def posed_rings(ring: np.ndarray, points: np.ndarray, angles: np.ndarray, target) -> np.ndarray:
    """The outline ``ring`` (K, 2) with each point of ``points`` moved onto ``target`` and rotated
    by each angle about it: (len(points) * len(angles), K, 2)."""
    c, s = np.cos(angles)[None, :, None], np.sin(angles)[None, :, None]  # counter-clockwise rotations
    rel = ring[None, :, :] - points[:, None, :]  # (P, K, 2): the outline seen from each point
    rx, ry = rel[:, None, :, 0], rel[:, None, :, 1]
    posed = np.stack([c * rx - s * ry + target[0], s * rx + c * ry + target[1]], axis=-1)  # (P, A, K, 2)
    return posed.reshape(-1, ring.shape[0], 2)


def check(polygon, task: Task, points: int = POINTS, angles: np.ndarray = ANGLES) -> Verdict:
    """Whether the tool whose top-down outline is ``polygon`` (tool frame, m) reaches ``task``'s
    target from behind the bottom red line without touching an obstacle (Appendix 4.A)."""
    import shapely
    from shapely.geometry import box

    polygon = outline(polygon)
    if polygon is None:
        return Verdict(False)
    pts = interior_points(polygon, points)
    ring = np.asarray(polygon.exterior.coords)
    posed = posed_rings(ring, pts, angles, task.target)
    touches = posed[:, :, 1].min(axis=1) < LINE_Y  # crosses the bottom red line (the outline is the hull's)
    if task.obstacles and touches.any():
        obstacles = shapely.union_all([box(*o) for o in task.obstacles]).buffer(CLEARANCE, join_style="mitre")
        shapely.prepare(obstacles)
        candidates = np.flatnonzero(touches)
        touches[candidates] = ~shapely.intersects(obstacles, shapely.polygons(posed[candidates]))
    hits = np.flatnonzero(touches)
    if not len(hits):
        return Verdict(False, poses_tried=len(posed))
    p, a = divmod(int(hits[0]), len(angles))
    return Verdict(True, pts[p], float(angles[a]), len(posed))


def outline(geometry):
    """The largest polygon of a (multi)polygon, without holes; None if it has no area. Holes are
    filled: an obstacle that would fit in a hole of a tool counts as touched."""
    from shapely.geometry import MultiPolygon, Polygon

    if geometry is None or geometry.is_empty:
        return None
    if isinstance(geometry, MultiPolygon):
        geometry = max(geometry.geoms, key=lambda g: g.area)
    if not isinstance(geometry, Polygon) or geometry.area <= 0:
        return None
    return Polygon(geometry.exterior.coords)


def mesh_footprint(vertices: np.ndarray, faces: np.ndarray, simplify: float = 0.001, closed: bool = True):
    """A mesh's top-down outline: the union of its triangles projected on the table (x, y), as one
    polygon (``outline``), simplified to ``simplify`` m; None for a mesh with no area from above.
    A vertical line through the outline crosses a ``closed``, consistently wound surface as often
    upwards as downwards, so the triangles whose projection winds counter-clockwise cover the
    outline alone (even where the surface folds through itself): half the triangles to unite."""
    import shapely

    tri = np.asarray(vertices, float)[np.asarray(faces)][:, :, :2]  # (F, 3, 2)
    signed = 0.5 * ((tri[:, 1, 0] - tri[:, 0, 0]) * (tri[:, 2, 1] - tri[:, 0, 1])
                    - (tri[:, 2, 0] - tri[:, 0, 0]) * (tri[:, 1, 1] - tri[:, 0, 1]))
    tri = tri[signed > 1e-10] if closed else tri[np.abs(signed) > 1e-10]
    if not len(tri):
        return None
    union = shapely.union_all(shapely.buffer(shapely.polygons(tri), 1e-6, join_style="mitre"))
    shape = outline(union)
    return None if shape is None else shape.simplify(simplify)


def pose(point: np.ndarray, angle: float, target, z: float) -> tuple[np.ndarray, np.ndarray]:
    """The body pose (pos, quat w-x-y-z) that puts tool-frame ``point`` on ``target`` rotated by
    ``angle`` about the vertical."""
    c, s = np.cos(angle), np.sin(angle)
    p = np.asarray(point, float)
    offset = np.array([c * p[0] - s * p[1], s * p[0] + c * p[1]])
    pos = np.array([target[0] - offset[0], target[1] - offset[1], z])
    return pos, np.array([np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)])
