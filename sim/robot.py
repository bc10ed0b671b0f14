"""The Jackal in PyBullet: skid-steer drive from ``cmd_vel`` with the Jackal's limits, wheel odometry,
sensor extrinsics read from the URDF's fixed joints."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pybullet as p

from sim.camera import hardware
from stack.transforms import from_xyz_quat, inv

URDF = Path(__file__).parent / "jackal_urdf" / "jackal.urdf"
WHEELS = ("front_left_wheel", "rear_left_wheel", "front_right_wheel", "rear_right_wheel")


def _clip(x: float, limit: float) -> float:
    """``x`` limited to [-limit, limit] (what ``float(np.clip(x, -limit, limit))`` gives, NaN included,
    without NumPy's cost on one number: the robot is commanded at every physics step)."""
    return min(max(x, -limit), limit)


class Jackal:
    def __init__(self, client: int, start_xy_yaw, rng: np.random.Generator):
        self.client = client
        self.hw = hardware()["jackal"]
        x, y, yaw = start_xy_yaw
        z0 = self.hw["wheel_radius"] - self.hw["wheel_z"] + 0.002  # base_link height with wheels on the floor
        self.body = p.loadURDF(str(URDF), [x, y, z0], p.getQuaternionFromEuler([0, 0, yaw]),
                               physicsClientId=client)
        self.links = {}
        self.joints = {}
        for j in range(p.getNumJoints(self.body, physicsClientId=client)):
            info = p.getJointInfo(self.body, j, physicsClientId=client)
            self.joints[info[1].decode()] = j
            self.links[info[12].decode()] = j
        self.wheel_ids = [self.joints[w] for w in WHEELS]
        for jid in self.wheel_ids:
            p.changeDynamics(self.body, jid, lateralFriction=0.9, rollingFriction=0.0, spinningFriction=0.0,
                             physicsClientId=client)
        T_world_base = self.T_world_base()
        self.extrinsics = {name: inv(T_world_base) @ self._link_pose(name)
                           for name in ("velodyne", "camera_color_optical_frame", "camera_link")}
        # command state with acceleration limits
        self.v = 0.0
        self.w = 0.0
        # wheel odometry: per-side scale errors (calibration) drawn from the seed
        slip = self.hw["wheel_odometry_slip"]
        self.odo_scale = 1.0 + slip * rng.standard_normal(2)
        self.T_odom_base = np.eye(4)
        self.odo_v = 0.0
        self.odo_w = 0.0
        self.track_eff = self.hw["track"] * 1.5  # skid-steer effective track (Jackal's wheel_separation_multiplier)

    def _link_pose(self, link: str) -> np.ndarray:
        st = p.getLinkState(self.body, self.links[link], computeForwardKinematics=True, physicsClientId=self.client)
        return from_xyz_quat(st[4], st[5])

    def T_world_base(self) -> np.ndarray:
        return from_xyz_quat(*self.xyz_quat_world_base())

    def xyz_quat_world_base(self) -> tuple[tuple, tuple]:
        """``base_link`` in ``world`` as PyBullet gives it: position and quaternion (x, y, z, w)."""
        return p.getBasePositionAndOrientation(self.body, physicsClientId=self.client)

    @property
    def T_base_velodyne(self) -> np.ndarray:
        return self.extrinsics["velodyne"]

    @property
    def T_base_camera(self) -> np.ndarray:
        return self.extrinsics["camera_color_optical_frame"]

    def command(self, v_cmd: float, w_cmd: float, dt: float) -> None:
        """Apply cmd_vel through the Jackal's speed and acceleration limits to the wheel motors."""
        hw = self.hw
        v_cmd = _clip(float(v_cmd), hw["max_speed"])
        w_cmd = _clip(float(w_cmd), hw["max_yaw_rate"])
        self.v += _clip(v_cmd - self.v, hw["max_accel"] * dt)
        self.w += _clip(w_cmd - self.w, hw["max_yaw_accel"] * dt)
        r = hw["wheel_radius"]
        left = (self.v - self.w * self.track_eff / 2) / r
        right = (self.v + self.w * self.track_eff / 2) / r
        p.setJointMotorControlArray(self.body, self.wheel_ids, p.VELOCITY_CONTROL,
                                    targetVelocities=[left, left, right, right], forces=[20.0] * 4,
                                    physicsClientId=self.client)

    def update_odometry(self, dt: float) -> None:
        """Integrate wheel odometry from the joint speeds (it drifts: slip and scale errors)."""
        states = p.getJointStates(self.body, self.wheel_ids, physicsClientId=self.client)
        r = self.hw["wheel_radius"]
        wl = 0.5 * (states[0][1] + states[1][1]) * r * self.odo_scale[0]
        wr = 0.5 * (states[2][1] + states[3][1]) * r * self.odo_scale[1]
        v = 0.5 * (wl + wr)
        w = (wr - wl) / self.track_eff
        dyaw = w * dt
        c, s = np.cos(dyaw / 2), np.sin(dyaw / 2)
        cy, sy = np.cos(dyaw), np.sin(dyaw)
        step = np.array([[cy, -sy, 0.0, v * dt * c], [sy, cy, 0.0, v * dt * s], [0.0, 0.0, 1.0, 0.0],
                         [0.0, 0.0, 0.0, 1.0]])
        self.T_odom_base = self.T_odom_base @ step
        self.odo_v, self.odo_w = v, w
