"""Belief and affinity targets against hand-built cases."""
import numpy as np
import pytest

from stack.dope.net import N_AFFINITY, N_BELIEF
from stack.dope.targets import make_targets, to_input_px, to_output_coords


def _object(centre_px, half=(16.0, 24.0)):
    cx, cy = centre_px
    hw, hh = half
    corners = [(cx + hw, cy - hh), (cx - hw, cy - hh), (cx - hw, cy + hh), (cx + hw, cy + hh)]
    corners += [(x + 4, y - 4) for x, y in corners]
    return np.array(corners + [(cx, cy)], dtype=float)


def test_coordinate_mapping_round_trips_and_centres_cells():
    uv = np.array([[3.5, 3.5], [0.0, 0.0], [100.25, 37.0]])
    assert np.allclose(to_input_px(to_output_coords(uv)), uv)
    assert np.allclose(to_output_coords([[3.5, 11.5]]), [[0.0, 1.0]])  # cell centres at 8k + 3.5


def test_belief_peaks_at_the_key_points_of_the_right_class():
    kp = _object((67.5, 51.5))
    b, a = make_targets(kp[None], np.array([2]), 3, (16, 20))
    assert b.shape == (3 * N_BELIEF, 16, 20) and a.shape == (3 * N_AFFINITY, 16, 20)
    assert b[:2 * N_BELIEF].max() == 0 and a[:2 * N_AFFINITY].max() == 0  # other classes empty
    for k in range(9):
        m = b[2 * N_BELIEF + k]
        r, c = np.unravel_index(np.argmax(m), m.shape)
        x, y = to_output_coords(kp[k])
        assert (abs(c - x) <= 0.5) and (abs(r - y) <= 0.5)
        assert m.max() <= 1.0
    # the centroid lies exactly on a cell centre: a peak of exactly 1, 1 cell away exp(-1/2)
    m = b[2 * N_BELIEF + 8]
    assert m[6, 8] == pytest.approx(1.0) and m[6, 9] == pytest.approx(np.exp(-0.5), rel=1e-5)


def test_affinities_are_unit_vectors_towards_the_centroid():
    kp = _object((67.5, 51.5))
    _, a = make_targets(kp[None], np.array([0]), 1, (16, 20))
    x, y = to_output_coords(kp[0])  # front top right: centroid is left-down of it
    r, c = int(round(y)), int(round(x))
    v = a[0:2, r, c]
    expected = to_output_coords(kp[8]) - to_output_coords(kp[0])
    assert np.allclose(v, expected / np.linalg.norm(expected), atol=1e-6)
    norms = np.hypot(a[0::2], a[1::2])
    assert np.allclose(norms[norms > 0], 1.0, atol=1e-6)
    assert norms[0, r + 4, c] == 0  # outside the disc


def test_two_objects_give_two_peaks_and_off_grid_points_are_skipped():
    kps = np.stack([_object((40, 60)), _object((120, 60))])
    kps[1, 0] = (-200, -200)  # far outside the crop
    b, _ = make_targets(kps, np.array([0, 0]), 1, (16, 20))
    centre = b[8]
    assert (centre > 0.9).sum() >= 2
    assert b[0].max() > 0.5  # first object's corner is still there


def test_class_index_out_of_range_is_an_error():
    with pytest.raises(ValueError, match="class index 3"):
        make_targets(_object((40, 40))[None], np.array([3]), 3, (8, 8))
