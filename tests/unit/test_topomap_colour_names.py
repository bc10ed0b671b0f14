"""Colour names (eleven basic colours) and the colour-verification step of the topological-map paper's detector."""
import json

import numpy as np
import pytest

from stack.dope.colour_names import NAMES, ColourModel, box_histogram, colour_names, cosine_distance, name_probabilities


def patch(rgb, size=(20, 30), noise=0.0, seed=0):
    img = np.empty(size + (3,), dtype=float)
    img[:] = rgb
    if noise:
        img += np.random.default_rng(seed).normal(0, noise, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("rgb,name", [((250, 140, 15), "orange"), ((20, 40, 220), "blue"), ((30, 150, 30), "green"),
                                      ((250, 250, 250), "white"), ((10, 10, 10), "black"), ((128, 128, 128), "grey"),
                                      ((200, 20, 25), "red"), ((250, 225, 20), "yellow"), ((120, 50, 150), "purple"),
                                      ((240, 150, 200), "pink"), ((120, 70, 30), "brown")])
def test_basic_colours_are_named(rgb, name):
    p = colour_names(np.array(rgb, dtype=np.uint8))
    assert NAMES[int(np.argmax(p))] == name
    assert p.sum() == pytest.approx(1.0, abs=1e-5)


def test_lookup_table_agrees_with_the_direct_computation():
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (500, 3)).astype(np.uint8)
    centre = (rgb // 8) * 8 + 3.5  # the table's cell centres
    np.testing.assert_allclose(colour_names(rgb), name_probabilities(centre), atol=1e-5)


def test_box_histogram_of_a_two_colour_box():
    img = np.zeros((40, 40, 3), np.uint8)
    img[:, :20] = (250, 140, 15)  # orange
    img[:, 20:] = (20, 40, 220)  # blue
    h = box_histogram(img, (0, 0, 40, 40))
    assert h.sum() == pytest.approx(1.0, abs=1e-4)
    assert h[NAMES.index("orange")] == pytest.approx(0.5, abs=0.05)
    assert h[NAMES.index("blue")] == pytest.approx(0.5, abs=0.05)
    h_left = box_histogram(img, (-5, 0, 20, 40))  # clipped to the image
    assert h_left[NAMES.index("orange")] > 0.9


def test_cosine_verification_keeps_the_right_colours_and_drops_others(tmp_path):
    hists = {"Juice": [box_histogram(patch((245, 140, 20), noise=6, seed=s), (0, 0, 30, 20)) for s in range(20)]
             + [box_histogram(patch((250, 210, 60), noise=6, seed=s), (0, 0, 30, 20)) * 0.0
                + 0.7 * box_histogram(patch((245, 140, 20), noise=6, seed=s), (0, 0, 30, 20))
                + 0.3 * box_histogram(patch((250, 210, 60), noise=6, seed=s), (0, 0, 30, 20)) for s in range(20)]}
    cm = ColourModel.fit(hists, quantile=0.95)
    orange = box_histogram(patch((240, 135, 25), noise=6, seed=99), (0, 0, 30, 20))
    blue = box_histogram(patch((40, 60, 200), noise=6, seed=99), (0, 0, 30, 20))
    grey = box_histogram(patch((130, 130, 130), noise=6, seed=99), (0, 0, 30, 20))
    assert cm.verify("Juice", orange)
    assert not cm.verify("Juice", blue)
    assert not cm.verify("Juice", grey)
    assert cosine_distance(orange, cm.models["Juice"]) < cosine_distance(blue, cm.models["Juice"])
    assert cm.verify("NoModel", blue)  # classes without a model are not filtered
    path = tmp_path / "colour.json"
    cm.save(path)
    cm2 = ColourModel.load(path)
    assert cm2.thresholds == cm.thresholds
    np.testing.assert_allclose(cm2.models["Juice"], cm.models["Juice"])
    bad = json.loads(path.read_text())
    bad["models"]["Juice"] = [0.1, 0.2]
    path.write_text(json.dumps(bad))
    with pytest.raises(ValueError, match="models.Juice"):
        ColourModel.load(path)
