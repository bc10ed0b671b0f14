"""Replay's image loop with a second detector process beside it (``detected_images(..., helper)``): the
images come out in their order with the detections the one detector would give, the helper holds at
most two images and takes every image it has room for, and an image in the helper does not hold back
the images the gate passes by for long. The helper here is a stand-in (its jobs finish when asked, or
at once), so the test is about the loop's order, not about processes."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from stack.keyframes import KeyframeGate, KeyframeSettings
from stack.messages import CameraFrame, CameraInfo, Detection, WheelOdometry
from testbed.replay import detected_images

INFO = CameraInfo(4, 3, np.eye(3))


def frame(k: int) -> CameraFrame:
    return CameraFrame(0.1 * k, INFO, np.full((3, 4, 3), k, np.uint8), np.full((3, 4), k, np.float32))


class Reader:
    """Images 0..n-1 at 10 Hz; with ``odometry`` each follows a wheel odometry message (standing
    still for ``stand`` images, then moving 5 cm per image)."""

    def __init__(self, n: int, stand: int = 0):
        self.n, self.stand = n, stand
        self.read = 0  # images read so far

    def camera_frames(self):
        return (frame(k) for k in range(self.n))

    def frames(self, lidar: bool, camera: bool, odometry: bool):
        for k in range(self.n):
            T = np.eye(4)
            T[0, 3] = 0.05 * max(0, k - self.stand)
            yield WheelOdometry(0.1 * k - 0.01, T, 0.0, 0.0)
            self.read += 1
            yield frame(k)


class Detector:
    def __init__(self):
        self.seen = []

    def detect(self, f):
        self.seen.append(int(f.rgb[0, 0, 0]))
        return [Detection("det", float(f.rgb[0, 0, 0]), np.eye(4), np.zeros((9, 2)), np.ones(9), 0.0)]


def tags(dets):
    """A list of detections as (class, stamp) pairs, which compare with ==; None stays None."""
    return None if dets is None else [(d.cls, int(d.stamp)) for d in dets]


class Helper(Detector):
    """Jobs finish when ``result()`` is asked (``instant``: as soon as they are submitted); records how
    many were in it at once."""

    def __init__(self, instant: bool = False):
        super().__init__()
        self.instant = instant
        self.in_flight, self.most = 0, 0

    def fits(self, f):
        return f.rgb.shape == (3, 4, 3)

    def unfinished(self):
        return 0 if self.instant else self.in_flight

    def submit(self, f):
        self.in_flight += 1
        self.most = max(self.most, self.in_flight)

        def result():
            self.in_flight -= 1
            return self.detect(f), 0.5

        return SimpleNamespace(result=result, done=lambda: self.instant)


def run(reader, every=1, gate=None, helper=None):
    return [(int(f.rgb[0, 0, 0]), tags(dets), seconds > 0 if dets is not None else None)
            for f, dets, _, seconds in detected_images(reader, Detector(), every, gate, helper)]


def test_with_a_helper_the_images_and_detections_are_those_without():
    for every in (1, 2, 3):
        alone = run(Reader(11), every)
        detected = [k for k, d, _ in alone if d is not None]
        for instant in (False, True):
            helper = Helper(instant)
            shared = run(Reader(11), every, helper=helper)
            assert [(k, d) for k, d, _ in shared] == [(k, d) for k, d, _ in alone]
            assert [k for k, _, _ in shared] == list(range(11))
            assert helper.most <= 2 and helper.in_flight == 0
            assert all(s for _, d, s in shared if d is not None)  # each detected image has its seconds
            if instant:  # a helper that keeps up takes every image
                assert helper.seen == detected
            else:  # one that holds its images takes the first two, then what it has room for
                assert helper.seen[:2] == detected[:2]
                if every == 1:  # images come faster than it gives them back: this process detects some
                    assert 2 < len(helper.seen) < len(detected)


def test_an_image_in_the_helper_holds_back_a_few_images_at_most():
    """Behind a gate that lets one image through and then holds the standing robot's next ones, the
    helper's image comes back after at most five more images rather than at the next detection."""
    settings = KeyframeSettings(min_motion_m=0.1, min_turn_deg=5.0, max_interval_s=100.0)
    alone = run(Reader(20, stand=12), gate=KeyframeGate(settings))
    reader, helper, collected = Reader(20, stand=12), Helper(), []

    class Watching:
        def fits(self, f):
            return True

        def unfinished(self):
            return helper.unfinished()

        def submit(self, f):
            job = helper.submit(f)

            def result():
                collected.append((int(f.rgb[0, 0, 0]), reader.read))
                return job.result()

            return SimpleNamespace(result=result, done=job.done)

    got = [(int(f.rgb[0, 0, 0]), tags(dets)) for f, dets, _, _ in
           detected_images(reader, Detector(), 1, KeyframeGate(settings), Watching())]
    assert got == [(k, d) for k, d, _ in alone]
    detected = [k for k, d in got if d is not None]
    assert detected[0] == 0 and detected[1] > 6  # the gate holds the standing robot's images
    assert collected[0] == (0, 5)  # image 0 came back once four more had been read, not at the next detection
