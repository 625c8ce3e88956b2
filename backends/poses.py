"""Rigid poses in double precision (Bullet's (x, y, z, w) quaternions): shared by the PyBullet
backend and its Panda arm, so neither imports the other."""

from __future__ import annotations


def compose(pos_a, orn_a, pos_b, orn_b) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Pose ``a * b`` (Bullet order quaternions), in double precision.

    ``pybullet.multiplyTransforms`` and ``invertTransform`` round to float32 (~1e-8 m), which
    would show in poses read back after being set; these few lines do not.
    """
    ax, ay, az, aw = orn_a
    bx, by, bz, bw = orn_b
    # rotate pos_b by orn_a: v + 2 w (u x v) + 2 u x (u x v), with u the vector part
    vx, vy, vz = pos_b
    tx, ty, tz = 2 * (ay * vz - az * vy), 2 * (az * vx - ax * vz), 2 * (ax * vy - ay * vx)
    rx = vx + aw * tx + (ay * tz - az * ty)
    ry = vy + aw * ty + (az * tx - ax * tz)
    rz = vz + aw * tz + (ax * ty - ay * tx)
    pos = (pos_a[0] + rx, pos_a[1] + ry, pos_a[2] + rz)
    orn = (aw * bx + ax * bw + ay * bz - az * by,
           aw * by - ax * bz + ay * bw + az * bx,
           aw * bz + ax * by - ay * bx + az * bw,
           aw * bw - ax * bx - ay * by - az * bz)
    return pos, orn


def invert(pos, orn) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The inverse of a pose (Bullet order quaternion), in double precision."""
    inv_orn = (-orn[0], -orn[1], -orn[2], orn[3])
    p, _ = compose((0.0, 0.0, 0.0), inv_orn, pos, (0.0, 0.0, 0.0, 1.0))
    return (-p[0], -p[1], -p[2]), inv_orn
