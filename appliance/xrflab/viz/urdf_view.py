"""A robot of ours drawn in the 3D view from its URDF (viz/urdf/*.urdf), with viser's own
primitives.

Why not viser's ViserUrdf: it loads the URDF through yourdfpy and trimesh, which import scipy,
shapely, embree, rtree, networkx and lxml: 77 MB of resident memory in the appliance from the
first 3D view until it stops (measured: `import viser` 48 MB, + ViserUrdf 125 MB), against the
appliance's budget of 250 MB for everything (issue 30). Our URDFs are written here and only use
boxes and cylinders, so the standard library's XML parser and viser's `add_box`/`add_cylinder`
draw them. Anything else in a URDF (a mesh, a sphere, a joint type other than fixed, revolute,
continuous, prismatic) is refused when the file is read, so a new robot's URDF that needs more is
found by its test, not drawn wrong.

The scene tree, per joint: a frame at the joint's origin under the parent link's frame, and under
it the child link's frame, which the joint's value turns (about `axis`) or moves (along it).
`update_cfg` takes the actuated joints' values in the order the file lists them, as ViserUrdf
did."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

ACTUATED = ("revolute", "continuous", "prismatic")


class UrdfError(ValueError):
    """A URDF this view does not draw (what and where)."""


@dataclass(frozen=True)
class Visual:
    shape: str  # "box" or "cylinder"
    size: tuple[float, float, float]  # box: x y z; cylinder: radius, length, 0
    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float]
    rgba: tuple[float, float, float, float]


@dataclass(frozen=True)
class Joint:
    name: str
    kind: str
    parent: str
    child: str
    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float]
    axis: tuple[float, float, float]


@dataclass
class Robot:
    root: str
    links: dict[str, list[Visual]] = field(default_factory=dict)
    joints: list[Joint] = field(default_factory=list)  # parents before children


def _floats(text: str | None, n: int, what: str) -> tuple[float, ...]:
    parts = (text or "").split()
    if len(parts) != n:
        raise UrdfError(f"{what}: {n} numbers expected, got {text!r}")
    return tuple(float(p) for p in parts)


def _origin(el: ET.Element | None, what: str) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    if el is None:
        return (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
    xyz = _floats(el.get("xyz", "0 0 0"), 3, f"{what} origin xyz")
    rpy = _floats(el.get("rpy", "0 0 0"), 3, f"{what} origin rpy")
    return xyz, rpy  # type: ignore[return-value]


def parse(path: Path) -> Robot:
    """The links' boxes and cylinders and the joint tree of a URDF."""
    top = ET.parse(path).getroot()
    colors: dict[str, tuple[float, ...]] = {}
    for m in top.findall("material"):
        c = m.find("color")
        if c is not None:
            colors[m.get("name", "")] = _floats(c.get("rgba"), 4, f"material {m.get('name')}")
    links: dict[str, list[Visual]] = {}
    for link in top.findall("link"):
        name = link.get("name", "")
        visuals = []
        for i, v in enumerate(link.findall("visual")):
            what = f"{path.name}: link {name} visual {i}"
            xyz, rpy = _origin(v.find("origin"), what)
            geometry = v.find("geometry")
            shapes = list(geometry) if geometry is not None else []
            if len(shapes) != 1 or shapes[0].tag not in ("box", "cylinder"):
                raise UrdfError(f"{what}: only one box or cylinder is drawn, got {[s.tag for s in shapes]}")
            g = shapes[0]
            if g.tag == "box":
                size = _floats(g.get("size"), 3, f"{what} box size")
            else:
                size = (float(g.get("radius", "nan")), float(g.get("length", "nan")), 0.0)
            mat = v.find("material")
            rgba: tuple[float, ...] = (0.7, 0.7, 0.7, 1.0)
            if mat is not None:
                c = mat.find("color")
                named = colors.get(mat.get("name", ""), rgba)
                rgba = _floats(c.get("rgba"), 4, f"{what} color") if c is not None else named
            visuals.append(Visual(g.tag, size, xyz, rpy, rgba))  # type: ignore[arg-type]
        links[name] = visuals
    joints: dict[str, Joint] = {}
    for el in top.findall("joint"):
        name, kind = el.get("name", ""), el.get("type", "")
        if kind not in ("fixed", *ACTUATED):
            raise UrdfError(f"{path.name}: joint {name}: type {kind!r} is not drawn")
        parent, child = el.find("parent"), el.find("child")
        if parent is None or child is None:
            raise UrdfError(f"{path.name}: joint {name}: parent and child links needed")
        xyz, rpy = _origin(el.find("origin"), f"{path.name}: joint {name}")
        axis_el = el.find("axis")
        axis = _floats(axis_el.get("xyz"), 3, f"joint {name} axis") if axis_el is not None else (1.0, 0.0, 0.0)
        joints[name] = Joint(name, kind, parent.get("link", ""), child.get("link", ""), xyz, rpy, axis)  # type: ignore[arg-type]
    children = {j.child for j in joints.values()}
    roots = [n for n in links if n not in children]
    if len(roots) != 1:
        raise UrdfError(f"{path.name}: one root link expected, got {roots}")
    robot = Robot(roots[0], links)
    # Parents before children, each joint in the file's order among those ready.
    placed = {roots[0]}
    pending = list(joints.values())
    while pending:
        ready = [j for j in pending if j.parent in placed]
        if not ready:
            raise UrdfError(f"{path.name}: joints {[j.name for j in pending]} hang from no placed link")
        for j in ready:
            robot.joints.append(j)
            placed.add(j.child)
            pending.remove(j)
    return robot


def quat_rpy(rpy: tuple[float, float, float]) -> tuple[float, float, float, float]:
    """URDF's fixed-axis roll, pitch, yaw (about x, then y, then z) as a wxyz quaternion."""
    r, p, y = (a / 2 for a in rpy)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


def quat_axis(axis: tuple[float, float, float], angle: float) -> tuple[float, float, float, float]:
    n = math.sqrt(sum(a * a for a in axis)) or 1.0
    s = math.sin(angle / 2) / n
    return (math.cos(angle / 2), axis[0] * s, axis[1] * s, axis[2] * s)


class UrdfView:
    """One robot in a viser scene under `root_node_name`; `mesh_color_override` (r, g, b, a in
    0..1) draws every part in one colour (the setpoint's translucent ghost)."""

    def __init__(
        self,
        server: Any,
        path: Path,
        root_node_name: str,
        mesh_color_override: tuple[float, float, float, float] | None = None,
    ) -> None:
        robot = parse(path)
        scene = server.scene
        self._root = scene.add_frame(root_node_name, show_axes=False)
        frame_of = {robot.root: root_node_name}
        self._moving: list[tuple[Joint, Any]] = []
        for j in robot.joints:
            at = f"{frame_of[j.parent]}/{j.name}"
            scene.add_frame(at, show_axes=False, wxyz=quat_rpy(j.rpy), position=j.xyz)
            child = scene.add_frame(f"{at}/{j.child}", show_axes=False)
            frame_of[j.child] = f"{at}/{j.child}"
            if j.kind in ACTUATED:
                self._moving.append((j, child))
        self._visuals = []
        for link, visuals in robot.links.items():
            for i, v in enumerate(visuals):
                rgba = mesh_color_override or v.rgba
                color = tuple(int(round(255 * c)) for c in rgba[:3])
                opacity = rgba[3] if rgba[3] < 1.0 else None
                name = f"{frame_of[link]}/visual_{i}"
                if v.shape == "box":
                    h = scene.add_box(
                        name, color=color, dimensions=v.size, opacity=opacity, wxyz=quat_rpy(v.rpy), position=v.xyz
                    )
                else:
                    h = scene.add_cylinder(
                        name,
                        radius=v.size[0],
                        height=v.size[1],
                        color=color,
                        opacity=opacity,
                        wxyz=quat_rpy(v.rpy),
                        position=v.xyz,
                    )
                self._visuals.append(h)
        self._show = True

    def joint_names(self) -> tuple[str, ...]:
        """The actuated joints, in the order `update_cfg` takes their values."""
        return tuple(j.name for j, _ in self._moving)

    def update_cfg(self, configuration: np.ndarray | list[float]) -> None:
        """The actuated joints' values (rad, or m for a prismatic joint); missing ones stay."""
        for (j, frame), q in zip(self._moving, np.asarray(configuration, dtype=float)):
            if j.kind == "prismatic":
                frame.position = (j.axis[0] * q, j.axis[1] * q, j.axis[2] * q)
            else:
                frame.wxyz = quat_axis(j.axis, float(q))

    @property
    def show_visual(self) -> bool:
        return self._show

    @show_visual.setter
    def show_visual(self, visible: bool) -> None:
        self._show = bool(visible)
        for h in self._visuals:
            h.visible = self._show

    def remove(self) -> None:
        """The whole robot (viser removes a frame's subtree with it)."""
        self._root.remove()
