"""The topological-map paper's detector: 31-d HOG, the linear SVM, non-maximum suppression, saving and
loading (training with hard negatives and the colour step: ``tests/e2e/test_topomap_hog_e2e.py``)."""
import numpy as np
import pytest

from helpers.topomap_hog import scene as _scene
from stack.topomap.hog_detector import (HogDetector, TrainingImage, fhog, fit_colour_model, iou, nms, train_detector,
                                train_linear_svm)


def test_fhog_shape_and_contrast_sensitivity():
    img = np.zeros((64, 96, 3), np.uint8)
    img[:, 48:] = 200  # a vertical edge, dark to bright
    F = fhog(img, 4)
    assert F.shape == (16, 24, 31)
    assert np.all(F >= 0) and F.max() <= 0.2 * 4 * 0.5 + 1e-6 + 0.5
    edge = F[8, 11:13]
    assert edge[..., :27].sum() > 0 and F[8, 2, :27].sum() == 0  # gradient only at the edge
    Fi = fhog(255 - img, 4)  # inverted contrast: same insensitive part, different sensitive bins
    np.testing.assert_allclose(Fi[..., 18:27], F[..., 18:27], atol=1e-5)
    assert not np.allclose(Fi[..., :18], F[..., :18])


def test_iou_and_nms():
    a = np.array([[0, 0, 10, 10], [5, 0, 15, 10], [50, 50, 60, 60]], float)
    assert iou(a[:1], a[1:2])[0, 0] == pytest.approx(50 / 150)
    keep = nms(a, np.array([0.9, 0.8, 0.1]), threshold=0.3)
    assert list(keep) == [0, 2]


def test_linear_svm_separates_two_clouds():
    rng = np.random.default_rng(0)
    X = np.vstack([rng.normal(1.5, 1, (100, 5)), rng.normal(-1.5, 1, (100, 5))])
    y = np.r_[np.ones(100), -np.ones(100)]
    w, b = train_linear_svm(X, y, C=1.0)
    assert np.mean(np.sign(X @ w + b) == y) > 0.95


def test_save_and_load(tmp_path):
    rng = np.random.default_rng(2)
    train = []
    for _ in range(12):
        img, b = _scene(rng, (30, 150, 30))
        train.append(TrainingImage(img, b, ["G"] * len(b), np.ones(len(b))))
    det = train_detector(train, ["G"], n_components=2, cells_area=24, mining_rounds=0)
    det.colour = fit_colour_model(train, ["G"])
    det.save(tmp_path / "hog.npz", tmp_path / "hog.json")
    det2 = HogDetector.load(tmp_path / "hog.npz", tmp_path / "hog.json")
    assert [c.shape for c in det2.components] == [c.shape for c in det.components]
    img, _ = _scene(rng, (30, 150, 30))
    a = [(d.cls, round(d.score, 4)) for d in det.detect(img, threshold=-1)]
    assert a == [(d.cls, round(d.score, 4)) for d in det2.detect(img, threshold=-1)]
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="bad.npz"):
        HogDetector.load(tmp_path / "bad.npz", None)
