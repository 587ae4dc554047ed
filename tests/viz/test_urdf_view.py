"""The 3D view's own URDF drawing (viz/urdf_view.py): every robot's URDF of ours is read (boxes,
cylinders, the joint tree), a joint's value turns or moves its child frame the right way, what it
cannot draw is refused, and the appliance does not import the trimesh stack for it (the memory it
saves is the point: issue 30's 250 MB)."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from xrflab.viz import scene
from xrflab.viz.urdf_view import UrdfError, UrdfView, parse, quat_axis, quat_rpy

REPO = Path(__file__).resolve().parents[2]


def rot(q: tuple[float, float, float, float]) -> np.ndarray:
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rx(a: float) -> np.ndarray:
    return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])


def ry(a: float) -> np.ndarray:
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def rz(a: float) -> np.ndarray:
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


@pytest.mark.parametrize("rpy", [(0.3, 0.0, 0.0), (0.0, 1.5708, 0.0), (0.2, -0.7, 1.1), (-2.0, 0.4, 3.0)])
def test_rpy_is_urdfs_fixed_axis_x_then_y_then_z(rpy: tuple[float, float, float]) -> None:
    expected = rz(rpy[2]) @ ry(rpy[1]) @ rx(rpy[0])
    assert np.allclose(rot(quat_rpy(rpy)), expected, atol=1e-12)


def test_a_joint_turns_about_its_axis() -> None:
    # tilt_joint of Jiwy turns about -y: positive looks up, the camera's +x goes up (+z).
    up = rot(quat_axis((0.0, -1.0, 0.0), 0.5)) @ np.array([1.0, 0.0, 0.0])
    assert up[2] > 0.4 and abs(up[1]) < 1e-12


@pytest.mark.parametrize(
    ("path", "actuated"),
    [
        (scene.URDF_JIWY, ("pan_joint", "tilt_joint")),
        (scene.URDF_CELL, ("table_joint", "press_joint", "feeder_joint")),
        (scene.URDF_YOUBOT, ("j1", "j2", "j3", "j4", "j5")),
    ],
)
def test_every_robot_of_ours_is_read(path: Path, actuated: tuple[str, ...]) -> None:
    robot = parse(path)
    assert tuple(j.name for j in robot.joints if j.kind != "fixed") == actuated
    assert sum(len(v) for v in robot.links.values()) >= 4
    assert all(v.shape in ("box", "cylinder") for vs in robot.links.values() for v in vs)


def test_what_it_cannot_draw_is_refused(tmp_path: Path) -> None:
    mesh = tmp_path / "mesh.urdf"
    mesh.write_text(
        '<robot name="r"><link name="a"><visual><geometry><mesh filename="x.stl"/></geometry></visual></link></robot>'
    )
    with pytest.raises(UrdfError, match="only one box or cylinder"):
        parse(mesh)
    floating = tmp_path / "floating.urdf"
    floating.write_text(
        '<robot name="r"><link name="a"/><link name="b"/>'
        '<joint name="j" type="floating"><parent link="a"/><child link="b"/></joint></robot>'
    )
    with pytest.raises(UrdfError, match="type 'floating'"):
        parse(floating)


def test_a_scene_of_each_robot_in_a_real_viser_server() -> None:
    import viser

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        jiwy = UrdfView(server, scene.URDF_JIWY, "/jiwy")
        ghost = UrdfView(server, scene.URDF_JIWY, "/ghost", mesh_color_override=(0.1, 0.8, 0.3, 0.3))
        jiwy.update_cfg(np.array([0.4, -0.2]))
        pan = jiwy._moving[0][1]
        assert np.allclose(pan.wxyz, quat_axis((0.0, 0.0, 1.0), 0.4))
        ghost.show_visual = False
        assert not any(h.visible for h in ghost._visuals) and all(h.visible for h in jiwy._visuals)
        cell = UrdfView(server, scene.URDF_CELL, "/cell")
        cell.update_cfg([0.0, 0.1, 0.05])
        press = cell._moving[1][1]
        assert np.allclose(press.position, (0.0, 0.0, -0.1))  # press_joint's axis is -z: it goes down
        youbot = UrdfView(server, scene.URDF_YOUBOT, "/youbot/robot")
        youbot.update_cfg(np.zeros(5))
        for view in (jiwy, ghost, cell, youbot):
            view.remove()
    finally:
        server.stop()


def test_the_3d_view_does_not_import_the_trimesh_stack() -> None:
    """viz.scene with its three URDF robots drawn: no yourdfpy, trimesh, scipy.spatial or shapely
    in the process (they were 77 MB resident with viser's ViserUrdf)."""
    code = (
        "import sys, viser\n"
        "from xrflab.viz import scene\n"
        "from xrflab.viz.urdf_view import UrdfView\n"
        "s = viser.ViserServer(host='127.0.0.1', port=0, verbose=False)\n"
        "for p in (scene.URDF_JIWY, scene.URDF_CELL, scene.URDF_YOUBOT): UrdfView(s, p, '/r' + p.stem)\n"
        "s.stop()\n"
        "print('loaded:', *(m for m in ('yourdfpy', 'trimesh', 'shapely', 'embreex', 'rtree') if m in sys.modules))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO / "appliance", check=True
    )
    assert out.stdout.strip().splitlines()[-1] == "loaded:", out.stdout
