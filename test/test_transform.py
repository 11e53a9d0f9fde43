"""Quaternions and rigid transforms (core/geometry/quaternion.py, core/geometry/transform.py):
worked numbers."""

from __future__ import annotations

import math

import pytest

from sensing_nodes.core.geometry import quaternion as quat
from sensing_nodes.core.geometry.transform import Transform


def close(a, b, tol=1e-12):
    return all(abs(x - y) <= tol for x, y in zip(a, b, strict=True))


def test_upside_down_mount_turns_z_over():
    upside_down = quat.from_rpy(math.pi, 0.0, 0.0)
    assert close(upside_down, (1.0, 0.0, 0.0, math.cos(math.pi / 2)))
    assert close(quat.rotate(upside_down, (0.0, 0.0, 1.0)), (0.0, 0.0, -1.0))
    # A rate about the sensor's z is a rate about -z of the base.
    assert close(quat.rotate(upside_down, (0.0, 0.0, 0.3)), (0.0, 0.0, -0.3))


def test_yaw_quarter_turn_rotates_x_onto_y():
    q = quat.from_rpy(0.0, 0.0, math.pi / 2)
    assert close(quat.rotate(q, (1.0, 0.0, 0.0)), (0.0, 1.0, 0.0))
    assert quat.yaw(q) == pytest.approx(math.pi / 2, abs=1e-15)


@pytest.mark.parametrize('rpy', [(0.1, -0.2, 0.3), (-3.0, 1.2, 2.5), (0.0, 0.0, -3.1)])
def test_rpy_round_trip(rpy):
    assert close(quat.to_rpy(quat.from_rpy(*rpy)), rpy, 1e-12)


def test_product_is_rotation_composition():
    a, b = quat.from_rpy(0.3, 0.1, -0.4), quat.from_rpy(-1.0, 0.5, 2.0)
    v = (0.2, -1.5, 0.7)
    assert close(quat.rotate(quat.multiply(a, b), v), quat.rotate(a, quat.rotate(b, v)), 1e-12)


def test_unit_check_refuses_nan_and_far_from_unit():
    assert quat.is_unit((0.0, 0.0, 0.0, 1.0))
    assert quat.is_unit((0.0, 0.0, 0.7071, 0.7071))          # 4 printed digits
    assert not quat.is_unit((0.0, 0.0, 0.0, 0.0))
    assert not quat.is_unit((0.0, 0.0, 0.0, 2.0))
    assert not quat.is_unit((math.nan, 0.0, 0.0, 1.0))


def test_laser_point_into_base_frame():
    # A laser 0.1 m ahead of base_link, turned 90 deg left: its x axis is base_link's y axis.
    base_to_laser = Transform.from_planar(0.1, 0.0, math.pi / 2)
    hit = Transform((1.0, 0.0, 0.0))
    assert close(base_to_laser.compose(hit).translation, (0.1, 1.0, 0.0))


def test_compose_with_inverse_is_identity():
    t = Transform((0.3, -0.2, 0.5), quat.from_rpy(0.4, -0.3, 2.0))
    both = t.compose(t.inverse())
    assert close(both.translation, (0.0, 0.0, 0.0), 1e-12)
    assert quat.angle_between(both.rotation, quat.IDENTITY) < 1e-7


def test_planar_round_trip_and_distance():
    t = Transform.from_planar(1.5, -2.0, -3.0)
    assert close(t.planar(), (1.5, -2.0, -3.0), 1e-12)
    d, a = t.distance_to(Transform.from_planar(1.5, -1.0, -3.0 + 0.1))
    assert d == pytest.approx(1.0) and a == pytest.approx(0.1)


@pytest.mark.parametrize('rpy', [(0.0, 0.0, 0.0), (math.pi, 0.0, 0.0), (-math.pi / 2, 0.0, 0.3),
                                 (0.2, -0.4, 2.9), (-1.0, 1.2, -3.0)])
def test_mount_rpy_is_mount_rotation_inverted(rpy):
    """The doctor reports a declared mount matrix as roll, pitch, yaw: the angles it was made of
    (pitch within +-pi/2)."""
    from sensing_nodes.core.geometry.imu_mount import mount_rotation, mount_rpy

    assert close(mount_rpy(mount_rotation(*rpy)), rpy, tol=1e-12)
