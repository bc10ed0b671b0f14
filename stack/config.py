"""The stack's one configuration: a typed tree of every setting, read in one place.

Sections (every key with its default and meaning: ``docs/configuration.md``):

    odometry      KISS-ICP LiDAR odometry (:class:`stack.lidar_slam.LidarOdometryConfig`)
    detector      DOPE + FPR: input image, stages, FPR on/off, weights, thresholds, decoding, checks
    evidence      what a map object needs before it is published (:class:`stack.evidence.EvidenceConfig`)
    store         the object store: labelling policy, association gate, evidence gate on/off
    loop_closure  place recognition + verification + pose graph (:class:`stack.loops.closure.LoopClosureConfig`)
    components    other people's parts by import path, ``MODULE:CLASS`` (null: the bundled ones)

Where values come from, each layer over the one before:

    defaults  <  a TOML, YAML or JSON file  <  DOPESLAM_SECTION__KEY environment variables  <  --set SECTION.KEY=VALUE

An environment variable names the section and the key joined by a double underscore, upper or lower
case: ``DOPESLAM_DETECTOR__STAGES=3``, ``DOPESLAM_LOOP_CLOSURE__ENABLED=true``. ``--set`` takes
``section.key=value``; a few keys have a short name (:data:`ALIASES`: ``input``, ``stages``, ``fpr``,
``weights``, ``policy``, ``detector``, ``odometry``). Values given as text (environment, ``--set``)
are read as the key's type: ``3``, ``0.5``, ``true``/``false``, ``null`` (unset), a JSON list
``[[0.3, 0.6], [0.5, 0.8]]``. Unknown sections and keys are errors, as are values of the wrong type;
every error is a :class:`ConfigError` whose one-line message names where the value came from (the
file, the environment variable or ``--set``), the key and what was expected.

:func:`resolve_config` is the one reader. :func:`apply_sets` and :func:`expand_grid` change a config
by keys (for sweeps), :func:`dump_toml` / :func:`write_config` write the resolved config so a run can
be repeated with ``--config DIR/config.toml``.

Settings of the machine rather than of the stack (they change no output) are environment variables
read here too: ``DOPESLAM_TORCH_THREADS`` (:func:`torch_threads`).
"""
from __future__ import annotations

import itertools
import json
import math
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from stack.errors import DopeSlamError
from stack.evidence import EvidenceConfig
from stack.io import write_text
from stack.lidar_slam import LidarOdometryConfig
from stack.loops.closure import LoopClosureConfig
from stack.retire import RetireConfig

ENV_PREFIX = "DOPESLAM_"
ENV_SEPARATOR = "__"  # DOPESLAM_<SECTION>__<KEY>
ENV_TORCH_THREADS = "DOPESLAM_TORCH_THREADS"
FILE_SUFFIXES = (".toml", ".yaml", ".yml", ".json")


class ConfigError(DopeSlamError, ValueError):
    """A setting that cannot be used; the message (one line) names its source, the key and what was expected."""


class DetectorConfig(BaseModel):
    """DOPE + FPR (:class:`stack.dope_fpr.DopeDetector`); the defaults are the shipped detector's."""

    model_config = ConfigDict(extra="forbid")

    input: Literal["rgb", "depth"] = Field("rgb", description="network input: colour image, or depth (works in darkness)")
    stages: int = Field(6, ge=1, le=6, description="DOPE stages run (1-6)")
    fpr: bool = Field(True, description="false-positive reduction on the belief maps (off: every detection passes)")
    weights: str | None = Field(None, description="weights file (null: the shipped ones for the input)")
    thresholds: str | None = Field(None, description="FPR thresholds JSON (null: the file beside the weights)")
    every: int = Field(1, ge=1, description="run the detector on every n-th image only")
    keyframe_m: float = Field(0.0, ge=0, description="run the detector only on images the robot has travelled this far "
                              "(m, by wheel odometry) since the last detected one, or turned keyframe_deg (0 and 0: "
                              "every image)")
    keyframe_deg: float = Field(0.0, ge=0, description="... or turned this much (deg) since it")
    keyframe_max_s: float = Field(1.0, ge=0, description="... or taken this long (s) after it, so a still robot still "
                                  "looks (0: never)")
    input_size: tuple[int, int] = Field((320, 240), description="network input size, width and height (px)")
    peak_threshold: float = Field(0.3, ge=0, description="belief-map peaks below this are no key point")
    angle_threshold: float = Field(0.5, ge=0, description="a corner joins the centroid its affinity points at within this")
    min_corners: int = Field(4, ge=0, le=8, description="fewer associated corners: no detection")
    max_reproj_px: float = Field(12.0, gt=0, description="PnP reprojection error above this: no detection")
    depth_refine: bool = Field(True, description="slide each pose along its ray to fit the aligned depth image")
    depth_check: bool = Field(True, description="FPR also fails a cuboid the depth image does not support")
    colour_check: bool = Field(True, description="FPR also fails a detection whose colours fit another class (lit RGB)")
    colour_model: str | None = Field(None, description="colour-name models JSON (null: the shipped one)")
    colour_margin: float = Field(0.0, ge=0, description="another class must fit better by more than this")
    min_colour_brightness: float = Field(20.0, ge=0, description="darker silhouettes (mean 0-255) skip the colour check")
    window_min_pixels: int = Field(40, ge=0, description="depth input: windows with fewer pixels above the floor are skipped")
    shape_check: bool = Field(True, description="depth input: FPR also fails a detection whose object another class's "
                              "cuboid explains clearly better (its outline in the depth image)")
    shape_min_residual_m: float = Field(0.006, ge=0, description="shape check: the detected class's depth residual (m) "
                                        "must exceed this to fail")
    shape_ratio: float = Field(1.5, ge=1, description="shape check: ... and this many times the best other class's")
    depth_windows: list[tuple[float, float]] | None = Field(
        None, description="depth input: [[near, far], ...] m (null: sliding 0.3-1.8 m, 0.3 m wide, 0.1 m overlap)")
    channels_last: bool = Field(True, description="run the network in channels-last memory order (about 15 % faster "
                                "on a CPU; the maps differ in the last float bits)")
    refinement_order: Literal["auto", "channels_last", "contiguous"] = Field(
        "auto", description="the memory order of the refinement stages' 7x7 convolutions: auto is contiguous on "
        "an AVX2 CPU (about 8 % less network time there), else as channels_last; the maps differ in the last "
        "float bits")
    fold_stages: bool = Field(True, description="run each refinement stage's first convolution on the previous "
                              "stage's last hidden layer instead of its maps (the same maps to the last float bits, "
                              "about a fifth fewer multiply-adds)")
    precision: Literal["fp32", "bf16", "int8"] = Field(
        "fp32", description="the network's arithmetic: bf16 halves its time on a CPU with native bfloat16 "
        "(AVX512-BF16, AMX; elsewhere it runs fp32); int8 runs its convolutions in 8-bit integers on any x86 CPU, "
        "at the calibration beside the weights (NAME_int8.json); neither's maps are always fp32's (docs/speed.md)")

    @field_validator("precision")
    @classmethod
    def _int8_runs_folded(cls, value, info):
        if value == "int8" and info.data.get("fold_stages") is False:
            raise ValueError("int8 runs the folded network only (detector.fold_stages = true)")
        return value

    def keyframes(self):
        """The :class:`stack.keyframes.KeyframeSettings` of ``keyframe_*`` (None while off)."""
        from stack.keyframes import KeyframeSettings

        k = KeyframeSettings(self.keyframe_m, self.keyframe_deg, self.keyframe_max_s)
        return k if k.enabled else None

    def dope_kwargs(self) -> dict:
        """Keyword arguments of :class:`stack.dope_fpr.DopeDetector` (``dims`` and ``threads`` aside)."""
        return {"weights": self.weights, "input": self.input, "stages": self.stages, "fpr": self.fpr,
                "thresholds": self.thresholds, "input_size": tuple(self.input_size),
                "peak_threshold": self.peak_threshold, "angle_threshold": self.angle_threshold,
                "min_corners": self.min_corners, "max_reproj_px": self.max_reproj_px,
                "depth_windows": [tuple(w) for w in self.depth_windows] if self.depth_windows else None,
                "depth_refine": self.depth_refine, "depth_check": self.depth_check,
                "colour_check": self.colour_check, "colour": self.colour_model, "colour_margin": self.colour_margin,
                "min_colour_brightness": self.min_colour_brightness, "window_min_pixels": self.window_min_pixels,
                "channels_last": self.channels_last, "refinement_order": self.refinement_order,
                "fold_stages": self.fold_stages, "precision": self.precision,
                "shape_check": self.shape_check, "shape_min_residual_m": self.shape_min_residual_m,
                "shape_ratio": self.shape_ratio}


class StoreConfig(BaseModel):
    """The persistent object store (:class:`stack.object_store.ObjectStore`)."""

    model_config = ConfigDict(extra="forbid")

    policy: str = Field("robust-mean", description="labelling policy: a registered name (last, last-fpr, "
                        "best-score, robust-mean, ...) or MODULE:FUNCTION")
    gate_m: float = Field(0.5, gt=0, description="a detection this near a map object of its class joins it")
    evidence_gate: bool = Field(True, description="publish only on the [evidence] settings (off: every object with "
                                "a label is published)")


class LoopClosureSection(LoopClosureConfig):
    """Loop closure: off by default; the rest are :class:`stack.loops.closure.LoopClosureConfig`'s settings."""

    enabled: bool = Field(False, description="close loops; labels are placed again on the corrected trajectory")
    vocabulary: str | None = Field(None, description="place-recognition vocabulary .npz (null: the bundled one)")

    def closure_config(self) -> LoopClosureConfig:
        return LoopClosureConfig(**self.model_dump(exclude={"enabled", "vocabulary"}))


class RetireSection(RetireConfig):
    """Retiring labels whose place the depth images show empty; the rest are :class:`stack.retire.RetireConfig`'s settings."""

    enabled: bool = Field(True, description="retire labels whose place is seen empty (off: a label stays until edited)")

    def settings(self) -> RetireConfig | None:
        """What ``DopeSlam(retire=...)`` takes: the settings, or None when retiring is off."""
        return RetireConfig(**self.model_dump(exclude={"enabled"})) if self.enabled else None


class ComponentsConfig(BaseModel):
    """Other people's parts, by import path; null: the bundled one (``stack.interfaces`` Protocols)."""

    model_config = ConfigDict(extra="forbid")

    detector: str | None = Field(None, description="MODULE:CLASS of a detector (constructed with no arguments, "
                                 "detect(frame) -> list[Detection]); replaces [detector]'s DOPE")
    odometry: str | None = Field(None, description="the odometry: kiss-icp (null: the same, with [odometry]'s "
                                 "settings), wheel, an installed entry point (group dopeslam.odometry), or "
                                 "MODULE:CLASS called with the LiDAR's mounting T_base_lidar (stack.interfaces.Odometry)")


class StackConfig(BaseModel):
    """Every setting of the stack. ``StackConfig()`` is the stack as shipped."""

    model_config = ConfigDict(extra="forbid")

    #: short names accepted by :func:`apply_sets` (and so by ``--set`` and ``--grid``)
    ALIASES: ClassVar[dict[str, str]] = {
        "input": "detector.input", "stages": "detector.stages", "fpr": "detector.fpr",
        "weights": "detector.weights", "policy": "store.policy",
        "detector": "components.detector", "odometry": "components.odometry",
    }

    odometry: LidarOdometryConfig = Field(default_factory=LidarOdometryConfig)
    detector: DetectorConfig = Field(default_factory=DetectorConfig)
    evidence: EvidenceConfig = Field(default_factory=EvidenceConfig)
    store: StoreConfig = Field(default_factory=StoreConfig)
    loop_closure: LoopClosureSection = Field(default_factory=LoopClosureSection)
    retire: RetireSection = Field(default_factory=RetireSection)
    components: ComponentsConfig = Field(default_factory=ComponentsConfig)

    def evidence_or_none(self) -> EvidenceConfig | None:
        """The evidence settings the object store takes (None: the gate is off)."""
        return self.evidence if self.store.evidence_gate else None


# ---------------------------------------------------------------------------------------------
# reading


def _section_keys(model: type[BaseModel], loc: Sequence) -> list[str]:
    """The keys allowed where ``loc`` points (the parent of an unknown key)."""
    cls = model
    for part in loc:
        field = cls.model_fields.get(str(part))
        ann = getattr(field, "annotation", None) if field else None
        if not (isinstance(ann, type) and issubclass(ann, BaseModel)):
            return []
        cls = ann
    return sorted(cls.model_fields)


def _describe(exc: ValidationError, model: type[BaseModel], source: str) -> ConfigError:
    e = exc.errors()[0]
    loc = [str(p) for p in e["loc"]]
    key = ".".join(loc)
    if e["type"] == "extra_forbidden":
        if len(loc) == 1:
            return ConfigError(f"{source}: unknown section '{key}'; sections {_section_keys(model, [])}")
        return ConfigError(f"{source}: unknown key '{key}'; section '{'.'.join(loc[:-1])}' has "
                           f"{_section_keys(model, loc[:-1])}")
    if e["type"] in ("model_type", "dict_type") and len(loc) == 1:
        return ConfigError(f"{source}: key '{key}': expected a section of keys, got {e['input']!r}")
    more = f" (and {len(exc.errors()) - 1} more)" if len(exc.errors()) > 1 else ""
    return ConfigError(f"{source}: key '{key}': {e['msg']}, got {e['input']!r}{more}")


def _validate(model: type[BaseModel], data: dict, source: str):
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise _describe(exc, model, source) from None


def _merge(base: dict, over: Mapping) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), dict) else v
    return out


def read_file(path: str | Path) -> dict:
    """A config file's contents as a mapping of sections (TOML, YAML or JSON, by the file's suffix)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in FILE_SUFFIXES:
        raise ConfigError(f"{path}: expected a config file ending in {', '.join(FILE_SUFFIXES)}")
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read ({exc})") from None
    try:
        if suffix == ".toml":
            try:
                import tomllib
            except ModuleNotFoundError:  # Python < 3.11
                import tomli as tomllib

            data = tomllib.loads(text)
        elif suffix == ".json":
            data = json.loads(text)
        else:
            import yaml

            data = yaml.safe_load(text)
    except Exception as exc:  # tomllib, json and yaml each raise their own; all mean "not this format"
        kind = {".toml": "TOML", ".json": "JSON"}.get(suffix, "YAML")
        raise ConfigError(f"{path}: not valid {kind}: {str(exc).splitlines()[0]}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected sections of key = value, got a {type(data).__name__}")
    return data


def parse_value(text: str):
    """A value given as text: ``null``/``none`` is None, ``[...]``/``{...}`` is JSON, anything else stays
    text for the key's type to read (``3``, ``0.5``, ``true``, ``rgb``)."""
    if not isinstance(text, str):
        return text
    s = text.strip()
    if s.lower() in ("null", "none", "~"):
        return None
    if s[:1] in "[{":
        try:
            return json.loads(s)
        except json.JSONDecodeError as exc:
            raise ValueError(f"not a JSON list or table ({exc.msg})") from None
    return s


def parse_assignment(text: str, what: str = "--set") -> tuple[str, str]:
    """``'section.key=value'`` -> ``('section.key', 'value')``."""
    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise ConfigError(f"{what} {text!r}: expected SECTION.KEY=VALUE, e.g. detector.stages=3")
    return key.strip(), value.strip()


def env_sets(environ: Mapping[str, str] | None = None) -> dict[str, tuple[str, str]]:
    """``{'section.key': (value, VARIABLE)}`` of every ``DOPESLAM_SECTION__KEY`` variable, in name order."""
    environ = os.environ if environ is None else environ
    out = {}
    for name in sorted(environ):
        if not name.upper().startswith(ENV_PREFIX) or ENV_SEPARATOR not in name[len(ENV_PREFIX):]:
            continue  # DOPESLAM_TORCH_THREADS, DOPESLAM_CACHE, ...: machine settings, not the config
        section, _, key = name[len(ENV_PREFIX):].partition(ENV_SEPARATOR)
        out[f"{section.lower()}.{key.lower().replace(ENV_SEPARATOR, '.')}"] = (environ[name], name)
    return out


def _canonical_key(model: type[BaseModel], key: str, source: str) -> list[str]:
    aliases = getattr(model, "ALIASES", {})
    key = aliases.get(key, key)
    parts = key.split(".")
    if len(parts) < 2 or not all(parts):
        short = f" or one of {sorted(aliases)}" if aliases else ""
        raise ConfigError(f"{source}: key {key!r}: expected SECTION.KEY{short}; sections {sorted(model.model_fields)}")
    return parts


def apply_sets(config: BaseModel, sets: Mapping[str, Any], source: str = "--set"):
    """A copy of ``config`` with ``{'section.key': value}`` applied, one at a time (a short name from
    the model's ``ALIASES`` may stand for ``section.key``). Values may be text (read as the key's
    type, see :func:`parse_value`) or already typed. Raises :class:`ConfigError` naming ``source``."""
    model = type(config)
    data = config.model_dump()
    for key, value in sets.items():
        where = source(key) if callable(source) else f"{source} {key}={value}"
        parts = _canonical_key(model, key, where)
        try:
            value = parse_value(value)
        except ValueError as exc:
            raise ConfigError(f"{where}: key '{'.'.join(parts)}': {exc}") from None
        node = data
        for i, p in enumerate(parts[:-1]):
            node = node.setdefault(p, {})  # an unknown section: validation names it
            if not isinstance(node, dict):
                raise ConfigError(f"{where}: key '{'.'.join(parts[:i + 1])}' is a value, not a section")
        node[parts[-1]] = value
        config = _validate(model, data, where)
        data = config.model_dump()
    return config


def changed_keys(config: BaseModel) -> dict[str, Any]:
    """``{'section.key': value}`` of every setting of ``config`` that differs from its model's default."""
    have, want = config.model_dump(), type(config)().model_dump()
    return {f"{section}.{key}": value for section, table in have.items() if isinstance(table, dict)
            for key, value in table.items() if value != want[section].get(key)}


def resolve_config(file: str | Path | None = None, sets: Mapping[str, Any] | Sequence[str] | None = None,
                   environ: Mapping[str, str] | None = None, model: type[BaseModel] = StackConfig):
    """THE reader: defaults < ``file`` < ``DOPESLAM_SECTION__KEY`` variables of ``environ`` (None:
    ``os.environ``) < ``sets`` (``{'section.key': value}`` or ``['section.key=value', ...]``, applied in
    order). ``model``: :class:`StackConfig` or a harness's extension of it. Raises :class:`ConfigError`."""
    config = model()
    if file is not None:
        config = _validate(model, _merge(config.model_dump(), read_file(file)), str(file))
    env = env_sets(environ)
    if env:
        config = apply_sets(config, {k: v for k, (v, _) in env.items()},
                            source=lambda k: f"environment variable {env[k][1]}")
    if sets:
        if not isinstance(sets, Mapping):
            pairs = [parse_assignment(s) for s in sets]
            for k, v in pairs:
                config = apply_sets(config, {k: v})
        else:
            config = apply_sets(config, sets)
    return config


def parse_grid(text: str) -> tuple[str, list[str]]:
    """``'detector.stages=1,3,6'`` -> ``('detector.stages', ['1', '3', '6'])``; commas inside brackets
    belong to a value (``detector.input_size=[320,240],[640,480]``)."""
    key, values = parse_assignment(text, "--grid")
    out, depth, cur = [], 0, ""
    for ch in values:
        depth += {"[": 1, "{": 1, "]": -1, "}": -1}.get(ch, 0)
        if ch == "," and depth == 0:
            out.append(cur.strip())
            cur = ""
        else:
            cur += ch
    out.append(cur.strip())
    if not all(out):
        raise ConfigError(f"--grid {text!r}: expected KEY=V1,V2,... with no empty value")
    return key, out


def expand_grid(config: BaseModel, grid: Mapping[str, Sequence[Any]]) -> list[tuple[dict[str, Any], BaseModel]]:
    """Every combination of the ``grid``'s values (``{'detector.stages': ['1', '6'], ...}``), in order,
    as ``(the combination's {key: value}, the config with it applied)``; each is validated."""
    keys = list(grid)
    points = []
    for combo in itertools.product(*(grid[k] for k in keys)):
        sets = dict(zip(keys, combo))
        points.append((sets, apply_sets(config, sets, source="--grid")))
    return points


# ---------------------------------------------------------------------------------------------
# writing


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string is a TOML basic string
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} as TOML")


def _toml_table(name: str, table: dict, lines: list[str]) -> None:
    lines.append(f"[{name}]")
    subtables = {k: v for k, v in table.items() if isinstance(v, dict)}
    for k, v in table.items():
        if not isinstance(v, dict):
            lines.append(f"# {k} = null" if v is None else f"{k} = {_toml_value(v)}")
    lines.append("")
    for k, v in subtables.items():
        _toml_table(f"{name}.{k}", v, lines)


def dump_toml(config: BaseModel) -> str:
    """The config as TOML, one ``[section]`` per section, every key (an unset one, null, as a comment:
    the key's default is null, so reading the file back gives the same config)."""
    data = config.model_dump()
    lines = [f"{k} = {_toml_value(v)}" for k, v in data.items() if not isinstance(v, dict) and v is not None]
    lines += [""] if lines else []
    for name, value in data.items():
        if isinstance(value, dict):
            _toml_table(name, value, lines)
    return "\n".join(lines)


def write_config(config: BaseModel, path: str | Path) -> Path:
    """Write ``config`` (TOML for ``.toml``, else JSON) atomically: a temporary file, then a rename."""
    path = Path(path)
    text = dump_toml(config) if path.suffix.lower() == ".toml" else json.dumps(config.model_dump(), indent=1) + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text(path, text)
    return path


# ---------------------------------------------------------------------------------------------
# the reference (docs/configuration.md is generated from it)


def _default_text(field) -> str:
    if field.default_factory is not None:
        return ""
    v = field.default
    if v is None:
        return "null"
    return _toml_value(list(v) if isinstance(v, tuple) else v)


def _reference(model: type[BaseModel], name: str, lines: list[str]) -> None:
    doc = re.sub(r":\w+:`~?([^`]+)`", r"`\1`", (model.__doc__ or "").strip().split("\n\n")[0].replace("\n", " ")).replace("``", "`")
    lines += [f"### `[{name}]`", "", doc, "", "| key | default | meaning |", "|---|---|---|"]
    nested = []
    for key, field in model.model_fields.items():
        ann = field.annotation
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            nested.append((key, ann))
            lines.append(f"| `{key}` | | the section `[{name}.{key}]` below |")
            continue
        meaning = (field.description or "").replace("|", "\\|")
        bounds = [f"{op} {getattr(m, attr)}" for m in field.metadata
                  for attr, op in (("ge", ">="), ("gt", ">"), ("le", "<="), ("lt", "<")) if hasattr(m, attr)]
        if getattr(ann, "__origin__", None) is Literal:
            bounds.append(" or ".join(f'"{a}"' for a in ann.__args__))
        allowed = f" ({', '.join(bounds)})" if bounds else ""
        lines.append(f"| `{key}` | `{_default_text(field)}` | {meaning}{allowed} |")
    lines.append("")
    for key, ann in nested:
        _reference(ann, f"{name}.{key}", lines)


def reference_markdown(model: type[BaseModel] = StackConfig) -> str:
    """Every section and key of ``model`` with its default and meaning, as Markdown tables."""
    lines: list[str] = []
    for name, field in model.model_fields.items():
        _reference(field.annotation, name, lines)
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# machine settings (environment only; they change no output)


def torch_threads(environ: Mapping[str, str] | None = None) -> int | None:
    """``DOPESLAM_TORCH_THREADS``: torch threads for the detector (unset or empty: torch's default).
    One thread is often faster than two on cores shared with other busy processes."""
    environ = os.environ if environ is None else environ
    raw = environ.get(ENV_TORCH_THREADS, "").strip()
    if not raw:
        return None
    try:
        n = int(raw)
    except ValueError:
        n = -1
    if n < 1:
        raise ConfigError(f"environment variable {ENV_TORCH_THREADS}: expected an integer >= 1, got {raw!r}")
    return n
