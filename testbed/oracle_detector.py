"""The ground-truth detector: the upper bound a real detector is measured against.

    dopeslam run --detector testbed.oracle_detector:OracleDetector

For every object in front of the camera with some of it visible in the image it returns the
object's true pose in the camera (``T_cam_obj`` from the simulator), FPR-passing and fully
certain. What is left of the label errors with it is the rest of the stack's: odometry drift,
pose interpolation at the image's time, the camera mounting, the labelling policy and the evidence
gate. It reads the simulator's truth, so it runs only in simulated episodes: ``dopeslam run``
hands it the episode through ``bind_episode`` before the first frame.
"""
from __future__ import annotations

import numpy as np

from stack.messages import CameraFrame, Detection


class OracleDetector:
    """``detect(frame)``: the true ``T_cam_obj`` of each object with more than ``min_visible`` of
    its cuboid's image area visible (``Episode.image_truth``), in front of the camera."""

    def __init__(self, min_visible: float = 0.0):
        self.min_visible = float(min_visible)
        self.episode = None

    def bind_episode(self, episode) -> None:
        """The episode whose truth the detections come from (a ``sim.episode.Episode``)."""
        self.episode = episode

    def detect(self, frame: CameraFrame) -> list[Detection]:
        if self.episode is None:
            raise RuntimeError("OracleDetector reads the simulator's truth: call bind_episode(episode) before "
                               "detect (dopeslam run does this); it cannot run on a bag")
        out = []
        for t in self.episode.image_truth(frame):
            if t["in_front"] and t["visible_fraction"] > self.min_visible:
                out.append(Detection(t["cls"], frame.stamp, np.array(t["T_cam_obj"], dtype=float),
                                     np.array(t["keypoints_px"], dtype=float), np.ones(9), belief_sum=0.0,
                                     fpr_pass=True, extra={"object": t["name"]}))
        return out
