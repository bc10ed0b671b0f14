"""The network in int8 (``precision = "int8"``): calibration files are checked like any file a user
hands in, a calibration fits only the network it was made for, and a quantised network is
deterministic and near its float maps (the shipped weights on rendered frames:
``tests/e2e/test_dope_detector.py``)."""
import json

import pytest
import torch

from stack.dope import int8
from stack.dope.net import DopeNet, DopeNetConfig, FoldedDopeNet

pytestmark = pytest.mark.skipif(not int8.available(), reason="this PyTorch has no x86 quantised kernels")


def _net(seed=0, stages=3):
    torch.manual_seed(seed)
    return FoldedDopeNet(DopeNet(DopeNetConfig(("A", "B"), width=0.125, stages=stages)).eval())


def _inputs(n=6, seed=1):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(2, 3, 48, 64, generator=g) for _ in range(n)]


def test_calibrate_save_load_quantize_is_deterministic_and_near_float(tmp_path):
    net = _net()
    cal = int8.calibrate(net, _inputs())
    assert cal["inputs"] == 12 and set(cal["blocks"]) == {"features", "hidden.0", "hidden.1", "hidden.2",
                                                         "on_features.0", "on_features.1", "on_hidden.0",
                                                         "on_hidden.1"}
    int8.save(tmp_path / "c.json", cal)
    loaded = int8.load(tmp_path / "c.json")
    x = _inputs(1, seed=7)[0]
    with torch.inference_mode():
        ref = net(x)  # calibrate leaves the float network as it was
        q1 = int8.quantize(_net(), loaded, x)(x)
        q2 = int8.quantize(_net(), loaded, x)(x)
    assert len(q1) == len(ref) == 3
    for (b1, a1), (b2, a2), (br, ar) in zip(q1, q2, ref):
        assert torch.equal(b1, b2) and torch.equal(a1, a2)  # the same calibration: the same bits
        assert b1.dtype == torch.float32
        scale = float(br.abs().max())
        assert float((b1 - br).abs().max()) < 0.25 * scale  # 8 bits through a few layers: near, not equal


def test_fewer_stages_run_the_same_blocks():
    net = _net()
    cal = int8.calibrate(net, _inputs(3))
    x = _inputs(1, seed=3)[0]
    q = int8.quantize(_net(), cal, x)
    with torch.inference_mode():
        full, two = q(x), q(x, 2)
    assert len(two) == 2 and all(torch.equal(a[0], b[0]) for a, b in zip(full, two))


def test_a_calibration_of_another_network_is_refused():
    cal = int8.calibrate(_net(stages=3), _inputs(2))
    x = _inputs(1)[0]
    with pytest.raises(int8.Int8Error, match="other weights"):
        int8.quantize(_net(stages=2), cal, x, source="c.json")
    broken = json.loads(json.dumps(cal))
    broken["blocks"]["features"].pop(next(iter(broken["blocks"]["features"])))
    with pytest.raises(int8.Int8Error, match="c.json: blocks.features"):
        int8.quantize(_net(), broken, x, source="c.json")


@pytest.mark.parametrize("content, says", [
    (None, "no such file; expected an int8 calibration"),
    (b"\xff\xfe", "unreadable (UnicodeDecodeError)"),
    (b"[1, 2]", "expected an int8 calibration"),
    (json.dumps({"format": "something-else", "blocks": {}}), "expected an int8 calibration"),
    (json.dumps({"format": int8.FORMAT, "blocks": {"features": 3}}), "blocks.features: expected an object"),
    (json.dumps({"format": int8.FORMAT, "blocks": {"features": {"o": {"scale": 0, "zero_point": 0, "quant_min": 0,
                                                                       "quant_max": 127}}}}), "blocks.features.o"),
    (json.dumps({"format": int8.FORMAT, "blocks": {"features": {"o": {"scale": 0.1, "zero_point": 200,
                                                                       "quant_min": 0, "quant_max": 127}}}}),
     "quant_min <= zero_point <= quant_max"),
    (json.dumps({"format": int8.FORMAT, "blocks": {"features": {"o": {"scale": True, "zero_point": 0,
                                                                       "quant_min": 0, "quant_max": 127}}}}),
     "expected scale > 0"),
    (json.dumps({"format": int8.FORMAT, "blocks": {}, "meta": {"weights_sha256": 5}}),
     "meta: expected an object whose weights_sha256"),
])
def test_bad_calibration_files_name_the_file_and_what_was_expected(tmp_path, content, says):
    path = tmp_path / "dope_rgb_int8.json"
    if content is not None:
        path.write_bytes(content if isinstance(content, bytes) else content.encode())
    with pytest.raises(int8.Int8Error) as e:
        int8.load(path)
    assert str(e.value).startswith(str(path)) and says in str(e.value), str(e.value)


def test_precision_int8_is_what_runs_on_a_cpu_and_falls_back_elsewhere(monkeypatch):
    from stack.config import DetectorConfig
    from stack.dope_fpr import effective_precision

    assert effective_precision("int8") == "int8"
    assert DetectorConfig(precision="int8").dope_kwargs()["precision"] == "int8"
    monkeypatch.setattr(int8, "available", lambda: False)
    assert effective_precision("int8") == "fp32"


def test_the_calibration_lies_beside_the_weights():
    from stack.dope_fpr import default_weights

    for mode in ("rgb", "depth"):
        path = int8.calibration_path(default_weights(mode))
        assert path.name == f"dope_{mode}_int8.json" and path.parent == default_weights(mode).parent
        if default_weights(mode).exists():
            assert int8.load(path)["blocks"]  # shipped with the weights


def test_a_calibration_beside_other_weights_is_refused(tmp_path):
    """Weights retrained in place keep the network's shape, so only the calibration's record of the
    weights it was made for tells a stale calibration apart."""
    import shutil

    from stack.dope_fpr import DopeDetector, default_weights

    if not default_weights("rgb").exists():
        pytest.skip("no shipped RGB weights")
    weights = tmp_path / "mine.pt"
    shutil.copy(default_weights("rgb"), weights)
    with pytest.raises(int8.Int8Error, match="mine_int8.json: no such file"):
        DopeDetector(weights=weights, input="rgb", dims={"E": (0.1, 0.14, 0.035)}, precision="int8")
    cal = int8.load(int8.calibration_path(default_weights("rgb")))
    int8.save(tmp_path / "mine_int8.json", cal)
    det = DopeDetector(weights=weights, input="rgb", dims={"E": (0.1, 0.14, 0.035)}, precision="int8")
    assert det.precision == "int8"
    cal["meta"]["weights_sha256"] = "0" * 64
    int8.save(tmp_path / "mine_int8.json", cal)
    with pytest.raises(int8.Int8Error, match="calibrated for other weights than"):
        DopeDetector(weights=weights, input="rgb", dims={"E": (0.1, 0.14, 0.035)}, precision="int8")
