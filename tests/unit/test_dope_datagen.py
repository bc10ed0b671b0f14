"""Synthetic DOPE data: shards are deterministic in the seed and their annotations match the pixels."""
import json

import numpy as np

from sim.datagen import DatagenConfig, generate_shard


def test_shard_annotations_match_segmentation_and_are_deterministic(tmp_path):
    cfg = DatagenConfig(out_dir=tmp_path / "a", n_images=3, shard_size=3, seed=5)
    (tmp_path / "a").mkdir()
    generate_shard(cfg, 0)
    arr = np.load(tmp_path / "a" / "shard_00000.npz")
    meta = json.loads((tmp_path / "a" / "shard_00000.json").read_text())
    assert arr["rgb"].shape == (3, 240, 320, 3) and arr["depth_mm"].dtype == np.uint16
    assert len(meta["images"]) == 3 and np.array(meta["K"]).shape == (3, 3)
    n_checked = 0
    for i, image in enumerate(meta["images"]):
        for k, o in enumerate(image["objects"]):
            kp = np.array(o["keypoints_px"])
            assert kp.shape == (9, 2) and len(o["quaternion_xyzw"]) == 4
            # the centroid projects from the location through K
            K = np.array(meta["K"])
            loc = np.array(o["location"])
            assert np.allclose(kp[8], (K @ loc)[:2] / loc[2], atol=0.01)
            mask = arr["seg"][i] == k
            if mask.sum() > 200 and o["pixels_visible"] > 0.8 * o["hull_area_px"]:
                ys, xs = np.nonzero(mask)
                # a well-visible object's pixels lie within its projected cuboid's bounding box
                assert xs.min() >= kp[:8, 0].min() - 2 and xs.max() <= kp[:8, 0].max() + 2
                assert ys.min() >= kp[:8, 1].min() - 2 and ys.max() <= kp[:8, 1].max() + 2
                d = arr["depth_mm"][i][mask]
                d = d[d > 0] / 1000.0
                assert abs(np.median(d) - loc[2]) < 0.15  # depth of the object's pixels is about its range
                n_checked += 1
    assert n_checked >= 1
    cfg_b = DatagenConfig(out_dir=tmp_path / "b", n_images=3, shard_size=3, seed=5)
    (tmp_path / "b").mkdir()
    generate_shard(cfg_b, 0)
    assert json.loads((tmp_path / "b" / "shard_00000.json").read_text())["images"] == meta["images"]


def test_slim_stands_carry_objects_as_the_scenarios_do(tmp_path):
    """With slim_stand_prob=1 every target above the floor stands on its class's slim stand: centred
    under it, its top at the object's bottom."""
    import pybullet as p

    from sim.camera import default_camera_info
    from sim.datagen import _World

    cfg = DatagenConfig(out_dir=tmp_path, seed=3, slim_stand_prob=1.0)
    rng = np.random.default_rng(0)
    world = _World(rng, tuple(cfg.classes), tmp_path)
    try:
        checked = 0
        for _ in range(10):
            _, placed = world.stage(cfg, default_camera_info())
            for ci, body, T in placed[:1]:  # the first target always has a free stand
                spec = world.specs[ci]
                bottom = T[2, 3] - spec.height / 2
                if bottom < 0.02:
                    continue
                pos, _ = p.getBasePositionAndOrientation(world.slim_stands[ci], physicsClientId=world.client)
                assert np.allclose(pos[:2], T[:2, 3], atol=1e-6)
                assert abs(pos[2] + 0.6 - bottom) < 1e-6
                checked += 1
        assert checked >= 3
    finally:
        p.disconnect(world.client)
