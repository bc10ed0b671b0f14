"""Sliding-window object detector of the topological-map paper (section 3): HOG shape filters, then the
colour-name verification step (``stack.dope.colour_names``).

What we chose, and why. The paper's iDPM is a deformable part model (root + part filters at twice
the resolution, latent SVM, three mixture components) on Felzenszwalb's 31-dimensional HOG, plus a
colour model. We keep the features (the 31-d HOG: 18 contrast-sensitive + 9 insensitive
orientations + 4 gradient energies, bilinear cell voting, four block normalisations, truncation at
0.2) and the three mixture components (by aspect ratio, as DPM initialises them), and train one
linear root filter per component with a linear SVM and hard-negative mining. We leave out the part
filters: our six objects are rigid cuboids whose image footprints are mostly 15-80 px, so parts at
twice the root resolution would be one or two cells each and deformation has nothing to model,
while the latent-SVM part training would cost hours of the two shared cores. Said plainly: this is
a mixture of HOG root filters (Dalal-Triggs / DPM without parts) with the paper's colour step.

Images are processed at the size the filters were trained at (320 x 240, DOPE's inference size:
larger frames are area-downscaled first); a feature pyramid with ``levels_per_octave`` levels
covers objects from about the filter size / ``max_scale`` to the whole image. Scores are linear
SVM margins (higher = more confident); non-maximum suppression per class.

Weights: ``stack/weights/hog_detector.npz`` (filters, biases, component shapes: arrays only) and
``stack/weights/hog_colour.json`` (the colour models).
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from stack.dope.colour_names import ColourModel, box_histogram
from stack.errors import InputDataError
from stack.io import atomic_path

log = logging.getLogger(__name__)
WEIGHTS_DIR = Path(__file__).resolve().parent.parent / "weights"
DEFAULT_WEIGHTS = WEIGHTS_DIR / "hog_detector.npz"
DEFAULT_COLOUR = WEIGHTS_DIR / "hog_colour.json"
N_FEAT = 31


# --- Felzenszwalb HOG ------------------------------------------------------------------------------

def _gradients(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel: the 18-bin contrast-sensitive orientation and the gradient magnitude, taken from
    the colour channel with the strongest gradient (as DPM does)."""
    img = image.astype(np.float32)
    if img.ndim == 2:
        img = img[..., None]
    dx = np.zeros_like(img)
    dy = np.zeros_like(img)
    dx[:, 1:-1] = img[:, 2:] - img[:, :-2]
    dy[1:-1] = img[2:] - img[:-2]
    mag2 = dx * dx + dy * dy
    best = np.argmax(mag2, axis=2)[..., None]
    gx = np.take_along_axis(dx, best, 2)[..., 0]
    gy = np.take_along_axis(dy, best, 2)[..., 0]
    mag = np.sqrt(np.take_along_axis(mag2, best, 2)[..., 0])
    ang = np.arctan2(gy, gx)
    b18 = np.floor((ang % (2 * np.pi)) * (18 / (2 * np.pi)) + 0.5).astype(np.int32) % 18
    return b18, mag


def _cell_histograms(b18: np.ndarray, mag: np.ndarray, cell: int) -> np.ndarray:
    """(H // cell, W // cell, 18) orientation histograms with bilinear voting into the four nearest cells."""
    H, W = mag.shape
    ch, cw = H // cell, W // cell
    fy = (np.arange(H) + 0.5) / cell - 0.5
    fx = (np.arange(W) + 0.5) / cell - 0.5
    y0 = np.floor(fy).astype(np.int64)
    x0 = np.floor(fx).astype(np.int64)
    wy1 = (fy - y0).astype(np.float32)
    wx1 = (fx - x0).astype(np.float32)
    out = np.zeros(ch * cw * 18, np.float64)
    bflat = b18.ravel()
    for dy_, wy in ((0, 1 - wy1), (1, wy1)):
        yy = y0 + dy_
        vy = (yy >= 0) & (yy < ch)
        for dx_, wx in ((0, 1 - wx1), (1, wx1)):
            xx = x0 + dx_
            vx = (xx >= 0) & (xx < cw)
            w = (mag * wy[:, None] * wx[None, :]).ravel()
            ok = (vy[:, None] & vx[None, :]).ravel()
            idx = ((yy[:, None] * cw + xx[None, :]).ravel() * 18 + bflat)
            out += np.bincount(idx[ok], weights=w[ok], minlength=ch * cw * 18)
    return out.reshape(ch, cw, 18).astype(np.float32)


def _normalise(hist: np.ndarray) -> np.ndarray:
    """The 31 features per cell from its 18-bin histogram and its neighbours' energies."""
    ch, cw = hist.shape[:2]
    insens = hist[..., :9] + hist[..., 9:]
    energy = np.sum(insens * insens, axis=2)
    e = np.pad(energy, 1, mode="edge")
    n = []
    for di in (-1, 1):
        for dj in (-1, 1):
            s = (e[1:-1, 1:-1] + e[1 + di:ch + 1 + di, 1:-1] + e[1:-1, 1 + dj:cw + 1 + dj]
                 + e[1 + di:ch + 1 + di, 1 + dj:cw + 1 + dj])
            n.append(1.0 / np.sqrt(s + 1e-4))
    N = np.stack(n, axis=-1)  # (ch, cw, 4)
    hs = np.minimum(hist[..., :, None] * N[..., None, :], 0.2)  # (ch, cw, 18, 4)
    hi = np.minimum(insens[..., :, None] * N[..., None, :], 0.2)  # (ch, cw, 9, 4)
    out = np.empty((ch, cw, N_FEAT), np.float32)
    out[..., :18] = 0.5 * hs.sum(-1)
    out[..., 18:27] = 0.5 * hi.sum(-1)
    out[..., 27:] = 0.2357 * hs.sum(2)
    return out


def fhog(image: np.ndarray, cell: int = 4) -> np.ndarray:
    """31-d HOG (Felzenszwalb et al. 2010) of an RGB or grey image: (H // cell, W // cell, 31) float32."""
    return _normalise(_cell_histograms(*_gradients(image), cell))


def fhog_cells(image: np.ndarray, cells: tuple[int, ...]) -> list[np.ndarray]:
    """The same image's HOG at several cell sizes (the gradients are computed once)."""
    b, m = _gradients(image)
    return [_normalise(_cell_histograms(b, m, c)) for c in cells]


# --- boxes ---------------------------------------------------------------------------------------

def iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of boxes a (N, 4) with b (M, 4), x0 y0 x1 y1 -> (N, M)."""
    a = np.asarray(a, dtype=float).reshape(-1, 4)
    b = np.asarray(b, dtype=float).reshape(-1, 4)
    x0 = np.maximum(a[:, None, 0], b[None, :, 0])
    y0 = np.maximum(a[:, None, 1], b[None, :, 1])
    x1 = np.minimum(a[:, None, 2], b[None, :, 2])
    y1 = np.minimum(a[:, None, 3], b[None, :, 3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    area = lambda r: (r[:, 2] - r[:, 0]) * (r[:, 3] - r[:, 1])  # noqa: E731
    return inter / np.maximum(area(a)[:, None] + area(b)[None, :] - inter, 1e-9)


def nms(boxes: np.ndarray, scores: np.ndarray, threshold: float = 0.4) -> np.ndarray:
    """Greedy non-maximum suppression (OpenCV's ``cv2.dnn.NMSBoxes``): indices of the boxes kept, best
    first; a box is dropped when its IoU with a kept, better-scoring one exceeds ``threshold``."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    scores = np.asarray(scores, dtype=np.float64).ravel()
    if len(boxes) == 0:
        return np.zeros(0, dtype=int)
    xywh = np.column_stack([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]])
    ranked = scores - scores.min() + 1.0  # NMSBoxes wants scores >= its threshold >= 0; the order is the same
    keep = cv2.dnn.NMSBoxes(xywh.tolist(), ranked.tolist(), 0.0, float(threshold))
    return np.asarray(keep, dtype=int).ravel()


# --- the model -----------------------------------------------------------------------------------

@dataclass(eq=False)
class Component:
    cls: str
    shape: tuple[int, int]  # filter rows, cols (cells)
    w: np.ndarray  # (rows, cols, 31)
    bias: float


@dataclass
class HogDetection:
    cls: str
    box: np.ndarray  # x0 y0 x1 y1 in the input image's pixels
    score: float
    component: int
    colour_distance: float | None = None
    colour_pass: bool | None = None


@dataclass
class HogDetector:
    components: list[Component] = field(default_factory=list)
    cell: int = 4
    width: int = 320  # the image width the filters were trained at
    levels_per_octave: int = 4
    max_scale: float = 2.0
    min_scale: float = 0.25
    nms_iou: float = 0.3
    colour: ColourModel | None = None
    colour_step: bool = True

    @property
    def classes(self) -> list[str]:
        return sorted({c.cls for c in self.components})

    # -- pyramid
    def pyramid(self, rgb: np.ndarray):
        """(scale, features) levels: ``levels_per_octave`` resized images, each described with cells of
        cell/2, cell, 2 cell, ... pixels (scale 2, 1, 0.5, ... of the image at the filters' cell size)."""
        cells = []
        c = self.cell / 2.0
        while c <= self.cell / self.min_scale + 1e-9:
            if self.cell / c <= self.max_scale + 1e-9:
                cells.append(c)
            c *= 2
        cells = [int(c) for c in cells if c >= 1 and float(c).is_integer()]
        for k in range(self.levels_per_octave):
            f = 2 ** (-k / self.levels_per_octave)
            w, h = int(round(rgb.shape[1] * f)), int(round(rgb.shape[0] * f))
            img = rgb if k == 0 else cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
            usable = [c for c in cells if min(w, h) >= 4 * c]
            for c, F in zip(usable, fhog_cells(img, tuple(usable))):
                yield f * self.cell / c, F

    # -- detection
    def detect(self, rgb: np.ndarray, threshold: float = -0.5, colour_step: bool | None = None,
               max_per_class: int = 20) -> list[HogDetection]:
        """Detections in an RGB image (any size: it is brought to the training width first)."""
        import torch

        f = self.width / rgb.shape[1]
        img = rgb if abs(f - 1) < 1e-6 else cv2.resize(rgb, (self.width, int(round(rgb.shape[0] * f))),
                                                       interpolation=cv2.INTER_AREA)
        by_cls: dict[str, list] = {}
        groups: dict[tuple, list[int]] = {}
        for ci, c in enumerate(self.components):
            groups.setdefault(c.shape, []).append(ci)
        weights = {shp: torch.from_numpy(np.stack([self.components[i].w for i in idx]).transpose(0, 3, 1, 2).copy())
                   for shp, idx in groups.items()}
        for s, F in self.pyramid(img):
            Ft = torch.from_numpy(F.transpose(2, 0, 1).copy())[None]
            for shp, idx in groups.items():
                if F.shape[0] < shp[0] or F.shape[1] < shp[1]:
                    continue
                with torch.no_grad():
                    R = torch.nn.functional.conv2d(Ft, weights[shp])[0].numpy()
                for k, ci in enumerate(idx):
                    c = self.components[ci]
                    sc = R[k] + c.bias
                    ys, xs = np.nonzero(sc > threshold)
                    if len(ys) == 0:
                        continue
                    cell = self.cell / s / f
                    boxes = np.column_stack([xs * cell, ys * cell, (xs + shp[1]) * cell, (ys + shp[0]) * cell])
                    by_cls.setdefault(c.cls, []).append((boxes, sc[ys, xs], np.full(len(ys), ci)))
        out = []
        use_colour = self.colour_step if colour_step is None else colour_step
        for cls, parts in by_cls.items():
            boxes = np.concatenate([p[0] for p in parts])
            scores = np.concatenate([p[1] for p in parts])
            comps = np.concatenate([p[2] for p in parts])
            top = np.argsort(-scores)[:50 * max_per_class]  # bounded NMS work
            boxes, scores, comps = boxes[top], scores[top], comps[top]
            keep = nms(boxes, scores, self.nms_iou)[:max_per_class]
            for i in keep:
                det = HogDetection(cls, boxes[i], float(scores[i]), int(comps[i]))
                if self.colour is not None and cls in self.colour.models:
                    h = box_histogram(rgb, det.box)
                    det.colour_distance = self.colour.distance(cls, h)
                    det.colour_pass = bool(det.colour_distance <= self.colour.thresholds[cls])
                out.append(det)
        if use_colour and self.colour is not None:
            out = [d for d in out if d.colour_pass is not False]
        out.sort(key=lambda d: -d.score)
        return out

    # -- persistence
    def save(self, path: str | Path = DEFAULT_WEIGHTS, colour_path: str | Path | None = DEFAULT_COLOUR) -> None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {"cell": np.array(self.cell), "width": np.array(self.width),
                  "levels_per_octave": np.array(self.levels_per_octave), "max_scale": np.array(self.max_scale),
                  "min_scale": np.array(self.min_scale), "nms_iou": np.array(self.nms_iou),
                  "classes": np.array([c.cls for c in self.components]),
                  "biases": np.array([c.bias for c in self.components])}
        for i, c in enumerate(self.components):
            arrays[f"w{i}"] = c.w.astype(np.float32)
        with atomic_path(path) as tmp:
            np.savez_compressed(tmp, **arrays)
        if colour_path is not None and self.colour is not None:
            self.colour.save(colour_path)

    @staticmethod
    def load(path: str | Path = DEFAULT_WEIGHTS, colour_path: str | Path | None = DEFAULT_COLOUR) -> "HogDetector":
        path = Path(path)
        try:
            a = np.load(path, allow_pickle=False)
            classes = [str(c) for c in a["classes"]]
            comps = [Component(cls, tuple(a[f"w{i}"].shape[:2]), a[f"w{i}"].astype(np.float32), float(a["biases"][i]))
                     for i, cls in enumerate(classes)]
        except (OSError, KeyError, ValueError) as exc:
            raise ValueError(f"{path}: unreadable HOG detector weights ({exc})") from exc
        for i, c in enumerate(comps):
            if c.w.ndim != 3 or c.w.shape[2] != N_FEAT:
                raise ValueError(f"{path}: field 'w{i}': expected (rows, cols, {N_FEAT}) filter, got {c.w.shape}")
        colour = ColourModel.load(colour_path) if colour_path is not None and Path(colour_path).exists() else None
        return HogDetector(comps, int(a["cell"]), int(a["width"]), int(a["levels_per_octave"]), float(a["max_scale"]),
                           float(a["min_scale"]), float(a["nms_iou"]), colour)


# --- training ------------------------------------------------------------------------------------

def window_features(rgb: np.ndarray, box, shape: tuple[int, int], cell: int) -> np.ndarray | None:
    """HOG of a box warped to a filter of ``shape`` cells (one cell of context each side, dropped)."""
    rows, cols = shape
    x0, y0, x1, y1 = (float(v) for v in box)
    bw, bh = x1 - x0, y1 - y0
    if bw < 2 or bh < 2:
        return None
    # context: one cell of the warped window on every side
    cx, cy = bw / cols, bh / rows
    src = np.float32([[x0 - cx, y0 - cy], [x1 + cx, y0 - cy], [x0 - cx, y1 + cy]])
    W, H = (cols + 2) * cell, (rows + 2) * cell
    dst = np.float32([[0, 0], [W, 0], [0, H]])
    M = cv2.getAffineTransform(src, dst)
    patch = cv2.warpAffine(rgb, M, (W, H), flags=cv2.INTER_AREA if bw > W else cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REFLECT)
    F = fhog(patch, cell)
    return F[1:1 + rows, 1:1 + cols]


def train_linear_svm(X: np.ndarray, y: np.ndarray, C: float = 0.01, pos_weight: float = 1.0,
                     max_iter: int = 1000) -> tuple[np.ndarray, float]:
    """L2-regularised squared-hinge linear SVM, min 0.5|w|^2 + C sum_i c_i max(0, 1 - y_i (w.x_i + b))^2
    (c_i = ``pos_weight`` for positives, 1 for negatives), solved in the primal by liblinear
    (scikit-learn's ``LinearSVC``). liblinear regularises the bias as one more weight on a constant
    feature; that feature is large (``intercept_scaling`` 100), so the bias is in effect free."""
    from sklearn.svm import LinearSVC

    X = np.asarray(X, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    svm = LinearSVC(penalty="l2", loss="squared_hinge", dual=False, C=C, fit_intercept=True,
                    intercept_scaling=100.0, tol=1e-6, max_iter=max_iter)
    svm.fit(X, (y > 0).astype(int), sample_weight=np.where(y > 0, pos_weight, 1.0))
    return svm.coef_.ravel().copy(), float(svm.intercept_[0])


def component_shapes(boxes: np.ndarray, n_components: int = 3, cells_area: float = 40.0,
                     min_side: int = 3) -> list[tuple[tuple[int, int], tuple[float, float]]]:
    """DPM's initialisation: split a class's boxes by aspect ratio (equal-count groups) and give each
    group a filter of about ``cells_area`` cells with the group's median aspect ratio.
    Returns [(shape (rows, cols), (aspect lo, aspect hi))]."""
    ar = (boxes[:, 2] - boxes[:, 0]) / np.maximum(boxes[:, 3] - boxes[:, 1], 1e-6)  # width / height
    qs = np.quantile(ar, np.linspace(0, 1, n_components + 1))
    out = []
    for k in range(n_components):
        lo, hi = qs[k], qs[k + 1]
        sel = (ar >= lo) & (ar <= hi)
        a = float(np.median(ar[sel])) if sel.any() else float(np.median(ar))
        rows = max(min_side, int(round(np.sqrt(cells_area / a))))
        cols = max(min_side, int(round(rows * a)))
        out.append(((rows, cols), (float(lo) if k else 0.0, float(hi) if k < n_components - 1 else np.inf)))
    return out


@dataclass
class TrainingImage:
    rgb: np.ndarray  # at the detector's width
    boxes: np.ndarray  # (M, 4)
    classes: list[str]
    visible: np.ndarray  # (M,) visible fraction


def _random_negative_boxes(rng, img: TrainingImage, cls: str, aspect: float, n: int, min_h: float = 12.0) -> list:
    H, W = img.rgb.shape[:2]
    own = img.boxes[[c == cls for c in img.classes]] if len(img.boxes) else np.zeros((0, 4))
    out = []
    for _ in range(n * 4):
        h = float(np.exp(rng.uniform(np.log(min_h), np.log(H * 0.9))))
        w = h * aspect
        if w >= W * 0.95:
            continue
        x0 = rng.uniform(0, W - w)
        y0 = rng.uniform(0, H - h)
        b = np.array([x0, y0, x0 + w, y0 + h])
        if len(own) and iou(b[None], own).max() > 0.3:
            continue
        out.append(b)
        if len(out) == n:
            break
    return out


def train_detector(images: list[TrainingImage], classes: list[str], cell: int = 4, n_components: int = 3,
                   cells_area: float = 32.0, negatives_per_image: int = 4, mining_rounds: int = 1,
                   mining_images: int = 200, C: float = 0.01, seed: int = 0, min_box_h: float = 12.0,
                   min_visible: float = 0.6, log_every: float = 20.0) -> HogDetector:
    """Train the mixture of root filters: warped positives, random negatives (and the other classes'
    objects), then rounds of hard-negative mining (the detector's confident false positives on
    training images are added to the negatives and the SVMs retrained)."""
    rng = np.random.default_rng(seed)
    det = HogDetector(cell=cell, width=images[0].rgb.shape[1])
    t_start = time.perf_counter()
    data: list[tuple[np.ndarray, np.ndarray]] = []  # per component: positives, negatives (flattened features)
    for cls in classes:
        pos = [(i, b) for i, im in enumerate(images) for b, c, v in zip(im.boxes, im.classes, im.visible)
               if c == cls and v >= min_visible and (b[3] - b[1]) >= min_box_h]
        if len(pos) < 10:
            log.warning("class %s: only %d positive boxes, skipped", cls, len(pos))
            continue
        pb = np.array([b for _, b in pos])
        shapes = component_shapes(pb, n_components, cells_area)
        ar = (pb[:, 2] - pb[:, 0]) / (pb[:, 3] - pb[:, 1])
        for k, (shape, (lo, hi)) in enumerate(shapes):
            members = [pos[i] for i in np.flatnonzero((ar >= lo) & (ar <= hi))]
            Xp = [f for f in (window_features(images[i].rgb, b, shape, cell) for i, b in members) if f is not None]
            aspect = shape[1] / shape[0]
            Xn = []
            for i in rng.permutation(len(images)):
                for b in _random_negative_boxes(rng, images[i], cls, aspect, negatives_per_image, min_box_h):
                    f = window_features(images[i].rgb, b, shape, cell)
                    if f is not None:
                        Xn.append(f)
            # other classes' objects are the hardest negatives: include them all
            for im in images:
                own = im.boxes[[cc == cls for cc in im.classes]]
                for b, c in zip(im.boxes, im.classes):
                    if c != cls and (b[3] - b[1]) >= min_box_h:
                        if len(own) and iou(b[None], own).max() > 0.3:
                            continue
                        f = window_features(im.rgb, b, shape, cell)
                        if f is not None:
                            Xn.append(f)
            Xp_a = np.array(Xp, dtype=np.float32).reshape(len(Xp), -1)
            Xn_a = np.array(Xn, dtype=np.float32).reshape(len(Xn), -1)
            data.append((Xp_a, Xn_a))
            w, b = _fit(Xp_a, Xn_a, C)
            det.components.append(Component(cls, shape, w.reshape(shape[0], shape[1], N_FEAT).astype(np.float32), b))
            log.info("class %s component %d %s: %d positives, %d negatives (%.0f s)", cls, k, shape, len(Xp_a),
                     len(Xn_a), time.perf_counter() - t_start)
    for r in range(mining_rounds):
        hard: dict[int, list] = {i: [] for i in range(len(det.components))}
        idx = rng.permutation(len(images))[:mining_images]
        last = time.perf_counter()
        for n, i in enumerate(idx):
            im = images[i]
            for d in det.detect(im.rgb, threshold=-1.0, colour_step=False, max_per_class=10):
                own = im.boxes[[c == d.cls for c in im.classes]] if len(im.boxes) else np.zeros((0, 4))
                if len(own) and iou(d.box[None], own).max() > 0.3:
                    continue
                hard[d.component].append((i, d.box))
            if time.perf_counter() - last > log_every:
                last = time.perf_counter()
                log.info("mining round %d: %d / %d images", r + 1, n + 1, len(idx))
        for ci, c in enumerate(det.components):
            Xh = [f for f in (window_features(images[i].rgb, b, c.shape, cell) for i, b in hard[ci]) if f is not None]
            if not Xh:
                continue
            Xp_a, Xn_a = data[ci]
            Xn_a = np.vstack([Xn_a, np.array(Xh, dtype=np.float32).reshape(len(Xh), -1)])
            data[ci] = (Xp_a, Xn_a)
            w, b = _fit(Xp_a, Xn_a, C)
            c.w = w.reshape(c.w.shape).astype(np.float32)
            c.bias = b
        log.info("mining round %d done: %d hard negatives (%.0f s)", r + 1, sum(len(h) for h in hard.values()),
                 time.perf_counter() - t_start)
    return det


def _fit(Xp: np.ndarray, Xn: np.ndarray, C: float) -> tuple[np.ndarray, float]:
    X = np.vstack([Xp, Xn])
    y = np.r_[np.ones(len(Xp)), -np.ones(len(Xn))]
    return train_linear_svm(X, y, C, pos_weight=0.5 * len(Xn) / max(1, len(Xp)))


def fit_colour_model(images: list[TrainingImage], classes: list[str], quantile: float = 0.95,
                     min_box_h: float = 12.0, min_visible: float = 0.6) -> ColourModel:
    hists = {c: [] for c in classes}
    for im in images:
        for b, c, v in zip(im.boxes, im.classes, im.visible):
            if c in hists and v >= min_visible and (b[3] - b[1]) >= min_box_h:
                hists[c].append(box_histogram(im.rgb, b))
    return ColourModel.fit(hists, quantile)


def load_shard_images(data_dir: str | Path, shards: list[int] | None = None, classes: tuple = (),
                      width: int = 320) -> list[TrainingImage]:
    """DOPE data shards (``sim.datagen`` format) as training images with tight visible boxes from the
    segmentation (value k = the k-th annotated object of the image)."""
    data_dir = Path(data_dir)
    out = []
    files = sorted(data_dir.glob("shard_*.json"))
    for meta_path in files:
        idx = int(meta_path.stem.split("_")[1])
        if shards is not None and idx not in shards:
            continue
        npz = meta_path.with_suffix(".npz")
        try:
            meta = json.loads(meta_path.read_text())
            a = np.load(npz)
            rgb, seg = a["rgb"], a["seg"]
        except (OSError, ValueError, KeyError) as exc:
            raise InputDataError(f"{npz}: unreadable DOPE data shard ({exc})") from exc
        for i, image in enumerate(meta["images"]):
            boxes, cls, vis = [], [], []
            for k, o in enumerate(image["objects"]):
                if classes and o["class"] not in classes:
                    continue
                ys, xs = np.nonzero(seg[i] == k)
                if len(xs) < 4:
                    continue
                boxes.append([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1])
                cls.append(o["class"])
                vis.append(o["pixels_visible"] / max(o["hull_area_px"], 1.0))
            im = rgb[i]
            f = width / im.shape[1]
            if abs(f - 1) > 1e-6:
                im = cv2.resize(im, (width, int(round(im.shape[0] * f))), interpolation=cv2.INTER_AREA)
                boxes = [list(np.asarray(b) * f) for b in boxes]
            out.append(TrainingImage(im, np.array(boxes, dtype=float).reshape(-1, 4), cls, np.array(vis, dtype=float)))
    return out
