"""Build the place-recognition vocabulary tree from key frames of training episodes.

The key frames are one camera image in ten (seed 001), i.e. the episode's camera run at a tenth of its
rate, which renders exactly the images that would have been kept. By default the training episodes are
the bundled scenarios whose names do not contain ``loop`` (the looping scenarios are where the tree is
used, so it is not trained on them), one per layout, lit at level 1 whatever their own light.

The result is cached by its inputs (scenarios, branching, depth, seed) under
``$DOPESLAM_CACHE/vocabulary`` (default ``~/.cache/dopeslam/vocabulary``).
"""
from __future__ import annotations

import hashlib
import logging
import os
import time
from pathlib import Path

import numpy as np

from stack.loops.place_recognition import FeatureConfig, VocabularyTree, describe

log = logging.getLogger(__name__)


def cache_dir() -> Path:
    from testbed.settings import cache_dir as cache

    return cache("vocabulary")


def training_scenarios() -> list[str]:
    """Bundled scenarios without ``loop`` in their names, one per layout (a dark variant of a lit
    scenario, rendered lit, would give the same images again)."""
    from sim.scenario import bundled_scenarios, load_scenario

    names, layouts = [], set()
    for name in bundled_scenarios():
        if "loop" in name:
            continue
        sc = load_scenario(name)
        layout = sc.model_dump_json(include={"room", "furniture", "objects", "robot", "route"})
        if layout not in layouts:
            layouts.add(layout)
            names.append(name)
    return names


def key_frame_images(scenario, keyframe_every: int = 10, duration: float | None = None, seed: int | None = None,
                     light: float | None = None, lidar: bool = False
                     ) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """The key frames of an episode: (RGB images, stamps (N,), T_world_camera (N, 4, 4)).

    Renders only the kept images (camera rate divided by ``keyframe_every``)."""
    from sim.episode import Episode
    from sim.scenario import load_scenario
    from stack.messages import CameraFrame

    sc = load_scenario(scenario) if not hasattr(scenario, "sensors") else scenario.model_copy(deep=True)
    sc.sensors.camera_rate = sc.sensors.camera_rate / keyframe_every
    images, stamps, poses = [], [], []
    t0 = last = time.perf_counter()
    with Episode(sc, seed=seed, duration=duration, light=light, lidar=lidar) as ep:
        for msg in ep.frames():
            if isinstance(msg, CameraFrame):
                images.append(msg.rgb)
                stamps.append(msg.stamp)
                poses.append(msg.T_world_camera)
            if time.perf_counter() - last > 15:
                last = time.perf_counter()
                log.info("%s: key frames up to t = %.0f of %.0f s (%.0f s wall)", sc.name, msg.stamp, ep.duration,
                         last - t0)
    return images, np.array(stamps), np.array(poses).reshape(-1, 4, 4)


def build_vocabulary(scenarios: list[str] | None = None, branching: int = 10, depth: int = 3, seed: int = 0,
                     out: str | os.PathLike | None = None, features: FeatureConfig | None = None) -> Path:
    """Train (or reuse from the cache) the vocabulary tree; returns the .npz path."""
    scenarios = list(scenarios or training_scenarios())
    features = features or FeatureConfig()
    inputs = f"{sorted(scenarios)}/{branching}/{depth}/{seed}/{features.model_dump_json()}"
    key = hashlib.sha1(inputs.encode()).hexdigest()[:12]
    path = Path(out) if out is not None else cache_dir() / f"vocabulary_b{branching}_d{depth}_{key}.npz"
    if path.exists():
        try:
            VocabularyTree.load(path)
            log.info("vocabulary: using %s", path)
            return path
        except ValueError as exc:
            log.warning("vocabulary: %s; rebuilding", exc)
    descs = []
    for name in scenarios:
        images, _, _ = key_frame_images(name, light=1.0)
        for img in images:
            f = describe(img, features)
            if f is not None:
                descs.append(f.descriptors)
        log.info("vocabulary: %s gave %d key frames, %d described", name, len(images), len(descs))
    tree = VocabularyTree.train(descs, branching=branching, depth=depth, seed=seed)
    tree.feature_config = features
    tree.save(path)
    log.info("vocabulary: %d words from %d images -> %s", tree.n_words, len(descs), path)
    return path


def default_vocabulary() -> VocabularyTree:
    return VocabularyTree.load(build_vocabulary())
