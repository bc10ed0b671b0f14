"""Training DOPE on the synthetic shards written by ``sim/datagen.py`` (``dopeslam train``).

Reads shards (``shard_NNNNN.npz`` + ``.json``) from a data directory, samples crops around the
annotated objects, builds belief/affinity targets (:mod:`stack.dope.targets`), and minimises the
L2 loss on every stage's beliefs and affinities, with pixels near key points up-weighted so that a
network predicting all-zero maps is not rewarded. Augmentation: brightness, contrast, per-channel
gain, blur and sensor noise. Adam with a step-decayed learning rate.

Checkpoints (model + optimiser + step + loss history) are written atomically every
``checkpoint_minutes`` and on exit; a run resumes from its checkpoint. Each checkpoint also writes
half-precision weights (what ships), a loss-curve PNG and an evaluation on held-out images (the
per-corner key-point error in pixels at the network's 320x240 input). New shards appearing in the
data directory while training runs are picked up. Creating a file ``STOP`` in the run directory ends
the run cleanly (final checkpoint written).

This module reads data files but does not import the simulator: it runs on any machine with torch,
on a GPU when one is present.
"""
from __future__ import annotations

import json
import logging
import math
import os
import re
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from stack.dope.net import N_BELIEF, STRIDE, DopeNet, DopeNetConfig, expand_stages, save_weights
from stack.dope.targets import make_targets, to_input_px
from stack.errors import InputDataError
from stack.io import atomic_path

log = logging.getLogger(__name__)

MEAN, STD = 0.5, 0.25  # input normalisation of [0, 1] images
CORNER_NAMES = ("FTR", "FTL", "FBL", "FBR", "RTR", "RTL", "RBL", "RBR", "C")


@dataclass
class TrainConfig:
    data_dir: str
    out_dir: str
    input: str = "rgb"  # "rgb" | "depth"
    width: float = 0.25
    stages: int = 6
    batch: int = 8
    crop: tuple = (128, 128)  # (w, h) input pixels, multiples of 8
    lr: float = 1e-3
    lr_decay_steps: tuple = (5000, 8000)  # multiply lr by 0.3 at each
    max_steps: int = 1_000_000
    max_minutes: float = 1e9
    checkpoint_minutes: float = 5.0
    peak_weight: float = 10.0
    sigma: float = 1.0
    radius: float = 1.5
    val_shards: int = 2  # the first shards (by index) are held out
    val_images: int = 24
    seed: int = 0
    init_from: str = ""  # weights/checkpoint to start from (e.g. RGB weights for the depth net)
    depth_window: tuple = (0.0, 0.0)  # (near, far) m for depth input; (0, 0) = around the nearest object
    min_visible: float = 0.15  # an object is a target when this fraction of its cuboid hull is seen
    threads: int = 0
    classes: tuple = ("OrangeJuice", "Yogurt", "Mustard", "Raisins", "Cookies", "E")
    class_weights: dict = field(default_factory=dict)  # {class: weight} picking a crop's focal object (default 1)
    extra: dict = field(default_factory=dict)


# --- data ----------------------------------------------------------------------------------------

_CORNER_SIGNS = np.array([[1, 1, 1], [-1, 1, 1], [-1, -1, 1], [1, -1, 1],
                          [1, 1, -1], [-1, 1, -1], [-1, -1, -1], [1, -1, -1], [0, 0, 0]])


def canonical_order(quat_xyzw, location) -> np.ndarray:
    """Key-point relabelling (index array) that makes the labelled front face the one towards the camera.

    A cuboid standing upright looks the same after a half turn about its vertical axis; only texture
    tells the two apart, which a small CPU-trained network learns slowly (DESIGN.md). The annotation is
    therefore relabelled by that half turn whenever the object's front (+z) faces away from the camera.
    The centroid and the translation PnP recovers are unchanged; the orientation is then defined up to
    that half turn. The vertical axis is the object axis most aligned with the camera's y (down) axis.
    """
    from scipy.spatial.transform import Rotation

    R = Rotation.from_quat(quat_xyzw).as_matrix()  # object -> camera
    up = int(np.argmax(np.abs(R[1])))
    to_cam = -np.asarray(location, dtype=float)
    if up == 2 or R[:, 2] @ to_cam >= 0:
        return np.arange(9)
    flip = -np.ones(3)
    flip[up] = 1  # half turn about the up axis negates the other two coordinates
    target = _CORNER_SIGNS * flip
    return np.array([int(np.nonzero(np.all(_CORNER_SIGNS == t, axis=1))[0][0]) for t in target])


class ShardData:
    """All shards of a data directory in memory: images and per-image targets (class, key points)."""

    def __init__(self, data_dir: str | Path, classes: tuple, min_visible: float = 0.15, load_depth: bool = False,
                 canonical: bool = True):
        self.data_dir = Path(data_dir)
        self.canonical = canonical
        self.classes = tuple(classes)
        self.min_visible = min_visible
        self.load_depth = load_depth
        self.loaded: set[int] = set()
        self.rgb: list[np.ndarray] = []
        self.depth: list[np.ndarray] = []
        self.objects: list[list[tuple[int, np.ndarray, np.ndarray]]] = []  # (class, kp (9,2), location (3,))
        self.shard_of: list[int] = []
        self.K: np.ndarray | None = None

    def available(self) -> list[int]:
        out = []
        for path in sorted(self.data_dir.glob("shard_*.npz")):
            m = re.fullmatch(r"shard_(\d+)\.npz", path.name)  # skips temporary files being written
            if m is None:
                continue
            idx = int(m.group(1))
            if path.with_suffix(".json").exists():
                out.append(idx)
        return out

    def refresh(self, only: set[int] | None = None, exclude: set[int] = frozenset()) -> int:
        """Load shards not loaded yet; returns how many images were added."""
        added = 0
        for idx in self.available():
            if idx in self.loaded or idx in exclude or (only is not None and idx not in only):
                continue
            npz = self.data_dir / f"shard_{idx:05d}.npz"
            meta_path = npz.with_suffix(".json")
            try:
                with open(meta_path) as f:
                    meta = json.load(f)
                arrays = np.load(npz)
                rgb = arrays["rgb"]
                depth = arrays["depth_mm"] if self.load_depth else None
            except (OSError, ValueError, KeyError) as exc:
                raise InputDataError(f"{npz}: unreadable DOPE data shard ({exc})") from exc
            if self.K is None:
                self.K = np.array(meta["K"], dtype=float)
            for i, image in enumerate(meta["images"]):
                objs = []
                for o in image["objects"]:
                    if o["class"] not in self.classes:
                        continue
                    seen = o["pixels_visible"] / max(o["hull_area_px"], 1.0)
                    if o["pixels_visible"] < 12 or seen < self.min_visible:
                        continue
                    kp = np.array(o["keypoints_px"], dtype=np.float64)
                    loc = np.array(o["location"], dtype=np.float64)
                    if self.canonical:
                        kp = kp[canonical_order(o["quaternion_xyzw"], loc)]
                    objs.append((self.classes.index(o["class"]), kp, loc))
                self.rgb.append(rgb[i])
                if depth is not None:
                    self.depth.append(depth[i])
                self.objects.append(objs)
                self.shard_of.append(idx)
                added += 1
            self.loaded.add(idx)
        return added

    def __len__(self) -> int:
        return len(self.rgb)


def normalise(img01: np.ndarray) -> np.ndarray:
    """(H, W, 3) float in [0, 1] -> (3, H, W) network input."""
    return ((img01 - MEAN) / STD).transpose(2, 0, 1).astype(np.float32)


def depth_input(depth_mm: np.ndarray, window: tuple[float, float]) -> np.ndarray:
    """(H, W, 3) float [0, 1] network image from a depth map (mm) and a (near, far) window in metres."""
    from stack.dope.depth_window import preprocess_depth

    img = preprocess_depth(depth_mm.astype(np.float32) / 1000.0, window[0], window[1])
    return np.repeat(img[..., None], 3, axis=2)


def augment_rgb(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """uint8 (H, W, 3) -> float [0, 1] with random brightness, contrast, gain, blur and noise."""
    x = img.astype(np.float32) / 255.0
    if rng.random() < 0.3:
        x = cv2.GaussianBlur(x, (0, 0), float(rng.uniform(0.3, 1.2)))
    contrast = rng.uniform(0.6, 1.4)
    brightness = rng.uniform(-0.2, 0.2)
    gain = rng.uniform(0.85, 1.15, 3).astype(np.float32)
    mean = x.mean()
    x = (x - mean) * contrast + mean + brightness
    x = x * gain
    if rng.random() < 0.2:
        x = x * rng.uniform(0.2, 0.6)  # dim scene
    x = x + rng.standard_normal(x.shape).astype(np.float32) * rng.uniform(0.0, 0.04)
    return np.clip(x, 0.0, 1.0)


def augment_depth(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    x = img + rng.standard_normal(img.shape).astype(np.float32) * rng.uniform(0.0, 0.03)
    return np.clip(x, 0.0, 1.0)


def choose_window(objects, rng: np.random.Generator, depth_range: float = 0.3, focus=None) -> tuple[float, float]:
    """A depth window of ``depth_range`` m containing ``focus`` (an annotated object), else a random
    annotated object, 10 % of the time a random window."""
    if objects and rng.random() < 0.9:
        z = (focus if focus is not None else objects[rng.integers(len(objects))])[2][2]
        near = z - rng.uniform(0.05, depth_range - 0.05)
    else:
        near = rng.uniform(0.25, 2.0)
    return float(near), float(near + depth_range)


def pick_focus(objects, cfg: TrainConfig, rng: np.random.Generator) -> int:
    """Index of the object a crop is centred on: uniform, or in proportion to ``cfg.class_weights``."""
    if not cfg.class_weights:
        return int(rng.integers(len(objects)))
    w = np.array([float(cfg.class_weights.get(cfg.classes[o[0]], 1.0)) for o in objects])
    return int(rng.choice(len(objects), p=w / w.sum()))


def sample_batch(data: ShardData, cfg: TrainConfig, rng: np.random.Generator, indices: np.ndarray | None = None):
    """(inputs (B,3,h,w), beliefs (B,C*9,h/8,w/8), affinities (B,C*16,h/8,w/8)) as float32 tensors."""
    cw, ch = cfg.crop
    n_cls = len(cfg.classes)
    xs, bs, afs = [], [], []
    pool = np.arange(len(data)) if indices is None else indices
    for _ in range(cfg.batch):
        i = int(pool[rng.integers(len(pool))])
        objs = data.objects[i]
        H, W = data.rgb[i].shape[:2]
        focus = None
        if objs and rng.random() < 0.85:
            focus = objs[pick_focus(objs, cfg, rng)]
            c = focus[1][8] + rng.uniform(-0.35, 0.35, 2) * (cw, ch)
        else:
            c = rng.uniform([0, 0], [W, H])
        x0 = int(np.clip(round(c[0] - cw / 2), 0, W - cw))
        y0 = int(np.clip(round(c[1] - ch / 2), 0, H - ch))
        if cfg.input == "depth":
            fixed = cfg.depth_window[1] > cfg.depth_window[0]
            window = cfg.depth_window if fixed else choose_window(objs, rng, focus=focus)
            img = depth_input(data.depth[i], window)[y0:y0 + ch, x0:x0 + cw]
            img = augment_depth(img, rng)
            in_window = [o for o in objs if window[0] - 0.05 <= o[2][2] <= window[1] + 0.05]
            use = in_window
        else:
            img = augment_rgb(data.rgb[i][y0:y0 + ch, x0:x0 + cw], rng)
            use = objs
        kps = np.array([o[1] - (x0, y0) for o in use]).reshape(-1, 9, 2)
        cls = np.array([o[0] for o in use], dtype=int)
        b, a = make_targets(kps, cls, n_cls, (ch // STRIDE, cw // STRIDE), sigma=cfg.sigma, radius=cfg.radius)
        xs.append(normalise(img))
        bs.append(b)
        afs.append(a)
    return torch.from_numpy(np.stack(xs)), torch.from_numpy(np.stack(bs)), torch.from_numpy(np.stack(afs))


# --- loss ----------------------------------------------------------------------------------------

def dope_loss(outputs, belief_t: torch.Tensor, affinity_t: torch.Tensor, peak_weight: float = 10.0):
    """Sum over stages of the weighted mean squared error of beliefs and affinities.

    Weights are ``1 + peak_weight * target`` for beliefs and ``1 + peak_weight * [affinity target set]``
    for affinities, so the few pixels that carry a key point count as much as the empty background.
    """
    wb = 1.0 + peak_weight * belief_t
    wa = 1.0 + peak_weight * (affinity_t.abs() > 0).float()
    total = belief_t.new_zeros(())
    for b, a in outputs:
        total = total + (wb * (b - belief_t) ** 2).mean() + (wa * (a - affinity_t) ** 2).mean()
    return total


# --- evaluation ----------------------------------------------------------------------------------

def refine_peak(belief: np.ndarray, y: int, x: int, r: int = 1) -> tuple[float, float]:
    """Sub-cell peak position: belief-weighted centroid of the (2r+1)^2 window (negative values clipped)."""
    h, w = belief.shape
    y0, y1, x0, x1 = max(0, y - r), min(h, y + r + 1), max(0, x - r), min(w, x + r + 1)
    win = np.clip(belief[y0:y1, x0:x1], 0, None)
    s = win.sum()
    if s <= 1e-9:
        return float(x), float(y)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    return float((win * xx).sum() / s), float((win * yy).sum() / s)


@torch.no_grad()
def evaluate_keypoints(model: DopeNet, data: ShardData, indices, cfg: TrainConfig, device, search_px: float = 24.0):
    """Per key point (8 corners + centroid) median error in input pixels at 320x240 and the fraction within 4 px.

    For every annotated object in the held-out images the peak of the class's belief map nearest to the
    ground truth (within ``search_px``) is taken; a missing peak counts as an error of ``search_px``.
    """
    model.eval()
    errs = [[] for _ in range(9)]
    rng = np.random.default_rng(123)
    for i in indices:
        objs = data.objects[i]
        if not objs:
            continue
        if cfg.input == "depth":
            o = objs[rng.integers(len(objs))]
            near = o[2][2] - 0.15
            img = depth_input(data.depth[i], (near, near + 0.3))
            objs = [p for p in objs if near - 0.05 <= p[2][2] <= near + 0.35]
        else:
            img = data.rgb[i].astype(np.float32) / 255.0
        x = torch.from_numpy(normalise(img))[None].to(device)
        belief = model(x)[-1][0][0].float().cpu().numpy()
        hb, wb = belief.shape[-2:]
        for cls, kp, _ in objs:
            for k in range(9):
                u, v = kp[k]
                if not (0 <= u < img.shape[1] and 0 <= v < img.shape[0]):
                    continue
                m = belief[cls * N_BELIEF + k]
                g = (np.array([u, v]) + 0.5) / STRIDE - 0.5
                rc = int(math.ceil(search_px / STRIDE))
                y0, y1 = max(0, int(round(g[1])) - rc), min(hb, int(round(g[1])) + rc + 1)
                x0, x1 = max(0, int(round(g[0])) - rc), min(wb, int(round(g[0])) + rc + 1)
                win = m[y0:y1, x0:x1]
                if win.size == 0 or win.max() < 0.05:
                    errs[k].append(search_px)
                    continue
                yy, xx = np.unravel_index(int(np.argmax(win)), win.shape)
                px, py = refine_peak(m, y0 + yy, x0 + xx)
                pu, pv = to_input_px(np.array([px, py]))
                errs[k].append(min(search_px, float(np.hypot(pu - u, pv - v))))
    model.train()
    out = {}
    for k, name in enumerate(CORNER_NAMES):
        e = np.array(errs[k]) if errs[k] else np.array([np.nan])
        out[name] = {"median_px": float(np.median(e)), "within4_pct": float(100 * np.mean(e <= 4.0)), "n": len(errs[k])}
    return out


# --- loop ----------------------------------------------------------------------------------------

def _atomic_torch_save(obj, path: Path) -> None:
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def plot_loss(history: list[tuple[int, float]], path: Path, title: str = "DOPE training loss") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not history:
        return
    steps, losses = np.array(history).T
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(steps, losses, lw=0.5, alpha=0.4, label="loss")
    if len(losses) > 20:
        k = max(5, len(losses) // 50)
        smooth = np.convolve(losses, np.ones(k) / k, mode="valid")
        ax.plot(steps[k - 1:], smooth, lw=1.5, label=f"mean of {k}")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss (sum over stages)")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=100, format="png")
    finally:
        plt.close(fig)


def lr_at(step: int, cfg: TrainConfig) -> float:
    lr = cfg.lr
    for s in cfg.lr_decay_steps:
        if step >= s:
            lr *= 0.3
    warm = 200
    return lr * min(1.0, (step + 1) / warm)


def train(cfg: TrainConfig) -> dict:
    """Train (or resume) until ``max_steps`` or ``max_minutes``; returns the final summary."""
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    data = ShardData(cfg.data_dir, cfg.classes, cfg.min_visible, load_depth=cfg.input == "depth")
    avail = data.available()
    if not avail:  # before anything is made
        raise InputDataError(f"{cfg.data_dir}: no shard_*.npz/.json pairs (run `dopeslam datagen` first)")
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / "checkpoint.pt"
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)

    in_ch = 3
    model = DopeNet(DopeNetConfig(tuple(cfg.classes), cfg.width, cfg.stages, in_ch)).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    step, history, evals = 0, [], []
    if ckpt_path.exists():
        ck = torch.load(ckpt_path, map_location=device, weights_only=True)
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        step = int(ck["step"])
        history = [tuple(h) for h in ck["history"]]
        evals = json.loads(ck.get("evals_json", "[]"))
        rng = np.random.default_rng([cfg.seed, step])
        log.info("resumed %s at step %d", ckpt_path, step)
    elif cfg.init_from:
        try:  # tensors only: nothing in the file runs
            blob = torch.load(cfg.init_from, map_location="cpu", weights_only=True)
            state = {k: v.float() for k, v in (blob.get("state_dict") or blob.get("model")).items()}
        except FileNotFoundError:
            raise InputDataError(f"{cfg.init_from}: file not found (--init-from)") from None
        except Exception as exc:  # noqa: BLE001 - torch's unpickler raises many kinds for foreign bytes
            why = (str(exc).strip().splitlines() or [type(exc).__name__])[0].split(". ")[0][:120]
            raise InputDataError(f"{cfg.init_from}: expected DOPE weights or a training checkpoint ({why})") from None
        n_src = 1 + max(int(k.split(".")[1]) for k in state if k.startswith("stages."))
        if n_src != cfg.stages:
            # a shorter cascade: its last stage is repeated (expand_stages) to reach cfg.stages
            src = DopeNet(DopeNetConfig(tuple(cfg.classes), cfg.width, n_src, in_ch))
            src.load_state_dict(state)
            state = expand_stages(src, cfg.stages).state_dict() if n_src < cfg.stages else \
                {k: v for k, v in state.items() if not k.startswith("stages.") or int(k.split(".")[1]) < cfg.stages}
        model.load_state_dict(state)
        log.info("initialised from %s (%d stages -> %d)", cfg.init_from, n_src, cfg.stages)

    val_ids = set(avail[:cfg.val_shards])
    val = ShardData(cfg.data_dir, cfg.classes, cfg.min_visible, load_depth=cfg.input == "depth")
    val.refresh(only=val_ids)
    n = data.refresh(exclude=val_ids)
    log.info("data: %d training images, %d held-out images from %s", n, len(val), cfg.data_dir)
    val_idx = np.arange(min(cfg.val_images, len(val)))

    t_start = time.time()
    t_ckpt = time.time()
    t_refresh = time.time()
    t_log = time.time()
    model.train()
    losses_since = []

    def checkpoint(final: bool = False):
        ev = evaluate_keypoints(model, val, val_idx, cfg, device) if len(val) else {}
        medians = {k: round(v["median_px"], 2) for k, v in ev.items()}
        evals.append({"step": step, "minutes": round((time.time() - t_start) / 60, 1), "median_px": medians,
                      "within4_pct": {k: round(v["within4_pct"], 1) for k, v in ev.items()}})
        log.info("eval step %d: median px %s", step, medians)
        state = {"model": model.state_dict(), "optimizer": opt.state_dict(), "step": step,
                 "history": [list(h) for h in history], "evals_json": json.dumps(evals),
                 "config_json": json.dumps(asdict(cfg))}
        _atomic_torch_save(state, ckpt_path)
        save_weights(out / "weights_fp16.pt", model, half=True,
                     extra={"input": cfg.input, "step": step, "train_images": len(data),
                            "data_dir": str(cfg.data_dir), "sigma": cfg.sigma, "radius": cfg.radius})
        plot_loss(history, out / "loss.png", f"DOPE ({cfg.input}) training loss")
        with open(out / "evals.json.tmp", "w") as f:
            json.dump({"config": asdict(cfg), "step": step, "train_images": len(data), "evals": evals}, f, indent=1)
        os.replace(out / "evals.json.tmp", out / "evals.json")

    try:
        while step < cfg.max_steps and (time.time() - t_start) / 60 < cfg.max_minutes:
            if (out / "STOP").exists():  # graceful stop: checkpoint and exit
                log.info("found %s: stopping", out / "STOP")
                (out / "STOP").unlink()
                break
            for g in opt.param_groups:
                g["lr"] = lr_at(step, cfg)
            x, bt, at = sample_batch(data, cfg, rng)
            x, bt, at = x.to(device), bt.to(device), at.to(device)
            outputs = model(x)
            loss = dope_loss(outputs, bt, at, cfg.peak_weight)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            step += 1
            lv = float(loss.detach())
            losses_since.append(lv)
            if step % 10 == 0:
                history.append((step, float(np.mean(losses_since[-10:]))))
            if time.time() - t_log > 60 or step % 100 == 0:
                dt = (time.time() - t_start) / 60
                log.info("step %d  loss %.4f  lr %.1e  %.1f min  %d images", step, np.mean(losses_since),
                         lr_at(step, cfg), dt, len(data))
                losses_since = []
                t_log = time.time()
            if time.time() - t_refresh > 120:
                added = data.refresh(exclude=val_ids)
                if added:
                    log.info("picked up %d new images (%d total)", added, len(data))
                t_refresh = time.time()
            if time.time() - t_ckpt > cfg.checkpoint_minutes * 60:
                checkpoint()
                t_ckpt = time.time()
    finally:
        checkpoint(final=True)
    return {"step": step, "evals": evals[-1] if evals else {}, "train_images": len(data)}
