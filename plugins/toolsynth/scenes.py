"""The reaching tasks and tools as backend-neutral scenes (thesis Appendix 4.A, Fig. 4.A.1).

One scene per dataset record holds both things a record shows: the task on a table, seen from
straight above by the ``task`` camera, and, 10 m above it in empty space, the tool lying flat with
``views`` cameras around it on a ring (``view0`` ... at equal azimuths, ``elevation`` degrees above
the horizontal, ``data.elevation``; the thesis renders 12 and does not say from how high). The tool's silhouette in a view is where the backend's
segmentation shows the tool body. The cameras of one view are the same on every backend and for
the differentiable renderer that trains the mesh decoder (:func:`tool_cameras`).

:func:`sim_verdict` confirms the geometric label in the simulator: the tool becomes a free body
of convex parts, the obstacles and the region behind the bottom line become solid boxes, and the
same poses as ``feasibility.check`` are tried with ``set_pose``, asking the simulator's contacts.
"""

from __future__ import annotations

import math

import numpy as np

from physint_backends.spec import Body, Camera, Geom, Light, Scene

from . import feasibility
from .tasks import EXTENT, LINE_WIDTH, LINE_X, LINE_Y, TARGET_RADIUS, Task
from .tools import THICKNESS

TOOL_AT = np.array([0.0, 0.0, 10.0])  # where the tool floats, out of the task camera's view
TASK_CAMERA_HEIGHT = 2.0
VIEW_RADIUS = 0.9  # m from the tool's centre
ELEVATION = 30.0  # degrees above the horizontal, of datasets that did not record theirs
VIEW_FOVY = 40.0
OBSTACLE_HEIGHT = 0.04
RGBA = {"table": (0.93, 0.93, 0.9, 1.0), "line": (0.85, 0.1, 0.1, 1.0), "target": (0.1, 0.75, 0.2, 1.0),
        "obstacle": (0.15, 0.3, 0.9, 1.0)}
BACKGROUND = (1.0, 1.0, 1.0)


def task_camera(size: int) -> Camera:
    """Straight down on the table, image up = +y (away from the robot), covering +-EXTENT."""
    fovy = math.degrees(2 * math.atan(EXTENT / TASK_CAMERA_HEIGHT))
    return Camera("task", pos=(0.0, 0.0, TASK_CAMERA_HEIGHT), lookat=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0),
                  fovy=fovy, width=size, height=size)


def tool_cameras(views: int, size: int, center=(0.0, 0.0, 0.0), elevation: float = ELEVATION) -> list[Camera]:
    """``views`` cameras on a ring round a tool at ``center``, at azimuths 0, 360/views, ... deg,
    ``elevation`` degrees above the horizontal."""
    out = []
    el = math.radians(elevation)
    for k in range(views):
        az = 2 * math.pi * k / views
        offset = VIEW_RADIUS * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        out.append(Camera(f"view{k}", pos=tuple(np.asarray(center) + offset), lookat=tuple(center), fovy=VIEW_FOVY,
                          width=size, height=size))
    return out


def task_bodies(task: Task, solid: bool = False) -> list[Body]:
    """The table, the three red lines, the target and the obstacles. ``solid`` (for the contact
    check) leaves out what is only drawn, adds the region behind the line as a box and grows each
    obstacle by the clearance the geometric check keeps from it."""
    h = OBSTACLE_HEIGHT
    bodies = []
    if not solid:
        table_z = 0.005
        bodies.append(Body.box("table", (2 * EXTENT + 0.1, 2 * EXTENT + 0.1, 0.01), pos=(0, 0, -table_z),
                               rgba=RGBA["table"], static=True))
        lines = [((2 * LINE_X + LINE_WIDTH, LINE_WIDTH), (0.0, LINE_Y)),  # bottom
                 ((LINE_WIDTH, EXTENT - LINE_Y), (-LINE_X, (EXTENT + LINE_Y) / 2)),  # left
                 ((LINE_WIDTH, EXTENT - LINE_Y), (LINE_X, (EXTENT + LINE_Y) / 2))]  # right
        for i, ((sx, sy), (x, y)) in enumerate(lines):
            bodies.append(Body.box(f"line{i}", (sx, sy, 0.002), pos=(x, y, 0.001), rgba=RGBA["line"], static=True,
                                   collide=False))
        bodies.append(Body("target", [Geom("cylinder", (TARGET_RADIUS, 0.003), rgba=RGBA["target"])],
                           pos=(task.target[0], task.target[1], 0.0015), static=True, collide=False))
    else:
        bodies.append(Body.box("behind_line", (4 * EXTENT, EXTENT, h), pos=(0.0, LINE_Y - EXTENT / 2, h / 2),
                               static=True))
    grow = feasibility.CLEARANCE if solid else 0.0  # the clearance the geometric check keeps
    for i, (x0, y0, x1, y1) in enumerate(task.obstacles):
        x0, y0, x1, y1 = x0 - grow, y0 - grow, x1 + grow, y1 + grow
        bodies.append(Body.box(f"obstacle{i}", (x1 - x0, y1 - y0, h), pos=((x0 + x1) / 2, (y0 + y1) / 2, h / 2),
                               rgba=RGBA["obstacle"], static=True))
    return bodies


def tool_body(tool_parts: list, rgba, pos=(0.0, 0.0, 0.0), static: bool = True, name: str = "tool") -> Body:
    """A tool as one body of convex mesh parts (``Tool.convex_parts`` or an imagined tool's)."""
    return Body(name, [Geom("mesh", mesh=m, rgba=tuple(rgba)) for m in tool_parts], pos=tuple(pos), static=static,
                density=600.0)


def record_scene(task: Task, tool_parts: list, rgba, task_size: int, views: int, tool_size: int,
                 elevation: float = ELEVATION) -> Scene:
    """A record's scene: the task under the ``task`` camera and the tool (its convex parts, e.g.
    ``Tool.convex_parts()``) under the view cameras."""
    bodies = task_bodies(task) + [tool_body(tool_parts, rgba, pos=TOOL_AT)]
    return Scene(bodies=bodies, cameras=[task_camera(task_size)] + tool_cameras(views, tool_size, TOOL_AT, elevation),
                 lights=[Light(pos=(0.3, -0.4, 3.0), lookat=(0, 0, 0)), Light(pos=(0.3, -0.4, 13.0), lookat=TOOL_AT)],
                 ground=None, background=BACKGROUND)


def render_record(sim, chosen_views, tool_index: int) -> dict[str, np.ndarray]:
    """The task image and the tool's RGB and silhouette in the chosen views of a live record scene."""
    task = sim.render("task").rgb
    rgb, sil = [], []
    for v in chosen_views:
        frame = sim.render(f"view{int(v)}", segmentation=True)
        rgb.append(frame.rgb)
        sil.append((frame.segmentation == tool_index).astype(np.uint8))
    return {"task": task, "tool_rgb": np.stack(rgb), "tool_sil": np.stack(sil)}


def check_scene(task: Task, tool_parts: list) -> Scene:
    """The contact check's world: solid obstacles, the solid region behind the line, and the tool
    as a free body (parked away from everything), no gravity, nothing drawn."""
    tool = tool_body(tool_parts, (0.8, 0.6, 0.2, 1.0), pos=(0.0, 0.0, 1.0), static=False)
    return Scene(bodies=task_bodies(task, solid=True) + [tool], cameras=[], ground=None, gravity=(0.0, 0.0, 0.0))


def sim_verdict(sim, task: Task, polygon, first: feasibility.Verdict | None = None) -> bool:
    """Whether the simulator finds a pose of the tool (the ``check_scene`` of ``sim``) that touches
    the region behind the line and no obstacle, trying ``first``'s witness pose first, then the
    poses of ``feasibility.check``."""
    z = OBSTACLE_HEIGHT / 2

    def reaches(point, angle) -> bool:
        pos, quat = feasibility.pose(point, angle, task.target, z)
        sim.set_pose("tool", pos, quat)
        touching = sim.contacts("tool")
        return "behind_line" in touching and not any(t.startswith("obstacle") for t in touching)

    if first is not None and first.feasible and reaches(first.point, first.angle):
        return True
    for point in feasibility.interior_points(feasibility.outline(polygon)):
        for angle in feasibility.ANGLES:
            if reaches(point, angle):
                return True
    return False


assert OBSTACLE_HEIGHT > THICKNESS  # the tool lies inside the obstacles' height in the contact check


def task_from_image(image: np.ndarray, kind: str = "A") -> Task:
    """A task read back from a top-down task image (``task_camera``'s): the target at the centre of
    the green pixels, each blue region an obstacle rectangle, in table metres (one pixel's
    accuracy: 9 mm at 64 px). None of green: ValueError."""
    from scipy import ndimage

    rgb = np.asarray(image, float)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    size = rgb.shape[0]
    metres = 2 * EXTENT / size

    def x_of(col):
        return (col + 0.5) * metres - EXTENT

    def y_of(row):
        return EXTENT - (row + 0.5) * metres

    green = (g > r + 50) & (g > b + 40)
    if not green.any():
        raise ValueError("no green target button in the task image")
    rows, cols = np.nonzero(green)
    target = (float(x_of(cols.mean())), float(y_of(rows.mean())))
    blue = (b > r + 60) & (b > g + 30)
    labels, count = ndimage.label(blue)
    obstacles = []
    for sl in ndimage.find_objects(labels):
        if sl is None or (sl[0].stop - sl[0].start) * (sl[1].stop - sl[1].start) < 2:
            continue
        top, bottom, left, right = sl[0].start, sl[0].stop - 1, sl[1].start, sl[1].stop - 1
        obstacles.append((float(x_of(left) - metres / 2), float(y_of(bottom) - metres / 2),
                          float(x_of(right) + metres / 2), float(y_of(top) + metres / 2)))
    return Task(kind, target, obstacles[:4])
