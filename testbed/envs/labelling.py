"""``DopeSlamLabelling-v0``: choose, per object and per camera frame, what a DOPE detection does to
that object's map label, on the cached perception of drive-through episodes.

Each step is one camera frame of an episode, after DOPE and fusion (``perception_cache``).

Observation (``Dict``):

- ``slots`` (max_objects, F) float32, one row per object slot (``slots.slot_features`` names the
  columns): a present flag (a detection of this slot in this frame), whether the slot is in use,
  its class one-hot, the detection's map-frame position, belief sum, FPR verdict (1 = passed),
  range (m) and stage count / 6; then the slot's label: whether it has one (is published), its
  position, log evidence count, belief sum, the detection-to-label distance and log of the slot's
  detections; then the slot's evidence as the stack judges it before publishing an object
  (``stack.evidence``; ``slots`` describes each): its FPR-passing detections within range, their
  time span (s), the largest angle between their viewing rays (deg), the anchor's height above the
  odometry's floor plane (m), the lowest corner of the class's cuboid above it (m; both 0 without a
  floor plane), and the class-vote share and lead at the anchor (0..1). A slot without a label is a candidate.
- ``pose`` (6,) float32: the robot's estimated pose in ``map`` (x, y, z, cos yaw, sin yaw) and the
  episode's elapsed fraction.

Action: ``MultiDiscrete([4] * max_objects)`` (0 ignore, 1 replace, 2 fuse, 3 withdraw; see
``slots``), with one more entry when ``stage_choice=True``: the index into ``stage_options`` of the
DOPE stage count to use on the next frame (it costs ``stage_cost_per_s`` per second of DOPE time).

Reward: the decrease of the map's cost (per class a one-to-one assignment of the published labels
to the true objects, as ``testbed.scoring.score_map``: each matched label's error, misplaced and
phantom labels, missing objects; ``slots.RewardConfig``). ``info`` holds, every step, each slot's
current detection's and label's distance to the truth (``detection_error_m``, ``label_error_m``:
for oracles and analysis, not for a learning policy), and at the end ``map_score``: the summary of
``testbed.scoring.score_map`` on the published labels (labels in the map, correct, misplaced and
phantom labels, map precision and recall, mean error, candidates: slots in use without a label),
the per-object rows (``labels``) and the per-label rows (``map_labels``).

Episodes: the product of ``scenario`` (one or a list) and ``seeds``. ``reset(seed=...)`` seeds
``self.np_random``, which picks the episode; ``reset(options={"episode": i})`` or
``options={"scenario": name, "seed": s}`` picks one. An episode's perception is built on first
use (minutes: simulation, odometry and DOPE) and cached on disk; see ``perception_cache``.
"""
from __future__ import annotations

import math
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from stack.evidence import EvidenceConfig
from stack.transforms import inv, transform_points
from testbed.envs import perception_cache as pc
from testbed.envs.render import TopDownMap, camera_panel, side_by_side
from testbed.envs.slots import (N_ACTIONS, POSITION_LIMIT_M, VALUE_LIMIT, RewardConfig, SlotMap, floor_half_extents,
                                slot_features, with_lists)
from testbed.scoring import score_map


def catalog_classes() -> list[str]:
    from sim.objects import load_catalog

    return list(load_catalog())


def resolve_input(input_mode: str, scenario) -> str:
    """``auto``: depth input in complete darkness (RGB is black there), else RGB."""
    if input_mode != "auto":
        return input_mode
    from sim.scenario import Scenario, load_scenario

    sc = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    return "depth" if sc.light <= 0.0 else "rgb"


def observation_space(n_slots: int, n_classes: int) -> spaces.Dict:
    return spaces.Dict({
        "slots": spaces.Box(-VALUE_LIMIT, VALUE_LIMIT, (n_slots, len(slot_features(n_classes))), np.float32),
        "pose": spaces.Box(np.array([-POSITION_LIMIT_M] * 3 + [-1.0, -1.0, 0.0], dtype=np.float32),
                           np.array([POSITION_LIMIT_M] * 3 + [1.0, 1.0, 1.0], dtype=np.float32), dtype=np.float32),
    })


def pose_features(T_map_base: np.ndarray, fraction: float) -> np.ndarray:
    yaw = math.atan2(T_map_base[1, 0], T_map_base[0, 0])
    x, y, z = np.clip(T_map_base[:3, 3], -POSITION_LIMIT_M, POSITION_LIMIT_M)
    return np.array([x, y, z, math.cos(yaw), math.sin(yaw), min(max(fraction, 0.0), 1.0)], dtype=np.float32)


def truth_in_map(objects: list, T_world_map: np.ndarray, classes: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(class index (K,), centroid in map (K, 3)) of the true objects; classes not in ``classes`` get -2."""
    index = {c: i for i, c in enumerate(classes)}
    cls = np.array([index.get(o["cls"] if isinstance(o, dict) else o.cls, -2) for o in objects], dtype=np.int64)
    xyz_world = np.array([np.asarray(o["T_world_obj"] if isinstance(o, dict) else o.T_world_obj)[:3, 3]
                          for o in objects]).reshape(-1, 3)
    return cls, transform_points(inv(T_world_map), xyz_world) if len(xyz_world) else xyz_world


def final_score(slots: SlotMap, objects: list, T_world_map: np.ndarray, classes: list[str]) -> dict:
    """``testbed.scoring.score_map`` on the slots' labels (slot j is label id j + 1): the same figures
    as ``dopeslam run``; the slots in use without a label are the candidates."""
    labels = [SimpleNamespace(id=j + 1, cls=classes[slots.cls[j]], xyz=slots.label[j].copy(),
                              observations=int(slots.ev_n[j]))
              for j in np.flatnonzero(slots.has)]
    truths = [o if not isinstance(o, dict) else
              SimpleNamespace(name=o["name"], cls=o["cls"], T_world_obj=np.asarray(o["T_world_obj"])) for o in objects]
    candidates = int(np.count_nonzero((slots.cls >= 0) & ~slots.has))
    rows, map_rows, summary = score_map(labels, truths, T_world_map, candidates)
    summary["final_cost"] = float(slots.cost)
    summary["dropped_detections"] = int(slots.dropped)
    summary["duplicate_detections"] = int(slots.duplicates)
    summary["recycled_slots"] = int(slots.recycled)
    summary["withdrawn_labels"] = int(slots.withdrawn)
    return {"summary": summary, "labels": rows, "map_labels": map_rows}


def class_dims(classes: list[str]) -> np.ndarray:
    """(C, 3) cuboid size of each class (the catalog's, as the object store's)."""
    from sim.objects import load_catalog

    cat = load_catalog()
    return np.array([np.asarray(cat[c].dims, dtype=float) if c in cat else np.zeros(3) for c in classes]).reshape(-1, 3)


class Replay:
    """A cached episode arranged for stepping: per stage count, detections sorted by frame."""

    def __init__(self, perception: pc.Perception, classes: list[str], default_stage: int):
        a = perception.arrays
        self.perception = perception
        self.classes = classes
        if list(perception.meta["classes"]) != list(classes):
            raise pc.PerceptionCacheError(f"{perception.spec.stem()}: cached classes {perception.meta['classes']} "
                                          f"differ from the catalog's {classes}; rebuild the cache")
        self.n_frames = int(len(a["frame_stamp"]))
        self.stamps = a["frame_stamp"]
        self.T_map_base = a["frame_T_map_base"]
        self.T_world_map = a["T_world_map"]
        self.objects = perception.meta["objects"]
        self.truth_cls, self.truth_xyz = truth_in_map(self.objects, self.T_world_map, classes)
        self.stage_options = tuple(int(s) for s in perception.spec.stages)
        self.default_stage = default_stage if default_stage in self.stage_options else max(self.stage_options)
        duration = max(float(perception.spec.duration), 1e-9)
        self.pose = np.stack([pose_features(T, (t - self.stamps[0]) / duration)
                              for T, t in zip(self.T_map_base, self.stamps)]) if self.n_frames else np.zeros((0, 6))
        probe = SlotMap(1, len(classes), self.truth_cls, self.truth_xyz)
        self.floor = pc.floor_of(perception)
        dims = class_dims(classes)
        self.by_stage = {}
        for s in self.stage_options:
            sel = np.flatnonzero(a["det_stage"] == s)
            sel = sel[np.argsort(a["det_frame"][sel], kind="stable")]
            d = {k: a[f"det_{k}"][sel] for k in pc.DET_FIELDS}
            d["err"] = probe.errors_to_truth(d["xyz"], d["cls"])
            d["stamp"] = self.stamps[a["det_frame"][sel]] if self.n_frames else np.zeros(len(sel))
            d["half"] = floor_half_extents(d["quat"], d["cls"], dims, self.floor)
            d = with_lists(d)
            starts = np.searchsorted(a["det_frame"][sel], np.arange(self.n_frames + 1))
            self.by_stage[s] = (d, starts)
        secs = perception.meta.get("stage_seconds")
        per_frame = perception.meta.get("detect_seconds_per_frame") or 0.0
        top = max(self.stage_options)
        self.stage_seconds = {s: float(secs[str(s)]) if secs and str(s) in secs else per_frame * s / top
                              for s in self.stage_options}
        self._map: TopDownMap | None = None

    def frame(self, k: int, stage: int) -> tuple[dict, int, int]:
        d, starts = self.by_stage[stage]
        return d, int(starts[k]), int(starts[k + 1])

    def top_down(self) -> TopDownMap:
        if self._map is None:
            a = self.perception.arrays
            self._map = TopDownMap(a["map_xy"], a["traj_T_map_base"][:, :2, 3], self.truth_xyz[:, :2])
        return self._map


class DopeSlamLabellingEnv(gym.Env):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, scenario=None, seeds=(0,), duration: float | None = None, light: float | None = None,
                 input_mode: str = "auto", stages: int = 6, weights=None, stage_choice: bool = False,
                 max_objects: int = 16, gate_m: float = 0.5, reward: RewardConfig | dict | None = None,
                 cache_dir=None, detector_factory=None, detector_id: str | None = None,
                 detector_stages=None, render_mode: str | None = None, thumb=pc.DEFAULT_THUMB,
                 build: bool = True, renderer: str = "auto", evidence: EvidenceConfig | dict | None = None):
        from sim.scenario import DEFAULT_SCENARIO

        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode: expected one of {self.metadata['render_modes']} or None, got {render_mode!r}")
        self.render_mode = render_mode
        self.classes = catalog_classes()
        scenarios = [scenario or DEFAULT_SCENARIO] if scenario is None or isinstance(scenario, str) else list(scenario)
        seeds = [int(seeds)] if isinstance(seeds, (int, np.integer)) else [int(s) for s in seeds]
        if not seeds:
            raise ValueError("seeds: expected at least one episode seed")
        self.episodes = [(sc, s) for sc in scenarios for s in seeds]
        self.duration, self.light, self.weights = duration, light, weights
        self.input_mode, self.stages = input_mode, int(stages)
        self.gate_m = float(gate_m)
        self.reward_cfg = RewardConfig(**reward) if isinstance(reward, dict) else (reward or RewardConfig())
        self.evidence_cfg = EvidenceConfig(**evidence) if isinstance(evidence, dict) else (evidence or EvidenceConfig())
        self.cache_dir, self.thumb, self.build, self.renderer = cache_dir, tuple(thumb), build, renderer
        self._factory, self._detector_id = detector_factory, detector_id
        if detector_factory is not None and not detector_id:
            raise ValueError("detector_id: a custom detector_factory needs an identity for the cache key")
        self._detector_stages = tuple(detector_stages) if detector_stages is not None else None
        self._replays: dict[int, Replay] = {}
        self.stage_choice = bool(stage_choice)
        self.stage_options = self._detector_stage_counts() if self.stage_choice else (self.stages,)
        if self.stage_choice and len(self.stage_options) < 2:
            raise ValueError("stage_choice: the detector gives one stage count per pass; nothing to choose")
        self.N = int(max_objects)
        self.observation_space = observation_space(self.N, len(self.classes))
        nvec = [N_ACTIONS] * self.N + ([len(self.stage_options)] if self.stage_choice else [])
        self.action_space = spaces.MultiDiscrete(np.array(nvec, dtype=np.int64))
        self.slots: SlotMap | None = None
        self.replay: Replay | None = None
        self.k = 0

    # --- episodes and their perception -------------------------------------------------------------
    def _detector_stage_counts(self, input_mode: str | None = None) -> tuple:
        if self._detector_stages is not None:
            return self._detector_stages
        if self._factory is not None or self._detector_id:
            return (self.stages,)  # a custom detector: one stage count unless detector_stages says more
        modes = [input_mode] if input_mode else sorted({resolve_input(self.input_mode, sc) for sc, _ in self.episodes})
        counts = {pc.dope_stage_counts(m, self.stages, self.weights) for m in modes}
        if len(counts) > 1:
            raise ValueError(f"the DOPE weights for inputs {modes} have different stage counts {sorted(counts)}")
        return counts.pop()

    def spec_for(self, i: int) -> pc.PerceptionSpec:
        sc, seed = self.episodes[i]
        input_mode = resolve_input(self.input_mode, sc)
        kept = self._detector_stage_counts(input_mode)
        if self._detector_id:
            det_id = self._detector_id
        else:
            det_id = pc.dope_detector_id(input_mode, self.weights)
        return pc.make_spec(sc, seed, self.duration, self.light, input_mode, kept, det_id, self.thumb, self.renderer)

    def replay_for(self, i: int) -> Replay:
        if i not in self._replays:
            spec = self.spec_for(i)
            factory = self._factory
            if factory is None and self.build:
                def factory(ep, spec=spec):
                    return pc.dope_factory(spec.input, self.stages, self.weights)[0](ep)

                factory.images_only = True  # DOPE reads the images alone
            perception = pc.load_or_build(spec, factory if self.build else None, self.cache_dir,
                                          scenario=self.episodes[i][0])
            self._replays[i] = Replay(perception, self.classes, self.stages)
        return self._replays[i]

    def episode_index(self, options: dict | None) -> int:
        options = options or {}
        if "episode" in options:
            i = int(options["episode"])
            if not 0 <= i < len(self.episodes):
                raise ValueError(f"options['episode']: expected 0..{len(self.episodes) - 1}, got {i}")
            return i
        if "seed" in options or "scenario" in options:
            want_sc = options.get("scenario")
            for i, (sc, s) in enumerate(self.episodes):
                if ("seed" not in options or s == int(options["seed"])) and (want_sc is None or sc == want_sc):
                    return i
            raise ValueError(f"options: no episode {options}; this env has {self.episodes}")
        return int(self.np_random.integers(len(self.episodes)))

    # --- gymnasium API ------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.episode = self.episode_index(options)
        self.replay = r = self.replay_for(self.episode)
        self.slots = SlotMap(self.N, len(self.classes), r.truth_cls, r.truth_xyz, self.gate_m, self.reward_cfg,
                             floor=r.floor, evidence=self.evidence_cfg)
        self.k = 0
        self.stage = r.default_stage
        self.steps = 0
        self._observe()
        return self._obs(), self._info()

    def step(self, action):
        if self.slots is None:
            raise RuntimeError("step() before reset()")
        if self.k >= self.replay.n_frames:
            raise RuntimeError("step() after the episode ended; call reset()")
        action = np.asarray(action)
        reward = self.slots.act(action[:self.N])
        if self.stage_choice:
            self.stage = self.stage_options[int(action[self.N])]
            reward -= self.reward_cfg.stage_cost_per_s * self.replay.stage_seconds.get(self.stage, 0.0)
        self.k += 1
        self.steps += 1
        terminated = self.k >= self.replay.n_frames
        self._observe()
        info = self._info()
        if terminated:
            r = self.replay
            info["map_score"] = final_score(self.slots, r.objects, r.T_world_map, self.classes)
            info["episode"] = {"scenario": r.perception.spec.scenario, "seed": r.perception.spec.seed,
                               "input": r.perception.spec.input, "frames": r.n_frames}
        return self._obs(), float(reward), terminated, False, info

    def _observe(self) -> None:
        r = self.replay
        if self.k < r.n_frames:
            d, lo, hi = r.frame(self.k, self.stage)
            self.slots.observe(d, lo, hi, self.stage)
        else:
            self.slots.observe(r.by_stage[self.stage][0], 0, 0, self.stage)

    def _obs(self) -> dict:
        r = self.replay
        pose = r.pose[min(self.k, r.n_frames - 1)].copy() if r.n_frames else np.zeros(6, np.float32)
        if self.k >= r.n_frames:
            pose[5] = 1.0
        return {"slots": self.slots.slots_obs(), "pose": pose}

    def _info(self) -> dict:
        det_err, lab_err = self.slots.oracle_info()
        return {"frame": self.k, "stage": self.stage, "detection_error_m": det_err, "label_error_m": lab_err,
                "map_cost": self.slots.cost}

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self.replay is None:
            raise RuntimeError("render() before reset()")
        r = self.replay
        k = min(self.k, r.n_frames - 1)
        cam = r.perception.meta["camera"]
        d, lo, hi = r.frame(k, self.stage) if r.n_frames else ({}, 0, 0)
        kps = [(d["kp"][i], d["cls"][i], d["fpr"][i]) for i in range(lo, hi)]
        caption = f"{r.perception.spec.scenario} seed {r.perception.spec.seed}  t={r.stamps[k] - r.stamps[0]:.1f}s  " \
                  f"{self.stage} stages"
        left = camera_panel(r.perception.thumbnail(k), (cam["width"], cam["height"]), kps, caption=caption)
        s = self.slots
        lab = np.flatnonzero(s.has)
        errs = s.errors_to_truth(s.label[lab], s.cls[lab]) if len(lab) else []
        labels = [(s.label[j], s.cls[j], float(e)) for j, e in zip(lab, errs)]
        dets = [(d["xyz"][i], d["cls"][i]) for i in range(lo, hi)]
        right = r.top_down().draw(r.T_map_base[:k + 1, :2, 3], r.T_map_base[k], r.truth_cls, labels, dets)
        return side_by_side(left, right)

    def close(self):
        self._replays.clear()
        super().close()
