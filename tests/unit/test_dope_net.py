"""The DOPE network: output shapes per stage count, layer counts, weights round trip, and its folded
form for inference (the same maps)."""
import copy

import pytest
import torch

from stack.dope.net import (N_AFFINITY, N_BELIEF, DopeNet, DopeNetConfig, FoldedDopeNet, load_weights, read_weights,
                            save_weights, set_memory_order)


@pytest.fixture(scope="module")
def net():
    torch.manual_seed(0)
    return DopeNet(DopeNetConfig(width=0.125, stages=6)).eval()


@pytest.mark.parametrize("stages", [1, 2, 6])
def test_outputs_every_stage_with_per_class_maps(net, stages):
    x = torch.randn(2, 3, 96, 128)
    with torch.no_grad():
        out = net(x, stages)
    assert len(out) == stages
    n_cls = len(net.classes)
    for belief, affinity in out:
        assert belief.shape == (2, n_cls * N_BELIEF, 12, 16)  # output stride 8
        assert affinity.shape == (2, n_cls * N_AFFINITY, 12, 16)


def test_fewer_stages_are_a_prefix_of_the_full_network(net):
    x = torch.randn(1, 3, 64, 64)
    with torch.no_grad():
        full = net(x, 6)
        two = net(x, 2)
    for (b6, a6), (b2, a2) in zip(full[:2], two):
        assert torch.allclose(b6, b2) and torch.allclose(a6, a2)


def test_layer_counts_follow_dope_stage_structure(net):
    # 12 feature convolutions; stage 1: 3x3 x3, 1x1, output; later stages: 7x7 x5, 1x1, output
    assert net.layer_count(1) == 12 + 5
    assert net.layer_count(6) == 12 + 5 + 5 * 7


def test_bad_stage_count_is_rejected(net):
    with pytest.raises(ValueError, match="stages must be 1..6"):
        net(torch.zeros(1, 3, 32, 32), 7)


def test_half_precision_weights_round_trip(net, tmp_path):
    path = tmp_path / "w.pt"
    save_weights(path, net, half=True, extra={"input": "rgb"})
    model, extra = load_weights(path)
    assert extra["input"] == "rgb"
    x = torch.randn(1, 3, 64, 64)
    with torch.no_grad():
        a = net(x)[-1][0]
        b = model(x)[-1][0]
    assert float((a - b).abs().max()) < 1e-2 * max(1.0, float(a.abs().max()))
    blob = torch.load(path, weights_only=True)
    assert all(v.dtype == torch.float16 for v in blob["state_dict"].values() if v.is_floating_point())


@pytest.mark.parametrize("kind", ["other dict", "junk bytes", "code", "bad config", "wrong tensors", "folder",
                                  "missing"])
def test_loading_a_non_weights_file_names_the_file(tmp_path, kind):
    """Whatever the file holds, one user error (a DopeSlamError) naming it; nothing in it runs."""
    import pickle

    from stack.errors import DopeSlamError
    from stack.dope.net import WeightsError

    bad = tmp_path / "bad.pt"
    good = DopeNet(DopeNetConfig(width=0.125, stages=2))
    if kind == "other dict":
        torch.save({"x": torch.zeros(1)}, bad)
    elif kind == "junk bytes":
        bad.write_bytes(b"\x00not a network" * 50)
    elif kind == "code":  # a pickle that would call a function: refused, never run
        bad.write_bytes(pickle.dumps(tmp_path.joinpath))
    elif kind == "bad config":
        torch.save({"config": {"no such field": 1}, "state_dict": {}}, bad)
    elif kind == "wrong tensors":
        torch.save({"config": {"width": 0.125, "stages": 2},
                    "state_dict": {k: torch.zeros(1) for k in good.state_dict()}}, bad)
    elif kind == "folder":
        bad.mkdir()
    with pytest.raises(WeightsError, match="bad.pt") as info:
        load_weights(bad)
    assert isinstance(info.value, DopeSlamError) and "\n" not in str(info.value)
    if kind not in ("bad config", "wrong tensors"):  # what reading alone can tell
        with pytest.raises(WeightsError, match="bad.pt"):
            read_weights(bad)


def test_a_cache_of_weights_that_are_not_one_is_a_user_error(tmp_path):
    from stack.dope.net import WeightsError
    from testbed.envs.perception_cache import dope_stage_counts

    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"\x00not a network" * 50)
    with pytest.raises(WeightsError, match="bad.pt"):
        dope_stage_counts("rgb", 6, bad)
    torch.save({"config": {"width": 0.125}, "state_dict": {}}, bad)
    with pytest.raises(WeightsError, match="no number of stages"):
        dope_stage_counts("rgb", 6, bad)


def test_expand_stages_repeats_the_last_stage():
    from stack.dope.net import expand_stages

    torch.manual_seed(1)
    short = DopeNet(DopeNetConfig(width=0.125, stages=2)).eval()
    long = expand_stages(short, 4).eval()
    assert long.config.stages == 4
    for k, v in short.stages[1].state_dict().items():
        assert torch.equal(long.stages[3].state_dict()[k], v)
    x = torch.randn(1, 3, 64, 64)
    with torch.no_grad():
        a, b = short(x), long(x)
    assert torch.allclose(a[1][0], b[1][0]) and len(b) == 4


def _randomised(net: DopeNet) -> DopeNet:
    """``net`` with every bias drawn too (a fresh network's are small): the folded border term must show."""
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.Conv2d) and m.bias is not None:
                m.bias.copy_(torch.randn(m.bias.shape, generator=g) * 0.5)
    return net


@pytest.mark.parametrize("in_channels, size", [(3, (48, 64)), (1, (40, 56))])
def test_the_folded_network_gives_the_same_maps_at_every_stage(in_channels, size):
    torch.manual_seed(2)
    net = _randomised(DopeNet(DopeNetConfig(width=0.125, stages=4, in_channels=in_channels)).eval())
    folded = FoldedDopeNet(net)
    x = torch.randn(2, in_channels, *size)
    with torch.no_grad():
        for stages in (1, 2, 4):
            want, got = net(x, stages), folded(x, stages)
            assert len(got) == stages
            for (bw, aw), (bg, ag) in zip(want, got):
                assert bg.shape == bw.shape and ag.shape == aw.shape
                scale = max(bw.abs().max().item(), aw.abs().max().item())
                assert (bg - bw).abs().max().item() < 1e-5 * scale
                assert (ag - aw).abs().max().item() < 1e-5 * scale
    # stage 1 takes no folded layer: bit for bit
    with torch.no_grad():
        assert torch.equal(net(x, 1)[0][0], folded(x, 1)[0][0])
    assert folded.classes == net.classes and folded.config is net.config
    assert [folded.layer_count(s) for s in (1, 4)] == [net.layer_count(s) for s in (1, 4)]
    with pytest.raises(ValueError, match="stages must be 1..4"):
        folded(x, 5)


def test_the_folded_network_follows_the_source_layers_it_folds():
    """The folded weights are the source's, composed: changing the source network after folding changes
    nothing, and a different second-stage kernel gives different maps (the fold is not a copy of one)."""
    torch.manual_seed(3)
    net = _randomised(DopeNet(DopeNetConfig(width=0.125, stages=2)).eval())
    x = torch.randn(1, 3, 32, 32)
    folded = FoldedDopeNet(net)
    with torch.no_grad():
        before = folded(x)[1][0].clone()
        net.stages[1][0].weight.mul_(2.0)
        other = FoldedDopeNet(net)(x)[1][0]
    assert torch.equal(folded(x)[1][0], before)
    assert not torch.allclose(other, before)


@pytest.mark.parametrize("folded", [False, True])
@pytest.mark.parametrize("channels_last, refinement_channels_last", [(True, False), (False, True), (True, True)])
def test_each_memory_order_gives_the_same_maps(folded, channels_last, refinement_channels_last):
    """The features and first stage in one memory order, the refinement stages in another: the trained
    network's maps at every stage count, and the refinement stages' weights in the order asked for."""
    torch.manual_seed(4)
    net = _randomised(DopeNet(DopeNetConfig(width=0.125, stages=3)).eval())
    model = copy.deepcopy(net)
    model = set_memory_order(FoldedDopeNet(model) if folded else model, channels_last, refinement_channels_last)
    first = torch.channels_last if channels_last else torch.contiguous_format
    refine = torch.channels_last if refinement_channels_last else torch.contiguous_format
    assert model.features[0].weight.is_contiguous(memory_format=first)
    later = [m for m in (model.hidden[1] if folded else model.stages[1]).modules()
             if isinstance(m, torch.nn.Conv2d) and m.kernel_size != (1, 1)]  # 1x1: in the first order
    assert later and all(m.weight.is_contiguous(memory_format=refine) for m in later)
    assert model.refinement_format == (None if first == refine else refine)
    x = torch.randn(2, 3, 40, 48)
    with torch.no_grad():
        for stages in (1, 2, 3):
            want = net(x, stages)
            got = model(x.contiguous(memory_format=first), stages)
            assert len(got) == stages
            for (bw, aw), (bg, ag) in zip(want, got):
                scale = max(bw.abs().max().item(), aw.abs().max().item())
                assert (bg - bw).abs().max().item() < 1e-5 * scale
                assert (ag - aw).abs().max().item() < 1e-5 * scale


@pytest.mark.parametrize("folded", [False, True])
@pytest.mark.parametrize("refinement_channels_last", [False, True])
def test_the_maps_do_not_depend_on_the_thread_count(folded, refinement_channels_last):
    """The detector's memory orders give the same bits on one thread and on two (at the shipped width
    and input size, one image and a batch of two): a run's outputs do not depend on how many threads
    its detector process has."""
    torch.manual_seed(6)
    net = _randomised(DopeNet(DopeNetConfig(width=0.25, stages=3)).eval())
    model = set_memory_order(FoldedDopeNet(net) if folded else net, True, refinement_channels_last)
    before = torch.get_num_threads()
    try:
        for batch in (1, 2):
            x = torch.randn(batch, 3, 240, 320).contiguous(memory_format=torch.channels_last)
            maps = {}
            for threads in (1, 2):
                torch.set_num_threads(threads)
                with torch.no_grad():
                    maps[threads] = model(x)
            for (b1, a1), (b2, a2) in zip(maps[1], maps[2]):
                assert torch.equal(b1, b2) and torch.equal(a1, a2)
    finally:
        torch.set_num_threads(before)
