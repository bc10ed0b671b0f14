"""A tiny training run on a hand-made shard lowers the loss, checkpoints, and resumes."""
import json

import cv2
import numpy as np
import pytest
import torch

from stack.dope.train import ShardData, TrainConfig, dope_loss, sample_batch, train
from stack.errors import UsageError


def _write_shard(folder, n=6, seed=0):
    rng = np.random.default_rng(seed)
    rgbs, depths, segs, images = [], [], [], []
    for _ in range(n):
        img = np.full((96, 128, 3), rng.integers(0, 255, 3), np.uint8)
        cx, cy = rng.uniform(40, 88), rng.uniform(35, 60)
        front = np.array([(cx + 12, cy - 18), (cx - 12, cy - 18), (cx - 12, cy + 18), (cx + 12, cy + 18)])
        rear = front + (6, -5)
        cv2.fillConvexPoly(img, rear.astype(np.int32), (40, 200, 40))
        cv2.fillConvexPoly(img, front.astype(np.int32), (200, 40, 40))
        kp = np.vstack([front, rear, [(cx + 3, cy - 2.5)]])
        rgbs.append(img)
        depths.append(np.full((96, 128), 800, np.uint16))
        segs.append(np.full((96, 128), -1, np.int16))
        images.append({"light": 1.0, "objects": [{"class": "E", "class_index": 0, "keypoints_px": kp.tolist(),
                                                   "location": [0.0, 0.0, 0.8], "quaternion_xyzw": [0, 0, 0, 1],
                                                   "pixels_visible": 900, "hull_area_px": 1000.0,
                                                   "in_frame": [True] * 9}]})
    for shard in (0, 1):
        np.savez_compressed(folder / f"shard_{shard:05d}.npz", rgb=np.stack(rgbs), depth_mm=np.stack(depths),
                            seg=np.stack(segs))
        (folder / f"shard_{shard:05d}.json").write_text(json.dumps({"K": np.eye(3).tolist(), "classes": ["E"],
                                                                    "images": images}))


def test_batches_have_targets_for_the_annotated_class(tmp_path):
    _write_shard(tmp_path)
    data = ShardData(tmp_path, ("Yogurt", "E"))
    assert data.refresh() == 12
    cfg = TrainConfig(str(tmp_path), str(tmp_path / "run"), batch=4, crop=(64, 64), classes=("Yogurt", "E"))
    x, b, a = sample_batch(data, cfg, np.random.default_rng(0))
    assert x.shape == (4, 3, 64, 64) and b.shape == (4, 18, 8, 8) and a.shape == (4, 32, 8, 8)
    assert float(b[:, :9].max()) == 0.0 and float(b[:, 9:].max()) > 0.5


def test_loss_weights_peaks():
    b = torch.zeros(1, 9, 8, 8)
    b[0, 0, 4, 4] = 1.0
    a = torch.zeros(1, 16, 8, 8)
    zeros = [(torch.zeros_like(b), torch.zeros_like(a))]
    # predicting all zeros misses the peak at 1 + peak_weight times the cost of one background pixel
    assert float(dope_loss(zeros, b, a, peak_weight=10.0)) == pytest.approx(11.0 / b.numel())


def test_tiny_training_run_lowers_the_loss_and_resumes(tmp_path):
    torch.set_num_threads(1)
    _write_shard(tmp_path)
    out = tmp_path / "run"
    cfg = TrainConfig(str(tmp_path), str(out), width=0.125, stages=2, batch=4, crop=(64, 64), lr=2e-3,
                      lr_decay_steps=(), max_steps=60, val_shards=1, val_images=2, classes=("E",), seed=0)
    summary = train(cfg)
    assert summary["step"] == 60
    ck = torch.load(out / "checkpoint.pt", weights_only=True)
    losses = [l for _, l in ck["history"]]
    assert np.mean(losses[-2:]) < 0.7 * losses[0]
    assert (out / "loss.png").exists() and (out / "weights_fp16.pt").exists()
    evals = json.loads((out / "evals.json").read_text())
    assert set(evals["evals"][-1]["median_px"]) == {"FTR", "FTL", "FBL", "FBR", "RTR", "RTL", "RBL", "RBR", "C"}
    cfg.max_steps = 70
    assert train(cfg)["step"] == 70  # resumed from the checkpoint, not from scratch


def test_class_weights_pick_the_weighted_class_more_often():
    from stack.dope.train import choose_window, pick_focus

    objs = [(0, np.zeros((9, 2)), np.array([0.0, 0.0, 0.6])), (1, np.zeros((9, 2)), np.array([0.0, 0.0, 1.5]))]
    rng = np.random.default_rng(0)
    plain = TrainConfig("d", "o", classes=("Yogurt", "E"))
    weighted = TrainConfig("d", "o", classes=("Yogurt", "E"), class_weights={"Yogurt": 4.0})
    n_plain = sum(pick_focus(objs, plain, rng) == 0 for _ in range(4000))
    n_weighted = sum(pick_focus(objs, weighted, rng) == 0 for _ in range(4000))
    assert 1800 < n_plain < 2200  # uniform: half
    assert 3000 < n_weighted < 3400  # 4 : 1 -> 80 %
    # the depth window holds the focal object whenever it is not the 10 % random window
    hits = [choose_window(objs, rng, focus=objs[1]) for _ in range(500)]
    inside = sum(lo <= 1.5 <= hi for lo, hi in hits)
    assert inside >= 400


def test_class_weight_flag_is_parsed_and_checked():
    from testbed.commands.dope import parse_class_weights

    assert parse_class_weights(["Yogurt=3", "E=0.5"]) == {"Yogurt": 3.0, "E": 0.5}
    for bad in ("Yogurt", "Banana=2", "Yogurt=-1", "Yogurt=x"):
        with pytest.raises(UsageError, match="--class-weight"):
            parse_class_weights([bad])
