"""Eleven basic colour names (Berlin and Kay) and the colour-verification step of the topological-map paper's
detector (section 3.3): a box's colour-name histogram is compared, by cosine distance, with the
class's colour model, and detections that do not match are dropped.

The RGB -> colour-name mapping is our own construction, a fixed lookup table (the seed uses the
learned mapping of van de Weijer et al., which cannot be downloaded here):

* each of the 11 names has a few hand-set sRGB prototypes (below), converted to CIELab (D65);
* a colour's probability for a name is ``exp(-d^2 / (2 sigma^2))`` of its Lab distance ``d`` to the
  nearest prototype of that name, normalised over the names (``sigma`` = 12 Lab units: a soft
  assignment so that shading between two names splits rather than flips);
* the table holds these 11 probabilities for every RGB colour quantised to 32 levels per channel
  (8 x 8 x 8 = 512 rgb values per cell), built once at import.

A box's histogram is the mean of its pixels' 11 probabilities (sums to 1); a class's model is the
normalised mean histogram of its training boxes; the class's threshold on cosine distance is a
quantile of its training boxes' distances (so most true boxes pass).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from stack.io import write_json

NAMES = ("black", "blue", "brown", "grey", "green", "orange", "pink", "purple", "red", "white", "yellow")

# hand-set sRGB prototypes per name (several shades, including the shaded sides of coloured surfaces)
PROTOTYPES: dict[str, tuple] = {
    "black": ((0, 0, 0), (28, 28, 30), (45, 40, 40)),
    "blue": ((0, 0, 255), (30, 60, 200), (70, 120, 210), (20, 40, 120), (0, 150, 220), (40, 170, 200), (30, 110, 150)),
    "brown": ((139, 69, 19), (110, 80, 50), (90, 60, 40), (150, 105, 60), (70, 45, 30)),
    "grey": ((128, 128, 128), (90, 90, 92), (165, 165, 165), (110, 115, 120)),
    "green": ((0, 160, 0), (40, 130, 40), (100, 200, 100), (0, 90, 20), (150, 210, 60)),
    "orange": ((255, 140, 0), (245, 140, 20), (230, 110, 30), (255, 170, 60), (200, 110, 20)),
    "pink": ((255, 150, 200), (230, 100, 160), (250, 190, 205), (200, 30, 90)),
    "purple": ((128, 0, 128), (120, 60, 150), (90, 40, 120), (150, 90, 190)),
    "red": ((220, 20, 20), (180, 0, 0), (200, 40, 30), (190, 30, 40), (130, 10, 15)),
    "white": ((255, 255, 255), (235, 235, 240), (215, 215, 210)),
    "yellow": ((255, 230, 0), (250, 220, 30), (240, 240, 100), (210, 190, 20), (250, 210, 60)),
}
SIGMA_LAB = 12.0
LEVELS = 32  # quantisation of each RGB channel in the table


def srgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """sRGB (..., 3) in 0-255 -> CIELab (D65)."""
    c = np.asarray(rgb, dtype=np.float64) / 255.0
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    M = np.array([[0.4124564, 0.3575761, 0.1804375], [0.2126729, 0.7151522, 0.0721750],
                  [0.0193339, 0.1191920, 0.9503041]])
    xyz = lin @ M.T / np.array([0.95047, 1.0, 1.08883])
    f = np.where(xyz > (6 / 29) ** 3, np.cbrt(xyz), xyz / (3 * (6 / 29) ** 2) + 4 / 29)
    L = 116 * f[..., 1] - 16
    a = 500 * (f[..., 0] - f[..., 1])
    b = 200 * (f[..., 1] - f[..., 2])
    return np.stack([L, a, b], axis=-1)


def name_probabilities(rgb: np.ndarray, sigma: float = SIGMA_LAB) -> np.ndarray:
    """(..., 3) sRGB -> (..., 11) colour-name probabilities (computed, not looked up)."""
    lab = srgb_to_lab(rgb)
    d2 = np.stack([np.min(np.sum((lab[..., None, :] - srgb_to_lab(np.array(PROTOTYPES[n]))) ** 2, axis=-1), axis=-1)
                   for n in NAMES], axis=-1)
    logits = -d2 / (2 * sigma ** 2)
    logits -= logits.max(axis=-1, keepdims=True)
    p = np.exp(logits)
    return p / p.sum(axis=-1, keepdims=True)


@lru_cache(maxsize=1)
def table() -> np.ndarray:
    """The lookup table (LEVELS^3, 11), built on first use."""
    step = 256 // LEVELS
    centres = np.arange(LEVELS) * step + (step - 1) / 2.0
    r, g, b = np.meshgrid(centres, centres, centres, indexing="ij")
    rgb = np.stack([r, g, b], axis=-1).reshape(-1, 3)
    return name_probabilities(rgb).astype(np.float32)  # (LEVELS^3, 11)


def colour_names(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) uint8 sRGB -> (..., 11) probabilities by table lookup."""
    q = np.asarray(rgb, dtype=np.uint8) // (256 // LEVELS)
    idx = (q[..., 0].astype(np.int32) * LEVELS + q[..., 1]) * LEVELS + q[..., 2]
    return table()[idx]


def name_image(rgb: np.ndarray) -> np.ndarray:
    """The most probable colour name's index per pixel (for pictures)."""
    return np.argmax(colour_names(rgb), axis=-1)


def box_histogram(rgb: np.ndarray, box) -> np.ndarray:
    """Colour-name histogram (11,) of an image's box (x0, y0, x1, y1 pixels; clipped to the image)."""
    H, W = rgb.shape[:2]
    x0, y0, x1, y1 = (int(round(v)) for v in box)
    x0, y0 = max(0, x0), max(0, y0)
    x1, y1 = min(W, x1), min(H, y1)
    if x1 <= x0 or y1 <= y0:
        return np.full(len(NAMES), 1.0 / len(NAMES))
    patch = rgb[y0:y1, x0:x1]
    return colour_names(patch).reshape(-1, len(NAMES)).mean(axis=0).astype(np.float64)


def cosine_distance(h: np.ndarray, model: np.ndarray) -> float:
    h = np.asarray(h, dtype=float)
    m = np.asarray(model, dtype=float)
    den = np.linalg.norm(h) * np.linalg.norm(m)
    return 1.0 if den <= 0 else float(1.0 - h @ m / den)


@dataclass
class ColourModel:
    """Per class: the mean colour-name histogram of its training boxes and a cosine-distance threshold."""

    models: dict[str, np.ndarray] = field(default_factory=dict)
    thresholds: dict[str, float] = field(default_factory=dict)

    @staticmethod
    def fit(histograms: dict[str, list[np.ndarray]], quantile: float = 0.95) -> "ColourModel":
        """Model = normalised mean histogram; threshold = the ``quantile`` of the training distances."""
        cm = ColourModel()
        for cls, hs in histograms.items():
            H = np.asarray(hs, dtype=float)
            if len(H) == 0:
                continue
            m = H.mean(axis=0)
            m /= m.sum()
            d = np.array([cosine_distance(h, m) for h in H])
            cm.models[cls] = m
            cm.thresholds[cls] = float(np.quantile(d, quantile))
        return cm

    def distance(self, cls: str, hist: np.ndarray) -> float:
        return cosine_distance(hist, self.models[cls])

    def verify(self, cls: str, hist: np.ndarray) -> bool:
        """True when the box's colours match the class's model (classes without a model pass)."""
        if cls not in self.models:
            return True
        return self.distance(cls, hist) <= self.thresholds[cls]

    def to_json(self) -> dict:
        return {"names": list(NAMES), "models": {c: [float(v) for v in m] for c, m in self.models.items()},
                "thresholds": dict(self.thresholds)}

    @staticmethod
    def from_json(data: dict, source: str = "<dict>") -> "ColourModel":
        if list(data.get("names", [])) != list(NAMES):
            raise ValueError(f"{source}: field 'names': expected {list(NAMES)}")
        cm = ColourModel()
        for c, m in data.get("models", {}).items():
            m = np.asarray(m, dtype=float)
            if m.shape != (len(NAMES),):
                raise ValueError(f"{source}: field 'models.{c}': expected {len(NAMES)} numbers")
            cm.models[c] = m
        for c, t in data.get("thresholds", {}).items():
            cm.thresholds[c] = float(t)
        missing = set(cm.models) - set(cm.thresholds)
        if missing:
            raise ValueError(f"{source}: field 'thresholds': missing {sorted(missing)}")
        return cm

    def save(self, path: str | Path) -> None:
        path = Path(path)
        write_json(path, self.to_json(), indent=1)

    @staticmethod
    def load(path: str | Path) -> "ColourModel":
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise ValueError(f"{path}: unreadable colour model ({exc})") from exc
        return ColourModel.from_json(data, str(path))
