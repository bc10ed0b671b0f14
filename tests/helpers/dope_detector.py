"""Shared by tests/e2e/test_dope_detector.py and tests/unit/test_dope_detector_unit.py."""
import pytest

from stack.dope_fpr import default_weights

needs_rgb_weights = pytest.mark.skipif(not default_weights("rgb").exists(), reason="no shipped RGB weights")
