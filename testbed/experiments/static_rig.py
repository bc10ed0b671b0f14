"""A static camera rig for the paper's bench experiments: the Jackal parked in an empty room, one
object placed at a given position in the camera's frame (x right, z forward, centroid at the lens'
height), frames rendered with the D435i model."""
from __future__ import annotations

import numpy as np
import pybullet as p
from scipy.spatial.transform import Rotation

from sim.episode import Episode
from sim.objects import load_catalog, spawn_object
from sim.scenario import Scenario
from stack.transforms import inv

RIG = {
    "name": "static_rig",
    "description": "empty room, parked robot (bench experiments)",
    "duration": 1.0,
    "room": {"size": [8.0, 6.0], "wall_height": 2.6},
    "furniture": [{"name": "cabinet", "kind": "box", "position": [3.2, 2.2], "size": [0.8, 0.6, 1.0]},
                  {"name": "shelf", "kind": "shelf", "position": [3.7, -1.0], "size": [0.4, 1.6, 1.4]}],
    "objects": [],
    "robot": {"start": [-1.5, 0.0, 0.0]},
    "route": {"waypoints": [[-1.5, 0.0]]},
    "sensors": {"lidar": False},
}


class StaticRig:
    def __init__(self, cls: str = "E", seed: int = 0, light: float = 1.0, renderer: str = "auto"):
        self.ep = Episode(Scenario.model_validate(RIG), seed=seed, light=light, renderer=renderer, lidar=False)
        self.client = self.ep.client
        self.spec = load_catalog()[cls]
        self.T_world_base = self.ep.robot.T_world_base()
        self.T_world_cam = self.T_world_base @ self.ep.T_base_camera
        self.body = spawn_object(self.client, self.spec, np.eye(4))
        col = p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.03, 0.03, 0.5], physicsClientId=self.client)
        vis = p.createVisualShape(p.GEOM_BOX, halfExtents=[0.03, 0.03, 0.5], rgbaColor=[0.25, 0.25, 0.25, 1],
                                  physicsClientId=self.client)
        self.stand = p.createMultiBody(0, col, vis, [0, 0, -5], physicsClientId=self.client)
        self.ep.world.object_bodies[cls] = self.body
        self.T_world_obj = np.eye(4)
        self.t = 0.0

    def place(self, x_m: float, z_m: float, yaw_to_camera_deg: float = 0.0) -> np.ndarray:
        """Put the object's centroid at (x, lens height, z) in the camera frame, its face towards the
        camera (turned by ``yaw_to_camera_deg``), on a stand. Returns T_cam_obj (truth)."""
        cam = self.T_world_cam
        fwd = cam[:3, 2] * np.array([1, 1, 0])
        fwd /= np.linalg.norm(fwd)
        right = np.array([fwd[1], -fwd[0], 0.0])
        centre = cam[:3, 3] + z_m * fwd + x_m * right
        yaw = np.arctan2(-fwd[1], -fwd[0]) + np.radians(yaw_to_camera_deg)
        bottom = centre - [0, 0, self.spec.height / 2]
        T = self.spec.standing_pose(bottom, yaw)
        quat = Rotation.from_matrix(T[:3, :3]).as_quat()
        p.resetBasePositionAndOrientation(self.body, list(T[:3, 3]), list(quat), physicsClientId=self.client)
        # the stand is a 1 m tall post whose top is the object's bottom
        p.resetBasePositionAndOrientation(self.stand, [bottom[0], bottom[1], bottom[2] - 0.5], [0, 0, 0, 1],
                                          physicsClientId=self.client)
        self.T_world_obj = T
        return inv(cam) @ T

    def frame(self, dt: float = 0.1):
        """One camera frame (RGB + depth with noise) of the current setup."""
        f = self.ep._camera_frame(self.t, self.T_world_base)
        self.t += dt
        return f

    def close(self):
        self.ep.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
