"""The DOPE network in 8-bit integer arithmetic (``precision = "int8"``), for CPUs without bfloat16.

Post-training static quantisation (PyTorch's FX graph mode, its ``x86`` engine): the folded network's
(:class:`stack.dope.net.FoldedDopeNet`) convolution blocks run in int8 with per-channel weight scales;
the 1x1 output layers, which write the belief and affinity maps, stay in float32. Each block takes and
gives float32, so the network's Python forward (any stage count) is unchanged.

The activations' scales come from a calibration file beside the weights (``dope_rgb_int8.json`` for
``dope_rgb.pt``), written by ``dopeslam calibrate-int8`` from datagen shards: plain numbers, so loading it
runs nothing. The same weights and calibration give the same network, bit for bit, on a given CPU.
"""
from __future__ import annotations

import itertools
import json
import math
import warnings
from pathlib import Path

import torch
from torch import nn

from stack.errors import DopeSlamError
from stack.io import atomic_path

ENGINE = "x86"
FORMAT = "dopeslam-int8-calibration"
VERSION = 1


class Int8Error(DopeSlamError, ValueError):
    """An int8 calibration file that is missing, unreadable or not for these weights (its path, what was expected)."""


def calibration_path(weights_path) -> Path:
    """Where the int8 calibration of ``weights_path`` lies: ``NAME_int8.json`` beside ``NAME.pt``."""
    p = Path(weights_path)
    return p.with_name(f"{p.stem}_int8.json")


def available() -> bool:
    """Whether this PyTorch build has the quantised CPU kernels int8 needs."""
    return ENGINE in torch.backends.quantized.supported_engines


def _blocks(net) -> dict[str, nn.Module]:
    """The folded network's blocks that run in int8, by name (the output layers stay float)."""
    out = {"features": net.features}
    for group in ("hidden", "on_features", "on_hidden"):
        for i, m in enumerate(getattr(net, group)):
            out[f"{group}.{i}"] = m
    return out


def _put(net, name: str, module: nn.Module) -> None:
    if name == "features":
        net.features = module
    else:
        group, i = name.split(".")
        getattr(net, group)[int(i)] = module


def _prepare(net, example: torch.Tensor) -> dict[str, nn.Module]:
    """Each block prepared for quantisation (observers in place), swapped into ``net``."""
    from torch.ao.quantization import get_default_qconfig_mapping
    from torch.ao.quantization.quantize_fx import prepare_fx

    blocks = _blocks(net)
    inputs: dict[str, torch.Tensor] = {}

    def grab(name):
        def hook(module, args, output):
            inputs.setdefault(name, args[0][:1].detach().clone())
        return hook

    hooks = [m.register_forward_hook(grab(name)) for name, m in blocks.items()]
    try:
        with torch.inference_mode():
            net(example[:1].float().contiguous())
    finally:
        for h in hooks:
            h.remove()
    mapping = get_default_qconfig_mapping(ENGINE)
    prepared = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # FX quantisation's deprecation notices
        for name, m in blocks.items():
            prepared[name] = prepare_fx(m, mapping, example_inputs=(inputs[name],))
            _put(net, name, prepared[name])
    return prepared


def _observers(block: nn.Module) -> dict[str, nn.Module]:
    """A prepared block's activation observers (per tensor); the weights' per-channel ones are left out:
    they take their scales from the weights themselves."""
    return {n: m for n, m in block.named_children() if n.startswith("activation_post_process")
            and m.qscheme in (torch.per_tensor_affine, torch.per_tensor_symmetric)}


def calibrate(net, batches, meta: dict | None = None) -> dict:
    """The activation scales of ``net`` (a FoldedDopeNet in float32, left as it is) from its inputs
    ``batches`` (an iterable of (N, 3, h, w) float32 tensors, as the detector feeds the network), as a
    JSON-ready dict for :func:`save` and :func:`quantize`."""
    import copy

    batches = iter(batches)
    first = next(batches, None)
    if first is None:
        raise Int8Error("int8 calibration: no network inputs to calibrate on")
    net = copy.deepcopy(net).float().eval()
    torch.backends.quantized.engine = ENGINE
    prepared = _prepare(net, first)
    seen = 0
    with torch.inference_mode():
        for x in itertools.chain([first], batches):
            net(x.float().contiguous())
            seen += len(x)
    blocks = {}
    for name, block in prepared.items():
        entry = {}
        for obs_name, obs in _observers(block).items():
            scale, zero_point = obs.calculate_qparams()
            entry[obs_name] = {"scale": float(scale.reshape(-1)[0]), "zero_point": int(zero_point.reshape(-1)[0]),
                               "quant_min": int(obs.quant_min), "quant_max": int(obs.quant_max)}
        blocks[name] = entry
    return {"format": FORMAT, "version": VERSION, "engine": ENGINE, "torch": torch.__version__.split("+")[0],
            "inputs": seen, "meta": dict(meta or {}), "blocks": blocks}


def save(path, calibration: dict) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        Path(tmp).write_text(json.dumps(calibration, indent=1, sort_keys=True) + "\n")


def load(path) -> dict:
    """A calibration file's content, checked for its shape; anything else: :class:`Int8Error`."""
    path = Path(path)
    expected = f"an int8 calibration ({FORMAT} JSON, as dopeslam calibrate-int8 writes)"
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise Int8Error(f"{path}: no such file; expected {expected} (run dopeslam calibrate-int8)") from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise Int8Error(f"{path}: unreadable ({type(exc).__name__}); expected {expected}") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT or not isinstance(data.get("blocks"), dict):
        raise Int8Error(f"{path}: expected {expected}")
    meta = data.setdefault("meta", {})
    if not isinstance(meta, dict) or not isinstance(meta.get("weights_sha256", ""), str):
        raise Int8Error(f"{path}: meta: expected an object whose weights_sha256 (if any) is a string")
    for name, block in data["blocks"].items():
        if not isinstance(block, dict):
            raise Int8Error(f"{path}: blocks.{name}: expected an object of observers")
        for obs, q in block.items():
            ok = isinstance(q, dict) and all(isinstance(q.get(k), (int, float)) and not isinstance(q.get(k), bool)
                                             for k in ("scale", "zero_point", "quant_min", "quant_max"))
            if not ok or not (math.isfinite(q["scale"]) and q["scale"] > 0) \
                    or not q["quant_min"] <= q["zero_point"] <= q["quant_max"]:
                raise Int8Error(f"{path}: blocks.{name}.{obs}: expected scale > 0 and quant_min <= zero_point "
                                f"<= quant_max")
    return data


def quantize(net, calibration: dict, example: torch.Tensor, source="the int8 calibration") -> nn.Module:
    """``net`` (a FoldedDopeNet in float32) with its blocks converted to int8 at ``calibration``'s scales,
    in place; ``example`` is one network input of the size it will run at (its content does not matter).
    A calibration made for another network: :class:`Int8Error` naming ``source``."""
    from torch.ao.quantization.observer import FixedQParamsObserver
    from torch.ao.quantization.quantize_fx import convert_fx

    torch.backends.quantized.engine = ENGINE
    net.float().eval()
    prepared = _prepare(net, example)
    blocks = calibration["blocks"]
    if set(blocks) != set(prepared):
        raise Int8Error(f"{source}: its blocks ({len(blocks)}) are not this network's ({len(prepared)}): "
                        "calibrated for other weights")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name, block in prepared.items():
            observers = _observers(block)
            if set(observers) != set(blocks[name]):
                raise Int8Error(f"{source}: blocks.{name}: its observers are not this network's "
                                "(other weights, or another PyTorch version: run dopeslam calibrate-int8)")
            for obs_name, obs in observers.items():
                q = blocks[name][obs_name]
                setattr(block, obs_name, FixedQParamsObserver(
                    scale=float(q["scale"]), zero_point=int(q["zero_point"]), dtype=obs.dtype, qscheme=obs.qscheme,
                    quant_min=int(q["quant_min"]), quant_max=int(q["quant_max"])))
        with torch.inference_mode():
            net(example[:1].float().contiguous())  # the weights' observers see the weights
        for name, block in prepared.items():
            _put(net, name, convert_fx(block))
    return net
