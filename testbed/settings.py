"""The harness's settings: the run-level keys beside the stack's config, and the environment.

:class:`RunConfig` is :class:`stack.config.StackConfig` with one more section, ``[run]``: what a
simulated episode is (scenario, seed, light, duration). Commands that simulate resolve it with
:func:`stack.config.resolve_config` (``model=RunConfig``); ``dopeslam replay`` reads the same files
and ignores ``[run]``. Short names for ``--set``/``--grid``: the stack's (``input``, ``stages``,
``fpr``, ...) and ``scenario``, ``seed``, ``light``, ``duration``.

Environment variables of the machine (they change where things go or how fast, not what comes
out) are read here and nowhere else in the harness (the simulator, which imports no harness code,
reads its two itself):

    DOPESLAM_CACHE          root of the caches (default ~/.cache/dopeslam): perception/, vocabulary/,
                            topomap_streams/; the simulator keeps its textures in assets/ under it
    DOPESLAM_DETECTOR_PROCESS  0: where testbed.run runs the DOPE detector ahead, and where replay
                            reads and detects the images beside the odometry, in a thread instead
                            of a child process (read by detection_process_wanted); 1: one child
                            process, 2: two, images in turn (unset: two where the detector runs on
                            every image, in testbed.run only from 150 images on, else one; read by
                            detector_processes_setting, for replay and for testbed.run)
    DOPESLAM_RENDER_WORKER  1: render camera images in a second process (read by sim.episode.Episode;
                            unset: on where testbed.run runs the detector ahead of an episode of at
                            least 150 images, else off; testbed.matrix sets 0 for cells side by side)
    DOPESLAM_TORCH_THREADS  torch threads of the detector (read by stack.config.torch_threads;
                            unset: 1 where testbed.run runs the detector ahead, and in replay's
                            detector process for colour input or in each of two, else torch's)

Configuration keys come from ``DOPESLAM_SECTION__KEY`` variables (a double underscore), see
:mod:`stack.config`.
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field

from stack.config import StackConfig

ENV_CACHE = "DOPESLAM_CACHE"


class RunSection(BaseModel):
    """A simulated episode; null: the scenario's own."""

    model_config = ConfigDict(extra="forbid")

    scenario: str | None = Field(None, description="bundled scenario name or TOML path (null: the default scenario)")
    seed: int | None = Field(None, ge=0, description="drives everything random (null: the scenario's seed)")
    light: float | None = Field(None, ge=0, le=1, description="light level 0-1 for the whole episode (null: the scenario's)")
    duration: float | None = Field(None, gt=0, description="seconds simulated (null: the scenario's)")
    profile: Literal["full", "fast"] = Field(
        "full", description="full: every sensor at the scenario's rates; fast (for large sweeps): the camera, and so "
                            "DOPE, at half the scenario's camera_rate and no segmentation image rendered, so the "
                            "per-image recall is not scored (what it costs: docs/speed.md)")
    lidar: Literal["points", "packets"] | None = Field(
        None, description="points: the Velodyne's sweeps as float points; packets: it publishes VLP-32C data packets "
                          "(ranges in 4 mm steps, 0.01 deg block azimuths) and each sweep is their decoding, as a "
                          "real one's (what it costs: docs/speed.md); null: the scenario's [sensors] lidar_packets")


class RunConfig(StackConfig):
    """The stack's config and the episode it runs in."""

    ALIASES: ClassVar[dict[str, str]] = {**StackConfig.ALIASES, "scenario": "run.scenario", "seed": "run.seed",
                                         "light": "run.light", "duration": "run.duration",
                                         "profile": "run.profile", "lidar": "run.lidar"}

    run: RunSection = Field(default_factory=RunSection)

    def stack(self) -> StackConfig:
        """The stack's part (every section but ``[run]``)."""
        return StackConfig(**{k: getattr(self, k) for k in StackConfig.model_fields})


FAST_CAMERA_FACTOR = 0.5  # the fast profile's camera rate, as a fraction of the scenario's


def profile_sensors(profile: str, camera_rate: float, needs_segmentation: bool) -> tuple[float, bool]:
    """(camera rate in Hz, whether to render the segmentation image) of a run profile for a scenario
    whose camera runs at ``camera_rate``; ``needs_segmentation``: something besides the per-image
    recall reads it (people walking through, a recorder, a ground-truth detector)."""
    if profile == "fast":
        return camera_rate * FAST_CAMERA_FACTOR, needs_segmentation
    return camera_rate, True


def detection_process_wanted(environ: Mapping[str, str] | None = None) -> bool:
    """``DOPESLAM_DETECTOR_PROCESS``: ``0`` runs the DOPE detector that ``testbed.run`` runs ahead of
    the pipeline, and replay's image reading and detection, in a thread; anything else or unset, in a
    child process (:mod:`testbed.detection_process`, :mod:`testbed.replay_detection`)."""
    environ = os.environ if environ is None else environ
    return environ.get("DOPESLAM_DETECTOR_PROCESS", "").strip() != "0"


def odometry_process_wanted(environ: Mapping[str, str] | None = None) -> bool | None:
    """``DOPESLAM_ODOMETRY_PROCESS``: ``0`` keeps the KISS-ICP that ``testbed.run`` runs beside its
    detector ahead in the command's own process; ``1``, a child process wherever it may
    (:mod:`testbed.odometry_process`); unset or anything else, None: the run chooses. The same bytes
    either way."""
    environ = os.environ if environ is None else environ
    value = environ.get("DOPESLAM_ODOMETRY_PROCESS", "").strip()
    return {"0": False, "1": True}.get(value)


def detector_processes_setting(environ: Mapping[str, str] | None = None) -> int | None:
    """``DOPESLAM_DETECTOR_PROCESS`` for replay's detector side and ``testbed.run``'s detector ahead:
    ``1`` or ``2`` processes, or None (unset or anything else: the command chooses; ``0``, a thread,
    is :func:`detection_process_wanted`'s)."""
    environ = os.environ if environ is None else environ
    value = environ.get("DOPESLAM_DETECTOR_PROCESS", "").strip()
    return int(value) if value in ("1", "2") else None


def cache_dir(name: str, environ: Mapping[str, str] | None = None, create: bool = True) -> Path:
    """``$DOPESLAM_CACHE/NAME`` (default ``~/.cache/dopeslam/NAME``), created unless ``create=False``."""
    environ = os.environ if environ is None else environ
    root = environ.get(ENV_CACHE) or Path.home() / ".cache" / "dopeslam"
    d = Path(root).expanduser() / name
    if create:
        d.mkdir(parents=True, exist_ok=True)
    return d

