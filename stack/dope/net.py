"""The DOPE network: a VGG-19 front end and a cascade of belief/affinity stages.

Topology (Tremblay et al. 2018, as used in the DOPESLAM paper, section 3.1), scaled by a width
multiplier so that it trains and runs on a CPU:

- features: VGG-19's first ten 3x3 convolutions (64, 64, pool, 128, 128, pool, 256 x4, pool,
  512, 512) then two 3x3 convolutions reducing to 256 and 128 features; output stride 8.
- stage 1: three 3x3 convolutions (128), a 1x1 (512) and a 1x1 output layer.
- stages 2..S: the previous stage's maps concatenated with the features, five 7x7 convolutions
  (128), a 1x1 (128) and a 1x1 output layer.

Every stage outputs, for every object class, 9 belief maps (8 cuboid corners + centroid, DOPE
order) and 16 affinity maps (the x, y unit vector from each corner towards the centroid).
All channel counts are multiplied by ``width``.

Two deliberate departures from the original, both for the 2-core CPU budget (see the model card):
one network is shared by all classes (one trunk, per-class channel groups in the output) instead
of one network per class, and each stage is one tower whose last layer emits beliefs and
affinities together instead of two parallel towers. The number of stages evaluated at inference
is a call argument (1..6): a 1-stage network is the same weights with the later stages skipped.
"""
from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass

import torch
from torch import nn

from stack.errors import DopeSlamError
from stack.io import atomic_path

N_BELIEF = 9  # 8 corners + centroid
N_AFFINITY = 16  # 8 corners x (dx, dy)
STRIDE = 8


@dataclass
class DopeNetConfig:
    classes: tuple = ("OrangeJuice", "Yogurt", "Mustard", "Raisins", "Cookies", "E")
    width: float = 0.25
    stages: int = 6
    in_channels: int = 3

    def to_dict(self) -> dict:
        d = asdict(self)
        d["classes"] = list(self.classes)
        return d

    @staticmethod
    def from_dict(d: dict) -> "DopeNetConfig":
        return DopeNetConfig(tuple(d["classes"]), float(d["width"]), int(d["stages"]), int(d.get("in_channels", 3)))


def _ch(n: int, width: float) -> int:
    return max(4, int(round(n * width)))


def _conv(cin: int, cout: int, k: int, relu: bool = True) -> list[nn.Module]:
    layers: list[nn.Module] = [nn.Conv2d(cin, cout, k, padding=k // 2)]
    if relu:
        layers.append(nn.ReLU(inplace=True))
    return layers


def _in_order(t: torch.Tensor, memory_format: torch.memory_format | None) -> torch.Tensor:
    return t if memory_format is None else t.contiguous(memory_format=memory_format)


def _stage_count(config: DopeNetConfig, stages: int | None) -> int:
    """The number of stages a forward pass evaluates (None: all); outside 1..``config.stages``: ValueError."""
    n = config.stages if stages is None else int(stages)
    if not 1 <= n <= config.stages:
        raise ValueError(f"stages must be 1..{config.stages}, got {n}")
    return n


class DopeNet(nn.Module):
    """Shared-trunk DOPE for ``len(config.classes)`` classes.

    ``forward(x, stages=None)`` returns a list (one entry per evaluated stage) of
    ``(belief, affinity)`` tensors shaped (B, C*9, H/8, W/8) and (B, C*16, H/8, W/8), class-major.
    """

    def __init__(self, config: DopeNetConfig | None = None):
        super().__init__()
        self.config = config or DopeNetConfig()
        w = self.config.width
        n_cls = len(self.config.classes)
        self.n_belief = n_cls * N_BELIEF
        self.n_affinity = n_cls * N_AFFINITY
        n_out = self.n_belief + self.n_affinity

        vgg = [64, 64, "M", 128, 128, "M", 256, 256, 256, 256, "M", 512, 512]
        layers: list[nn.Module] = []
        cin = self.config.in_channels
        for v in vgg:
            if v == "M":
                layers.append(nn.MaxPool2d(2, 2))
            else:
                layers += _conv(cin, _ch(v, w), 3)
                cin = _ch(v, w)
        layers += _conv(cin, _ch(256, w), 3)
        layers += _conv(_ch(256, w), _ch(128, w), 3)
        self.features = nn.Sequential(*layers)
        f = _ch(128, w)
        self.n_features = f

        stages = [nn.Sequential(*_conv(f, _ch(128, w), 3), *_conv(_ch(128, w), _ch(128, w), 3),
                                *_conv(_ch(128, w), _ch(128, w), 3), *_conv(_ch(128, w), _ch(512, w), 1),
                                *_conv(_ch(512, w), n_out, 1, relu=False))]
        for _ in range(1, self.config.stages):
            mods = _conv(f + n_out, _ch(128, w), 7)
            for _ in range(4):
                mods += _conv(_ch(128, w), _ch(128, w), 7)
            mods += _conv(_ch(128, w), _ch(128, w), 1)
            mods += _conv(_ch(128, w), n_out, 1, relu=False)
            stages.append(nn.Sequential(*mods))
        self.stages = nn.ModuleList(stages)
        self.refinement_format: torch.memory_format | None = None  # set by set_memory_order

    @property
    def classes(self) -> tuple:
        return tuple(self.config.classes)

    def forward(self, x: torch.Tensor, stages: int | None = None) -> list[tuple[torch.Tensor, torch.Tensor]]:
        n = _stage_count(self.config, stages)
        feats = self.features(x)
        outs = []
        prev = None
        feats_r = _in_order(feats, self.refinement_format) if n > 1 else feats
        for i in range(n):
            inp = feats if i == 0 else torch.cat([feats_r, _in_order(prev, self.refinement_format)], dim=1)
            prev = self.stages[i](inp)
            outs.append((prev[:, :self.n_belief], prev[:, self.n_belief:]))
        return outs

    def layer_count(self, stages: int | None = None) -> int:
        """Number of convolution layers evaluated for ``stages`` stages."""
        n = self.config.stages if stages is None else stages
        convs = sum(isinstance(m, nn.Conv2d) for m in self.features)
        for i in range(n):
            convs += sum(isinstance(m, nn.Conv2d) for m in self.stages[i])
        return convs


class FoldedDopeNet(nn.Module):
    """A trained :class:`DopeNet` rearranged for inference: the same maps, with about a fifth fewer
    multiply-adds (``FoldedDopeNet(net)``; ``net`` is left as it is, and the features are shared).

    Each stage from the second on starts with a 7x7 convolution of the features concatenated with the
    previous stage's maps, and those maps are a 1x1 convolution (no ReLU) of that stage's last hidden
    layer ``h``: ``maps = W h + b``. Convolutions compose, so the 7x7 convolution of the maps is the 7x7
    convolution of ``h`` with the kernel ``K W`` (``h`` has 32 channels at the shipped width, the maps
    150), plus the 7x7 convolution of the constant ``b`` over the image, which zero padding makes smaller
    near the borders (a one-channel convolution of an image of ones). The maps themselves are still
    computed, as every stage's output. The sums are reordered, so the maps differ from
    :class:`DopeNet`'s in the last float bits (about 2e-7 in belief).

    ``forward(x, stages=None)``, :attr:`config`, :attr:`classes` and :meth:`layer_count` are
    :class:`DopeNet`'s (the layer count is the source network's).
    """

    def __init__(self, net: DopeNet):
        super().__init__()
        self.config = net.config
        self.n_belief = net.n_belief
        self.n_affinity = net.n_affinity
        self.n_features = net.n_features
        self._layers = tuple(net.layer_count(s) for s in range(1, net.config.stages + 1))
        self.features = net.features
        f = net.n_features
        self.hidden = nn.ModuleList()  # per stage: the layers up to its last hidden layer h
        self.out = nn.ModuleList()  # per stage: its 1x1 output layer (h -> maps)
        self.on_features = nn.ModuleList()  # stages 2..S: the first 7x7 convolution's feature part
        self.on_hidden = nn.ModuleList()  # ... its part on the previous stage's h (K W, no bias)
        self.on_bias = nn.ModuleList()  # ... the previous maps' bias through it, over an image of ones
        for i, stage in enumerate(net.stages):
            layers = list(stage)
            self.out.append(layers[-1])
            if i == 0:
                self.hidden.append(nn.Sequential(*layers[:-1]))
                continue
            first, prev_out = layers[0], net.stages[i - 1][-1]
            with torch.no_grad():
                K = first.weight.double()
                W = prev_out.weight.double()[:, :, 0, 0]  # (maps, h)
                k, pad = first.kernel_size, first.padding
                conv_f = nn.Conv2d(f, first.out_channels, k, padding=pad)
                conv_f.weight.copy_(first.weight[:, :f])
                conv_f.bias.copy_(first.bias)
                conv_h = nn.Conv2d(W.shape[1], first.out_channels, k, padding=pad, bias=False)
                conv_h.weight.copy_(torch.einsum("ocyx,cj->ojyx", K[:, f:], W).float())
                conv_b = nn.Conv2d(1, first.out_channels, k, padding=pad, bias=False)
                conv_b.weight.copy_(torch.einsum("ocyx,c->oyx", K[:, f:], prev_out.bias.double())[:, None].float())
            self.on_features.append(conv_f)
            self.on_hidden.append(conv_h)
            self.on_bias.append(conv_b)
            self.hidden.append(nn.Sequential(*layers[1:-1]))  # the first layer's ReLU onwards
        self._bias_maps: dict = {}  # (stage, h, w, dtype, device, order) -> on_bias over an image of ones
        self.refinement_format: torch.memory_format | None = None  # set by set_memory_order
        self.eval()

    @property
    def classes(self) -> tuple:
        return tuple(self.config.classes)

    def layer_count(self, stages: int | None = None) -> int:
        return self._layers[(self.config.stages if stages is None else int(stages)) - 1]

    def forward(self, x: torch.Tensor, stages: int | None = None) -> list[tuple[torch.Tensor, torch.Tensor]]:
        n = _stage_count(self.config, stages)
        feats = self.features(x)
        h = self.hidden[0](feats)
        maps = self.out[0](h)
        outs = [(maps[:, :self.n_belief], maps[:, self.n_belief:])]
        ones = None
        fmt = self.refinement_format
        if n > 1 and fmt is not None:
            feats = _in_order(feats, fmt)
        for i in range(1, n):
            h = _in_order(h, fmt)  # the previous stage's last layer is a 1x1 convolution, in the first order
            key = (i, feats.shape[-2], feats.shape[-1], feats.dtype, feats.device, fmt)
            bias = self._bias_maps.get(key)
            if bias is None:  # the same for every image of a size: computed once
                if ones is None:
                    ones = torch.ones_like(feats[:1, :1])  # the image the previous maps' bias is convolved over
                with torch.no_grad():
                    bias = self._bias_maps[key] = self.on_bias[i - 1](ones)
            z = self.on_features[i - 1](feats) + self.on_hidden[i - 1](h) + bias
            h = self.hidden[i](z)
            maps = self.out[i](h)
            outs.append((maps[:, :self.n_belief], maps[:, self.n_belief:]))
        return outs


def set_memory_order(model: DopeNet | FoldedDopeNet, channels_last: bool, refinement_channels_last: bool):
    """Put ``model``'s weights in the memory order its convolutions run fastest in, in place.

    ``channels_last``: the features and the first stage (3x3 convolutions) in channels-last order, else
    the plain (contiguous) one; ``refinement_channels_last``: the same for the refinement stages' 7x7
    convolutions, whose input is converted to their order in the forward pass. The stages' 1x1
    convolutions stay in the first order: in the plain order PyTorch runs a single image's 1x1
    convolution as its own matrix product on one thread and through oneDNN on more, which differ in the
    last bits, so the maps would depend on the thread count; channels-last, they do not. The maps are the
    same in either order to the last float bits. Returns ``model``.
    """
    first = torch.channels_last if channels_last else torch.contiguous_format
    refine = torch.channels_last if refinement_channels_last else torch.contiguous_format
    model.to(memory_format=first)
    if isinstance(model, FoldedDopeNet):
        later = [*model.hidden[1:], *model.out[1:], *model.on_features, *model.on_hidden, *model.on_bias]
        model._bias_maps.clear()
    else:
        later = list(model.stages[1:])
    for m in later:
        m.to(memory_format=refine)
        for conv in m.modules():  # 1x1 convolutions stay in the first order (see above)
            if isinstance(conv, nn.Conv2d) and conv.kernel_size == (1, 1):
                conv.to(memory_format=first)
    model.refinement_format = None if refine == first else refine
    return model


def expand_stages(model: DopeNet, stages: int) -> DopeNet:
    """A network with ``stages`` stages whose extra stages start as copies of ``model``'s last stage.

    Stages 2..S share one shape (features + previous maps in, maps out), so a trained refinement stage
    can be repeated: training a short cascade and repeating its last stage is how the CPU budget buys
    a 6-stage network (the copies can then be fine-tuned).
    """
    n = model.config.stages
    if stages < n:
        raise ValueError(f"expand_stages: cannot shrink {n} stages to {stages}")
    if n < 2 and stages > n:
        raise ValueError("expand_stages: needs a trained refinement stage (a network of at least 2 stages)")
    cfg = DopeNetConfig(model.config.classes, model.config.width, stages, model.config.in_channels)
    out = DopeNet(cfg)
    state = dict(model.state_dict())
    for i in range(n, stages):
        for k, v in model.stages[n - 1].state_dict().items():
            state[f"stages.{i}.{k}"] = v.clone()
    out.load_state_dict(state)
    return out.train(model.training)


def split_class(maps: torch.Tensor, cls_index: int, per_class: int) -> torch.Tensor:
    """The channel group of one class from a class-major (B, C*per_class, H, W) tensor."""
    return maps[:, cls_index * per_class:(cls_index + 1) * per_class]


def save_weights(path, model: DopeNet, half: bool = True, extra: dict | None = None) -> None:
    """Plain state dict + config (loadable with ``torch.load(weights_only=True)``), written atomically."""
    from pathlib import Path

    path = Path(path)
    state = {k: (v.half() if half and v.is_floating_point() else v).contiguous().cpu()
             for k, v in model.state_dict().items()}
    blob = {"config": model.config.to_dict(), "state_dict": state, "extra": dict(extra or {})}
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        torch.save(blob, tmp)


class WeightsError(DopeSlamError, ValueError):
    """A weights file that is missing or is not a DOPE network's (its path and what was expected)."""


_EXPECTED = "a DOPE weights file (a dict with 'config' and 'state_dict', as dopeslam train writes)"


def read_weights(path) -> dict:
    """A weights file's contents (``config``, ``state_dict``, maybe ``extra``), read as tensors only:
    nothing in it runs. Raises :class:`WeightsError` for a missing file or one that is not a DOPE
    network's weights file."""
    expected = _EXPECTED
    try:
        with warnings.catch_warnings():  # torch's notes on a foreign file's pickle protocol: the error below says it
            warnings.simplefilter("ignore", UserWarning)
            blob = torch.load(str(path), map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise WeightsError(f"{path}: DOPE weights file not found") from None
    except IsADirectoryError:
        raise WeightsError(f"{path}: is a folder; expected {expected}") from None
    except Exception as exc:  # noqa: BLE001 - torch's unpickler raises many kinds for foreign bytes
        why = (str(exc).strip().splitlines() or [type(exc).__name__])[0].split(". ")[0][:120]
        raise WeightsError(f"{path}: unreadable ({why}); expected {expected}") from None
    if not isinstance(blob, dict) or not isinstance(blob.get("config"), dict) or "state_dict" not in blob:
        raise WeightsError(f"{path}: expected {expected}")
    return blob


def load_weights(path, device: str | torch.device = "cpu") -> tuple[DopeNet, dict]:
    """(model in eval mode, float32, on ``device``; the file's ``extra`` dict). Raises
    :class:`WeightsError` for a missing file or one that is not a DOPE network's weights (loaded as
    tensors only: nothing in it runs)."""
    blob = read_weights(path)
    try:
        model = DopeNet(DopeNetConfig.from_dict(blob["config"]))
        model.load_state_dict({k: v.float() for k, v in blob["state_dict"].items()})
    except (TypeError, ValueError, KeyError, RuntimeError, AttributeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise WeightsError(f"{path}: its 'config' and 'state_dict' do not make a DOPE network ({first[:200]})") from None
    model.eval().to(device)
    return model, dict(blob.get("extra", {}))
