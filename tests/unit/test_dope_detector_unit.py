"""The detector's interface: bad arguments are errors, and the torch threads follow the environment
(the shipped weights on rendered frames: ``tests/e2e/test_dope_detector.py``)."""
import pytest

from helpers.dope_detector import needs_rgb_weights
from stack.dope_fpr import DopeDetector

pytestmark = needs_rgb_weights


def test_missing_dims_or_bad_input_are_errors():
    with pytest.raises(ValueError, match="dims"):
        DopeDetector(input="rgb")
    with pytest.raises(ValueError, match="input"):
        DopeDetector(input="thermal", dims={"E": (0.1, 0.14, 0.035)})


def test_torch_threads_from_the_environment(monkeypatch):
    import torch

    before = torch.get_num_threads()
    monkeypatch.setenv("DOPESLAM_TORCH_THREADS", "1")
    try:
        DopeDetector(input="rgb", dims={"E": (0.1, 0.14, 0.035)})
        assert torch.get_num_threads() == 1
        monkeypatch.setenv("DOPESLAM_TORCH_THREADS", "two")
        with pytest.raises(ValueError, match="DOPESLAM_TORCH_THREADS"):
            DopeDetector(input="rgb", dims={"E": (0.1, 0.14, 0.035)})
    finally:
        torch.set_num_threads(before)


def test_precision_is_checked_and_falls_back_to_fp32_without_native_bfloat16(monkeypatch):
    import torch

    import stack.dope_fpr as dope_fpr
    from stack.config import DetectorConfig

    dims = {"E": (0.1, 0.14, 0.035)}
    with pytest.raises(ValueError, match="precision"):
        DopeDetector(input="rgb", dims=dims, precision="fp16")
    monkeypatch.setattr(dope_fpr, "bf16_native", lambda device="cpu": False)
    det = DopeDetector(input="rgb", dims=dims, precision="bf16")
    assert det.precision == "fp32" and next(det.model.parameters()).dtype == torch.float32
    monkeypatch.setattr(dope_fpr, "bf16_native", lambda device="cpu": True)
    det = DopeDetector(input="rgb", dims=dims, precision="bf16")
    assert det.precision == "bf16" and next(det.model.parameters()).dtype == torch.bfloat16
    assert DetectorConfig(precision="bf16").dope_kwargs()["precision"] == "bf16"
    with pytest.raises(Exception, match="precision"):
        DetectorConfig(precision="int4")


def test_refinement_order_follows_the_cpu_unless_named(monkeypatch):
    """``auto`` runs the refinement stages in the plain order on an AVX2 CPU, elsewhere in the order of
    ``channels_last``; a named order is what runs; anything else is an error, in the config too."""
    import torch

    from stack.config import DetectorConfig
    from stack.dope_fpr import refinement_memory_order

    dims = {"E": (0.1, 0.14, 0.035)}
    for capability, want in (("AVX2", "contiguous"), ("AVX512", "channels_last"), ("DEFAULT", "channels_last")):
        monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", lambda c=capability: c)
        assert refinement_memory_order("auto", True, "cpu") == want
        assert refinement_memory_order("auto", False, "cpu") == "contiguous"
        for named in ("channels_last", "contiguous"):
            assert refinement_memory_order(named, capability == "AVX2", "cpu") == named
        det = DopeDetector(input="rgb", dims=dims)
        assert det.refinement_order == want
        conv = next(m for m in det.model.hidden[1].modules() if isinstance(m, torch.nn.Conv2d))
        fmt = torch.channels_last if want == "channels_last" else torch.contiguous_format
        assert conv.weight.is_contiguous(memory_format=fmt)
    assert refinement_memory_order("auto", True, "cuda") == "channels_last"
    with pytest.raises(ValueError, match="refinement_order must be one of auto, channels_last, contiguous"):
        refinement_memory_order("nhwc")
    with pytest.raises(ValueError, match="refinement_order"):
        DopeDetector(input="rgb", dims=dims, refinement_order="nhwc")
    assert DetectorConfig(refinement_order="contiguous").dope_kwargs()["refinement_order"] == "contiguous"
    with pytest.raises(Exception, match="refinement_order"):
        DetectorConfig(refinement_order="nhwc")
