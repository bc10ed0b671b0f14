"""A synthetic scene for the HOG detector, shared by tests/unit/test_topomap_hog.py and
tests/e2e/test_topomap_hog_e2e.py."""
import numpy as np


def scene(rng, colour, H=120, W=160, with_object=True):
    img = rng.integers(60, 120, (H, W, 3)).astype(np.uint8)
    for _ in range(3):  # distractor blobs
        x, y = rng.integers(0, W - 20), rng.integers(0, H - 20)
        img[y:y + rng.integers(5, 20), x:x + rng.integers(5, 20)] = rng.integers(0, 255, 3)
    boxes = []
    if with_object:
        h = int(rng.integers(30, 50))
        w = h // 2
        x, y = int(rng.integers(0, W - w)), int(rng.integers(0, H - h))
        img[y:y + h, x:x + w] = colour
        img[y + h // 3:y + h // 3 + 3, x + 3:x + w - 3] = 20  # a dark stripe: some shape
        img[y + 2 * h // 3:y + 2 * h // 3 + 3, x + 3:x + w - 3] = 20
        boxes.append([x, y, x + w, y + h])
    return img, np.array(boxes, float).reshape(-1, 4)
