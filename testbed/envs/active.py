"""``DopeSlamActiveLabelling-v0``: labelling as in ``DopeSlamLabelling-v0``, live, with the policy
also driving the robot (active labelling: go and look again where a label is doubtful).

Each step simulates one camera period: the velocity command of the action drives the Jackal
through the physics, the LiDAR feeds KISS-ICP and the image goes through DOPE and fusion exactly
as in ``dopeslam run`` (``perception_cache.LivePerception``). Every env owns its own PyBullet
client (``sim.episode.Episode``), so several run side by side in one process or in workers.

Observation, reward and ``info``: as ``DopeSlamLabelling-v0`` (``labelling``), plus
``info["route_map"]``: the scenario's waypoints in the ``map`` frame (the route a person would give
the robot; ``RouteDriver`` follows it). Action: ``Dict(labels=MultiDiscrete([4] * max_objects),
velocity=Box(-1, 1, (2,)))``: forward speed and yaw rate as fractions of ``max_speed``
(default 1 m/s, 2 rad/s). The episode lasts the
scenario's duration (or ``duration``).
"""
from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from stack.transforms import inv, transform_points
from testbed.envs import perception_cache as pc
from testbed.envs.labelling import (catalog_classes, class_dims, final_score, observation_space, pose_features,
                                    resolve_input, truth_in_map)
from testbed.envs.render import TopDownMap, camera_panel, side_by_side
from testbed.envs.slots import N_ACTIONS, RewardConfig, SlotMap, floor_half_extents, with_lists


class VelocityCommand:
    """Stands in for the episode's route follower: returns the policy's last command."""

    def __init__(self):
        self.v = self.w = 0.0

    def __call__(self, t: float, T_world_base: np.ndarray) -> tuple[float, float]:
        return self.v, self.w


class DopeSlamActiveLabellingEnv(gym.Env):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, scenario=None, seeds=None, duration: float | None = None, light: float | None = None,
                 input_mode: str = "auto", stages: int = 6, weights=None, max_objects: int = 16,
                 gate_m: float = 0.5, reward: RewardConfig | dict | None = None, detector_factory=None,
                 render_mode: str | None = None, max_speed: tuple = (1.0, 2.0), renderer: str = "auto"):
        from sim.scenario import DEFAULT_SCENARIO, load_scenario

        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode: expected one of {self.metadata['render_modes']} or None, got {render_mode!r}")
        self.render_mode = render_mode
        self.scenario = load_scenario(scenario or DEFAULT_SCENARIO)
        self.seeds = None if seeds is None else ([int(seeds)] if np.isscalar(seeds) else [int(s) for s in seeds])
        self.duration, self.light = duration, light
        self.input_mode = resolve_input(input_mode, self.scenario)
        self.stages, self.weights = int(stages), weights
        self.gate_m = float(gate_m)
        self.reward_cfg = RewardConfig(**reward) if isinstance(reward, dict) else (reward or RewardConfig())
        self._factory = detector_factory
        self.renderer = renderer
        self.classes = catalog_classes()
        self._dims = class_dims(self.classes)
        self.N = int(max_objects)
        self.observation_space = observation_space(self.N, len(self.classes))
        v, w = float(max_speed[0]), float(max_speed[1])
        self.action_space = spaces.Dict({
            "labels": spaces.MultiDiscrete(np.full(self.N, N_ACTIONS, dtype=np.int64)),
            "velocity": spaces.Box(-1.0, 1.0, (2,), dtype=np.float32),  # fractions of max_speed
        })
        self.max_speed = np.array([v, w])
        self.ep = None
        self.slots: SlotMap | None = None
        self._gen = None
        self._detector = None

    # --- the live pipeline ------------------------------------------------------------------------
    def _make_detector(self, ep):
        if self._factory is not None:
            return self._factory(ep)
        if self._detector is None:  # DOPE does not depend on the episode: build it once
            self._detector = pc.dope_factory(self.input_mode, self.stages, self.weights)[0](ep)
        return self._detector

    def _close_episode(self) -> None:
        if self._gen is not None:
            self._gen.close()
            self._gen = None
        if self.ep is not None:
            self.ep.close()
            self.ep = None

    def _next_frame(self):
        ff = next(self._gen, None)
        if ff is None:
            return None
        if ff.T_map_base is not None:
            self._T_map_base = ff.T_map_base
        d = ff.detections[self.stages]
        d["err"] = self.slots.errors_to_truth(d["xyz"], d["cls"]) if self.slots is not None else np.zeros(len(d["cls"]))
        d["stamp"] = np.full(len(d["cls"]), ff.stamp)
        floor = self.live.odom.floor_plane_map()
        if self.slots is not None and self.slots.floor is None and floor is not None:
            self.slots.floor = floor
        d["half"] = floor_half_extents(d["quat"], d["cls"], self._dims, floor)
        return ff, with_lists(d)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        from sim.episode import Episode

        super().reset(seed=seed)
        options = options or {}
        self._close_episode()
        if "seed" in options:
            ep_seed = int(options["seed"])
        elif self.seeds is not None:
            ep_seed = self.seeds[int(self.np_random.integers(len(self.seeds)))]
        else:
            ep_seed = int(self.np_random.integers(2 ** 31 - 1))
        self.ep = ep = Episode(self.scenario, seed=ep_seed, duration=self.duration, light=self.light,
                               renderer=self.renderer)
        self.command = VelocityCommand()
        ep.follower = self.command
        self.live = pc.LivePerception(ep, self._make_detector(ep), self.classes, self.input_mode, (self.stages,),
                                      keep_images=self.render_mode is not None)
        self._gen = self.live.frames()
        self._T_map_base = np.eye(4)
        self.slots = None
        got = self._next_frame()
        if got is None:
            raise RuntimeError(f"{self.scenario.name}: the episode produced no fused camera frame "
                               "(is it shorter than one LiDAR sweep?)")
        stamps, _ = self.live.odom.trajectory()
        self.T_world_map = ep.T_world_base_at(stamps[0])  # map = base_link at the first registered scan
        truth_cls, truth_xyz = truth_in_map(ep.objects, self.T_world_map, self.classes)
        self.slots = SlotMap(self.N, len(self.classes), truth_cls, truth_xyz, self.gate_m, self.reward_cfg,
                             floor=self.live.odom.floor_plane_map())
        ff, d = got
        d["err"] = self.slots.errors_to_truth(d["xyz"], d["cls"])
        d["err_list"] = d["err"].tolist()
        T_map_world = inv(self.T_world_map)
        self.route_map = transform_points(T_map_world, np.array([[w[0], w[1], 0.0] for w in
                                                                  self.scenario.route.waypoints]))[:, :2]
        self.path = []
        self.episode_seed = ep_seed
        self._set_frame(ff, d)
        return self._obs(), self._info()

    def _set_frame(self, ff, d) -> None:
        self.frame = ff
        self.frame_dets = d
        self.slots.observe(d, 0, len(d["cls"]), self.stages)
        self.path.append(self._T_map_base[:2, 3].copy())

    def step(self, action):
        if self.slots is None or self._gen is None:
            raise RuntimeError("step() before reset() or after the episode ended")
        labels = np.asarray(action["labels"])
        v, w = np.clip(np.asarray(action["velocity"], dtype=float), -1.0, 1.0) * self.max_speed
        reward = self.slots.act(labels)
        self.command.v, self.command.w = float(v), float(w)
        got = self._next_frame()
        terminated = got is None
        if terminated:
            self.slots.observe(self.frame_dets, 0, 0, self.stages)
            info = self._info()
            info["map_score"] = final_score(self.slots, self.ep.objects, self.T_world_map, self.classes)
            info["episode"] = {"scenario": self.scenario.name, "seed": self.episode_seed, "input": self.input_mode,
                               "frames": self.live.n_frames}
            self._close_episode()
        else:
            self._set_frame(*got)
            info = self._info()
        return self._obs(terminated), float(reward), terminated, False, info

    def _obs(self, done: bool = False) -> dict:
        duration = self.duration or self.scenario.duration
        frac = 1.0 if done else self.frame.stamp / max(duration, 1e-9)
        return {"slots": self.slots.slots_obs(), "pose": pose_features(self._T_map_base, frac)}

    def _info(self) -> dict:
        det_err, lab_err = self.slots.oracle_info()
        return {"detection_error_m": det_err, "label_error_m": lab_err, "map_cost": self.slots.cost,
                "route_map": self.route_map.copy(), "stamp": self.frame.stamp}

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self.slots is None:
            raise RuntimeError("render() before reset()")
        d = self.frame_dets
        info = self.scenario.sensors
        kps = [(d["kp"][i], d["cls"][i], d["fpr"][i]) for i in range(len(d["cls"]))]
        left = camera_panel(self.frame.image, (info.camera_width, info.camera_height), kps,
                            caption=f"{self.scenario.name} t={self.frame.stamp:.1f}s (active)")
        s = self.slots
        lab = np.flatnonzero(s.has)
        labels = [(s.label[j], s.cls[j], float(s.label_err[j])) for j in lab]
        pts = np.concatenate(self.live.map_points) if self.live.map_points else np.zeros((0, 2))
        tdm = TopDownMap(pts, np.asarray(self.path), s.truth_xyz[:, :2])
        right = tdm.draw(np.asarray(self.path), self._T_map_base, s.truth_cls, labels,
                         [(d["xyz"][i], d["cls"][i]) for i in range(len(d["cls"]))])
        return side_by_side(left, right)

    def close(self):
        self._close_episode()
        super().close()


class RouteDriver:
    """Drives the scenario's route (``info["route_map"]``) from the estimated pose in the observation:
    heading control, slowing for turns, as the scripted episodes do."""

    def __init__(self, speed: float = 0.3, tolerance: float = 0.1, max_speed: tuple = (1.0, 2.0)):
        self.speed, self.tolerance = speed, tolerance
        self.max_speed = np.asarray(max_speed, dtype=float)
        self.idx = 0

    def reset(self) -> None:
        self.idx = 0

    def __call__(self, obs: dict, info: dict) -> np.ndarray:
        route = info["route_map"]
        x, y, _, c, s, _ = obs["pose"]
        while self.idx < len(route) and math.hypot(route[self.idx][0] - x, route[self.idx][1] - y) < self.tolerance:
            self.idx += 1
        if self.idx >= len(route):
            return np.zeros(2, dtype=np.float32)
        gx, gy = route[self.idx]
        err = (math.atan2(gy - y, gx - x) - math.atan2(s, c) + math.pi) % (2 * math.pi) - math.pi
        w = float(np.clip(3.0 * err, -1.5, 1.5))
        v = self.speed * max(0.0, math.cos(err)) ** 4
        return (np.array([v, w]) / self.max_speed).astype(np.float32)


class ActivePolicy:
    """A labelling baseline (``policies``) with a driver: the active env's action."""

    def __init__(self, labelling, driver=None, env=None):
        max_speed = tuple(env.unwrapped.max_speed) if env is not None else (1.0, 2.0)
        self.labelling, self.driver = labelling, driver or RouteDriver(max_speed=max_speed)

    def reset(self) -> None:
        self.labelling.reset()
        self.driver.reset()

    def __call__(self, obs: dict, info: dict) -> dict:
        return {"labels": self.labelling.labels(obs["slots"], info).astype(np.int64),
                "velocity": self.driver(obs, info)}
