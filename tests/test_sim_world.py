"""Simulated world: analytic 3D truth (velocity, acceleration, turn rate) of every trajectory."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.sim.config import TrajectoryConfig, WorldConfig
from drivers.sim.world import (
    CirclePath,
    Kinematics,
    StopAndGoPath,
    Trajectory,
    World,
    make_trajectory,
    turn_rate,
)

CONFIGS = [
    TrajectoryConfig(kind="static", position_m=(0.5, 0.1, 4.0)),
    TrajectoryConfig(kind="linear", position_m=(-3.0, 0.0, 5.0), end_m=(3.0, 0.2, 7.0)),
    TrajectoryConfig(kind="stop-and-go", position_m=(-2.0, 0.0, 5.0), end_m=(2.0, 0.0, 6.0)),
    TrajectoryConfig(kind="circle", center_m=(0.0, 0.0, 6.0), radius_m=4.0, phase_deg=30.0),
    TrajectoryConfig(kind="figure-eight", center_m=(0.0, 0.0, 5.0), radius_m=2.0, speed_mps=0.3),
    TrajectoryConfig(kind="random", center_m=(0.0, 0.0, 6.0), seed=3),
]
TIMES = np.linspace(0.3, 57.0, 41)


def numeric(traj: Trajectory, t: float, h: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Central differences of the position: velocity and acceleration."""
    p0, pm, pp = traj.position(t), traj.position(t - h), traj.position(t + h)
    return (pp - pm) / (2 * h), (pp - 2 * p0 + pm) / (h * h)


@pytest.mark.parametrize("config", CONFIGS, ids=lambda c: c.kind)
def test_kinematics_are_the_derivatives_of_the_position(config: TrajectoryConfig) -> None:
    traj = make_trajectory(config)
    for t in TIMES:
        kin = traj.kinematics(float(t))
        np.testing.assert_allclose(kin.position_m, traj.position(float(t)), atol=1e-12)
        eight = config.kind == "figure-eight"
        v_num, a_num = numeric(traj, float(t), 0.05 if eight else 1e-3)
        if config.kind == "linear" and abs(t - 21.08) < 0.01:
            continue  # the stop is a velocity step
        # the figure-eight's position goes through a linearly interpolated arc-length table (its
        # speed is off by ~4e-5 relative, its second difference kinked): a longer step, and looser
        tol_v, tol_a = (2e-4, 1e-3) if eight else (1e-5, 1e-4)
        np.testing.assert_allclose(kin.velocity_mps, v_num, atol=tol_v)
        np.testing.assert_allclose(kin.acceleration_mps2, a_num, atol=tol_a)


def test_circle_turn_rate_is_plus_v_over_r_counter_clockwise_from_above() -> None:
    traj = CirclePath(np.array([0.0, 0.0, 6.0]), 4.0, 0.25, 0.0)
    kin = traj.kinematics(3.0)
    assert kin.angular_speed_rad_s == pytest.approx(0.25 / 4.0)
    # phase 0 is the nearest point moving to +x; a quarter lap later it is at +x, moving to +z
    quarter = traj.kinematics(math.pi / 2 * 4.0 / 0.25)
    np.testing.assert_allclose(quarter.position_m, [4.0, 0.0, 6.0], atol=1e-12)
    np.testing.assert_allclose(quarter.velocity_mps, [0.0, 0.0, 0.25], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(kin.acceleration_mps2), 0.25**2 / 4.0)
    assert turn_rate(np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])) == 1.0  # x → z: +
    assert turn_rate(np.zeros(3), np.array([1.0, 0.0, 0.0])) == 0.0  # at rest: no turn


def test_figure_eight_turns_both_ways_at_the_curvature_rate() -> None:
    traj = make_trajectory(TrajectoryConfig(kind="figure-eight", radius_m=2.0, speed_mps=0.3))
    rates = np.array([traj.kinematics(float(t)).angular_speed_rad_s for t in TIMES])
    assert rates.max() > 0.05
    assert rates.min() < -0.05
    for t in TIMES[:10]:
        kin = traj.kinematics(float(t))
        assert float(np.linalg.norm(kin.velocity_mps)) == pytest.approx(0.3)
        assert float(kin.velocity_mps @ kin.acceleration_mps2) == pytest.approx(0.0, abs=1e-9)
        # ω = |a| / v with the sign of the turn
        assert abs(kin.angular_speed_rad_s) == pytest.approx(
            float(np.linalg.norm(kin.acceleration_mps2)) / 0.3
        )


def test_stop_and_go_shuttles_with_rests_and_smooth_starts() -> None:
    start, end = np.array([-2.0, 0.0, 5.0]), np.array([2.0, 0.0, 5.0])
    path = StopAndGoPath(start, end, speed_mps=0.5, stop_s=3.0)  # 4 m legs of 8 s
    rest = path.kinematics(9.5)
    np.testing.assert_allclose(rest.position_m, end)
    assert not np.any(rest.velocity_mps)
    back = path.kinematics(11.0 + 4.0)  # mid second leg, going back at the peak speed 2 v̄
    np.testing.assert_allclose(back.position_m, [0.0, 0.0, 5.0], atol=1e-12)
    np.testing.assert_allclose(back.velocity_mps, [-1.0, 0.0, 0.0], atol=1e-12)
    assert path.kinematics(22.0).position_m == pytest.approx(start)
    for t in (1e-6, 8.0 - 1e-6, 11.0 + 1e-6):  # starts and stops without velocity steps
        assert float(np.linalg.norm(path.kinematics(t).velocity_mps)) < 1e-5
    assert max(abs(path.kinematics(float(t)).angular_speed_rad_s) for t in TIMES) == 0.0


def test_world_pose_carries_the_3d_truth() -> None:
    config = WorldConfig(
        trajectory=TrajectoryConfig(kind="circle", center_m=(0.0, 0.0, 6.0), radius_m=4.0)
    )
    world = World.from_config(config)
    pose = world.pose(10.0)
    kin: Kinematics = world.trajectory.kinematics(10.0)
    np.testing.assert_array_equal(pose.position_m, kin.position_m)
    np.testing.assert_array_equal(pose.velocity_mps, kin.velocity_mps)
    np.testing.assert_array_equal(pose.acceleration_mps2, kin.acceleration_mps2)
    assert pose.angular_speed_rad_s == pytest.approx(0.25 / 4.0)
