"""The topological-map paper's detector trained with hard negatives learns a shape, and its colour step
rejects the wrong colour (HOG, the SVM, saving: ``tests/unit/test_topomap_hog.py``)."""
import numpy as np
import pytest

from helpers.topomap_hog import scene as _scene
from stack.topomap.hog_detector import TrainingImage, fit_colour_model, iou, train_detector


@pytest.mark.slow
def test_detector_learns_a_shape_and_the_colour_step_rejects_the_wrong_colour():
    rng = np.random.default_rng(1)
    orange = (245, 140, 20)
    train = []
    for _ in range(25):
        img, b = _scene(rng, orange)
        train.append(TrainingImage(img, b, ["Box"] * len(b), np.ones(len(b))))
    det = train_detector(train, ["Box"], n_components=1, cells_area=24, mining_rounds=1, mining_images=8,
                         negatives_per_image=6, C=0.1)
    det.colour = fit_colour_model(train, ["Box"], quantile=1.0)
    img, b = _scene(np.random.default_rng(7), orange)
    found = det.detect(img, threshold=-0.5)
    assert found and found[0].cls == "Box"
    assert iou(found[0].box[None], b)[0, 0] > 0.4
    # the same shape painted blue: the shape filter still fires, the colour step removes it
    blue_img, bb = _scene(np.random.default_rng(7), (30, 60, 220))
    shape_only = [d for d in det.detect(blue_img, threshold=-0.5, colour_step=False) if iou(d.box[None], bb)[0, 0] > 0.4]
    assert shape_only and shape_only[0].colour_pass is False
    with_colour = [d for d in det.detect(blue_img, threshold=-0.5) if iou(d.box[None], bb)[0, 0] > 0.4]
    assert not with_colour
