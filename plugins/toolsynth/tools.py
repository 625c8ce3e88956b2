"""The tools of the reaching tasks (thesis Appendix 4.A): straight sticks and L-shaped hooks.

A tool is five numbers (:class:`Tool`): its kind, the handle's length and width, the hook's length
and the side the hook points to. In the tool's own frame it lies flat on the table (z up,
``THICKNESS`` thick), the handle along +y with the grip end at the bottom and the hook at the top
end; the frame's origin is the centre of the tool's top-down bounding box. The thesis renders the
tool "in a top-down view for the geometric applicability check": that view is the tool's
footprint, a shapely polygon (:meth:`Tool.footprint`); the 3D tool is that outline extruded by
trimesh (:meth:`Tool.mesh`, written to .obj / .stl by :func:`export_mesh`), and for the
simulators, whose collision meshes are convex, the same solid as one convex box per part
(:meth:`Tool.convex_parts`: the handle, and the hook beside it).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

KINDS = ("stick", "hook")
THICKNESS = 0.02  # m: every tool is a 2 cm thick plate
# the ranges tools are drawn from (m)
HANDLE_LENGTH = (0.12, 0.45)
WIDTH = (0.015, 0.05)
HOOK_LENGTH = (0.04, 0.16)  # beyond the handle's edge


@dataclass(frozen=True)
class Tool:
    kind: str  # "stick" or "hook"
    length: float  # handle length along y, hook included (m)
    width: float  # handle (and hook) width (m)
    hook: float = 0.0  # hook length beyond the handle's edge (m); 0 for a stick
    side: int = 1  # +1: the hook points to +x (right in the task image), -1: to -x

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"tool kind must be one of {', '.join(KINDS)}, got {self.kind!r}")
        if self.kind == "stick" and self.hook:
            raise ValueError("a stick has no hook")

    # -- as numbers (a dataset field) ------------------------------------------------------------
    def to_array(self) -> np.ndarray:
        return np.array([KINDS.index(self.kind), self.length, self.width, self.hook, self.side], np.float32)

    @classmethod
    def from_array(cls, a) -> Tool:
        kind = KINDS[int(round(float(a[0])))]
        return cls(kind, float(a[1]), float(a[2]), float(a[3]) if kind == "hook" else 0.0,
                   1 if float(a[4]) >= 0 else -1)

    def describe(self) -> str:
        text = f"{self.kind}, {self.length * 100:.0f} cm long, {self.width * 100:.1f} cm wide"
        if self.kind == "hook":
            text += f", {self.hook * 100:.0f} cm hook to the {'right' if self.side > 0 else 'left'}"
        return text

    # -- geometry --------------------------------------------------------------------------------
    def _parts_xy(self) -> list[tuple[float, float, float, float]]:
        """Axis-aligned rectangles (x0, y0, x1, y1) of the handle and the hook, before centring."""
        w, half = self.width, self.width / 2
        parts = [(-half, 0.0, half, self.length)]
        if self.kind == "hook":
            if self.side > 0:
                parts.append((half, self.length - w, half + self.hook, self.length))
            else:
                parts.append((-half - self.hook, self.length - w, -half, self.length))
        return parts

    def _offset(self) -> np.ndarray:
        parts = np.array(self._parts_xy())
        lo, hi = parts[:, :2].min(0), parts[:, 2:].max(0)
        return -(lo + hi) / 2  # moves the bounding box's centre to the origin

    def rectangles(self) -> np.ndarray:
        """The parts as rectangles (x0, y0, x1, y1) in the tool frame, (n, 4)."""
        off = self._offset()
        return np.array(self._parts_xy()) + np.concatenate([off, off])

    def footprint(self):
        """The top-down outline, a shapely Polygon in the tool frame (m)."""
        import shapely
        from shapely.geometry import box

        return shapely.union_all([box(*r) for r in self.rectangles()]).normalize()

    def mesh(self):
        """The tool as one watertight trimesh: its footprint extruded by ``THICKNESS``, centred in z."""
        import trimesh

        m = trimesh.creation.extrude_polygon(self.footprint(), THICKNESS)
        m.apply_translation((0, 0, -THICKNESS / 2))
        return m

    def convex_parts(self) -> list:
        """The tool as convex trimesh boxes, one per part (simulators collide convex meshes)."""
        import trimesh

        out = []
        for x0, y0, x1, y1 in self.rectangles():
            part = trimesh.creation.box(extents=(x1 - x0, y1 - y0, THICKNESS))
            part.apply_translation(((x0 + x1) / 2, (y0 + y1) / 2, 0.0))
            out.append(part)
        return out


def footprint_parts(polygon, thickness: float = THICKNESS) -> list:
    """Any outline (an imagined tool's, seen from above) as convex parts a simulator collides: one
    extruded triangle per triangle of its earcut triangulation, centred on z = 0 as tools are."""
    import trimesh

    vertices, faces = trimesh.creation.triangulate_polygon(polygon, engine="earcut")
    parts = []
    for tri in faces:
        part = trimesh.creation.extrude_triangulation(vertices[tri], np.array([[0, 1, 2]]), thickness)
        part.apply_translation((0.0, 0.0, -thickness / 2))
        parts.append(part)
    return parts


def sample_tool(rng: np.random.Generator, kind: str | None = None) -> Tool:
    """A stick or a hook (even odds) with dimensions uniform in the ranges above."""
    kind = kind or KINDS[int(rng.integers(2))]
    length, width = rng.uniform(*HANDLE_LENGTH), rng.uniform(*WIDTH)
    if kind == "stick":
        return Tool("stick", float(length), float(width))
    return Tool("hook", float(length), float(width), float(rng.uniform(*HOOK_LENGTH)), int(rng.choice([-1, 1])))


def export_mesh(mesh, path: Path) -> Path:
    """Write a trimesh as .obj or .stl (by the suffix), atomically."""
    import os

    path = Path(path)
    if path.suffix.lower() not in (".obj", ".stl"):
        raise ValueError(f"a tool mesh is written as .obj or .stl, not {path.suffix!r}")
    tmp = path.with_name(f".{path.name}.tmp{path.suffix}")
    mesh.export(tmp)
    os.replace(tmp, path)
    return path
