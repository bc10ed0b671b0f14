"""The labelling envs (DopeSlamLabelling-v0, DopeSlamActiveLabelling-v0): gymnasium's checks,
reproducibility, the perception cache, the baselines and vector envs (what needs no episode, e.g. the
object slots and the cost: ``tests/unit/test_gym_env_unit.py``).

DOPE is replaced by a noisy ground-truth double (tests/labelling_double.py) so that these tests do
not depend on trained weights; the episodes are short drives in a small test scene.
"""
import json
from pathlib import Path

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import testbed.envs  # noqa: F401  (registers the ids)
from helpers.gym_env import DURATION, SCENE, cost_of_score, env_kwargs, run_policy
from labelling_double import NoisyOracle
from testbed.envs import perception_cache as pc
from testbed.envs.policies import BASELINES, make_policy
from testbed.envs.slots import RewardConfig, slot_features


@pytest.fixture(scope="session")
def cache(tmp_path_factory):
    """Two cached episodes of the test scene (seeds 0 and 1), built once for the whole module."""
    folder = tmp_path_factory.mktemp("perception")
    env = gymnasium.make("DopeSlamLabelling-v0", **env_kwargs(folder))
    for i in range(2):
        env.reset(options={"episode": i})
    env.close()
    return folder


# --- gymnasium's own checks ------------------------------------------------------------------------

@pytest.mark.slow
def test_cached_env_passes_gymnasium_check_env(cache):
    env = gymnasium.make("DopeSlamLabelling-v0", render_mode="rgb_array", **env_kwargs(cache))
    check_env(env.unwrapped)
    staged = gymnasium.make("DopeSlamLabelling-v0", stage_choice=True, **env_kwargs(cache))
    check_env(staged.unwrapped, skip_render_check=True)
    assert staged.action_space.nvec.tolist() == [4] * 16 + [6]


@pytest.mark.slow
def test_make_by_module_path_registers_on_the_fly(cache):
    env = gymnasium.make("testbed.envs:DopeSlamLabelling-v0", **env_kwargs(cache))
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)


# --- reproducibility ---------------------------------------------------------------------------------

def rollout(env, seed, n=60):
    obs, info = env.reset(seed=seed)
    env.action_space.seed(seed)
    out = [(obs["slots"].copy(), obs["pose"].copy(), None)]
    for _ in range(n):
        obs, r, term, trunc, info = env.step(env.action_space.sample())
        out.append((obs["slots"].copy(), obs["pose"].copy(), r))
        if term:
            break
    return out


@pytest.mark.slow
def test_reset_with_a_seed_reproduces_the_episode(cache):
    a = gymnasium.make("DopeSlamLabelling-v0", **env_kwargs(cache))
    b = gymnasium.make("DopeSlamLabelling-v0", **env_kwargs(cache))
    for seed in (3, 4):
        ra, rb = rollout(a, seed), rollout(b, seed)
        assert len(ra) == len(rb)
        for (sa, pa, wa), (sb, pb, wb) in zip(ra, rb):
            assert np.array_equal(sa, sb) and np.array_equal(pa, pb) and wa == wb
    # the seed picks the episode; options pick it by hand
    picked = set()
    for s in range(8):
        a.reset(seed=s)
        picked.add(a.unwrapped.episode)
    assert picked == {0, 1}  # both episodes (seeds 0 and 1) get chosen
    o0, _ = a.reset(options={"scenario": SCENE, "seed": 1})
    o1, _ = b.reset(options={"episode": 1})
    assert np.array_equal(o0["slots"], o1["slots"])


# --- the cache -----------------------------------------------------------------------------------------

class CountingFactory:
    def __init__(self):
        self.calls = 0

    def __call__(self, ep):
        self.calls += 1
        return NoisyOracle(ep)


@pytest.mark.slow
def test_cache_is_reused_and_rebuilt_when_any_key_field_changes(cache, tmp_path):
    factory = CountingFactory()
    # the session's episodes are reused: no detector is built
    env = gymnasium.make("DopeSlamLabelling-v0", **env_kwargs(cache, detector_factory=factory))
    env.reset(options={"episode": 0})
    assert factory.calls == 0
    # a short episode in a fresh folder: built once, then read back
    kw = env_kwargs(tmp_path, detector_factory=factory, seeds=[5], duration=1.0)
    gymnasium.make("DopeSlamLabelling-v0", **kw).reset(options={"episode": 0})
    assert factory.calls == 1
    gymnasium.make("DopeSlamLabelling-v0", **kw).reset(options={"episode": 0})
    assert factory.calls == 1
    spec = gymnasium.make("DopeSlamLabelling-v0", **kw).unwrapped.spec_for(0)
    files = sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith("."))
    assert files == sorted([f"{spec.stem()}.json", f"{spec.stem()}.npz", f"{spec.stem()}.thumbs.npz"])
    # any field of the key changes it
    for change in ({"seed": 6}, {"duration": 2.5}, {"input": "depth"}, {"stages": (6,)}, {"detector": "other"},
                   {"light": 0.5}, {"scenario_sha": "0" * 16}, {"renderer": "egl"}, {"version": pc.CACHE_VERSION + 1}):
        other = pc.PerceptionSpec.from_dict({**spec.to_dict(), **change})
        assert other.key() != spec.key(), change
        assert pc.load(other, tmp_path) is None
    # a new detector identity rebuilds
    gymnasium.make("DopeSlamLabelling-v0", **{**kw, "detector_id": "test-noisy-oracle-v2"}).reset(options={"episode": 0})
    assert factory.calls == 2
    # a cache file whose recorded spec is not the one asked for (stale format, hand-copied file) is rebuilt
    meta_path = tmp_path / f"{spec.stem()}.json"
    meta = json.loads(meta_path.read_text())
    meta["spec"]["version"] = pc.CACHE_VERSION - 1
    meta_path.write_text(json.dumps(meta))
    assert pc.load(spec, tmp_path) is None
    gymnasium.make("DopeSlamLabelling-v0", **kw).reset(options={"episode": 0})
    assert factory.calls == 3
    assert pc.load(spec, tmp_path) is not None


# --- baselines ---------------------------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("name", list(BASELINES))
def test_each_baseline_runs_a_short_episode(cache, name):
    env = gymnasium.make("DopeSlamLabelling-v0", **env_kwargs(cache))
    r = run_policy(env, name, 0)
    replay = env.unwrapped.replay
    s = r["summary"]
    assert r["steps"] == replay.n_frames
    assert s["objects"] == 6 and s["labelled"] + s["missing"] == 6
    # the drive passes every column and the double sees what is within 3 m: most objects get a label of
    # their class (correct, but for the worst detections, most of which are misplaced)
    assert s["correct_labels"] + s["misplaced"] >= 4
    if name != "oracle-worst":
        assert s["labelled"] >= 4
    # the return telescopes: initial cost (all missing) less the final cost
    assert r["return"] == pytest.approx(6 * RewardConfig().missing_cost_m - s["final_cost"])
    assert s["labels_in_map"] == s["correct_labels"] + s["misplaced"] + s["phantom"]
    assert s["false_labels"] == s["misplaced"] + s["phantom"]
    # the fast cost matches the score_map assignment the map score comes from
    assert s["final_cost"] == pytest.approx(cost_of_score(r))


@pytest.mark.slow
def test_baselines_order_as_expected_on_the_noisy_double(cache):
    env = gymnasium.make("DopeSlamLabelling-v0", **env_kwargs(cache))
    for ep in (0, 1):
        err = {n: run_policy(env, n, ep)["summary"] for n in BASELINES}
        best, worst = err["oracle-best"], err["oracle-worst"]
        for n, s in err.items():
            # the best single detection per object beats every rule that keeps one detection (averaging
            # may beat it: it is the paper's hand-picked best detection, not a bound)
            if n in ("last", "last-fpr", "best-score"):
                assert best["mean_error_m"] <= s["mean_error_m"] + 1e-12, n
            assert worst["mean_error_m"] >= s["mean_error_m"] - 1e-12, n
        assert best["false_labels"] == 0
        # averaging FPR-passing detections beats taking the last one, on this double
        assert err["robust-mean"]["mean_error_m"] < err["last"]["mean_error_m"]
        assert err["robust-mean"]["false_labels"] <= err["last-fpr"]["false_labels"]


# --- rendering ---------------------------------------------------------------------------------------

@pytest.mark.slow
def test_render_shows_the_camera_beside_the_map(cache):
    env = gymnasium.make("DopeSlamLabelling-v0", render_mode="rgb_array", **env_kwargs(cache))
    env.reset(options={"episode": 0})
    policy = make_policy("robust-mean", env)
    obs, info = env.reset(options={"episode": 0})
    for _ in range(20):
        obs, r, term, trunc, info = env.step(policy(obs, info))
    img = env.render()
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    cam, tdm = img[:, :320], img[:, 322:]
    assert cam.std() > 10  # an image, not a blank panel
    assert (tdm < 200).any(axis=2).sum() > 100  # LiDAR map, path and markers drawn on white


# --- vector envs -------------------------------------------------------------------------------------

def vector_rollout(venv, seeds, steps=40):
    obs, info = venv.reset(seed=seeds)
    venv.action_space.seed(0)
    rewards = []
    for _ in range(steps):
        obs, r, term, trunc, info = venv.step(venv.action_space.sample())
        rewards.append(r.copy())
    return obs, np.array(rewards)


@pytest.mark.slow
def test_sync_and_async_vector_envs_with_two_workers_agree(cache):
    def make():
        return gymnasium.make("DopeSlamLabelling-v0", **env_kwargs(cache, detector_factory=None, build=False))

    sync = gymnasium.vector.SyncVectorEnv([make, make])
    asyn = gymnasium.vector.AsyncVectorEnv([make, make])
    try:
        o1, r1 = vector_rollout(sync, [0, 1])
        o2, r2 = vector_rollout(asyn, [0, 1])
    finally:
        sync.close()
        asyn.close()
    assert r1.shape == (40, 2)
    assert np.array_equal(r1, r2)
    assert np.array_equal(o1["slots"], o2["slots"])


# --- the active variant --------------------------------------------------------------------------------

@pytest.mark.slow
def test_active_env_passes_check_env():
    env = gymnasium.make("DopeSlamActiveLabelling-v0", scenario=SCENE, duration=0.3, detector_factory=NoisyOracle,
                         renderer="tiny")
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


@pytest.mark.slow
def test_active_env_drives_and_labels():
    from testbed.envs.active import ActivePolicy

    env = gymnasium.make("DopeSlamActiveLabelling-v0", scenario=SCENE, duration=2.0, detector_factory=NoisyOracle,
                         render_mode="rgb_array", renderer="tiny")
    policy = ActivePolicy(make_policy("robust-mean", env), env=env)
    obs, info = env.reset(seed=0)
    start = obs["pose"][:2].copy()
    policy.reset()
    while True:
        obs, r, term, trunc, info = env.step(policy(obs, info))
        if term:
            break
        if r != 0.0:
            frame = env.render()
    assert obs["pose"][0] - start[0] > 0.2  # it drove towards the route's waypoint
    assert info["map_score"]["summary"]["labelled"] >= 1
    assert frame.shape == (240, 642, 3)
    env.close()


@pytest.mark.slow
def test_active_envs_each_own_a_pybullet_client():
    kw = dict(scenario=SCENE, duration=0.5, detector_factory=NoisyOracle, renderer="tiny")
    venv = gymnasium.vector.SyncVectorEnv([lambda: gymnasium.make("DopeSlamActiveLabelling-v0", **kw)] * 2)
    try:
        venv.reset(seed=[0, 1])
        clients = [e.unwrapped.ep.client for e in venv.envs]
        assert clients[0] != clients[1]
        act = venv.action_space.sample()
        obs, r, term, trunc, info = venv.step(act)
        assert obs["slots"].shape == (2, 16, len(slot_features(6)))
    finally:
        venv.close()


# --- evaluate-policy and the SB3 example -------------------------------------------------------------

@pytest.mark.slow
def test_evaluate_policy_writes_json_and_a_table_two_like_the_paper(cache, tmp_path):
    from testbed.commands.policy import evaluate, write_outputs

    kw = {k: v for k, v in env_kwargs(cache).items() if k not in ("scenario", "seeds")}
    result = evaluate(list(BASELINES), [SCENE], [0, 1], kw)
    j, t = write_outputs(result, tmp_path)
    doc = json.loads(j.read_text())
    g = doc["by_policy"]["robust-mean"][SCENE]
    assert g["episodes"] == 2 and g["objects"] == 6
    assert set(g["mean_error_cm"]) == {"mean", "std", "n"} and g["mean_error_cm"]["n"] == 2
    assert len(doc["runs"]) == 2 * len(BASELINES)
    # the same episode scored directly agrees with the table's per-seed run
    env = gymnasium.make("DopeSlamLabelling-v0", **env_kwargs(cache))
    direct = run_policy(env, "last", 1)["summary"]
    row = next(r for r in doc["runs"] if r["policy"] == "last" and r["seed"] == 1)
    assert row["mean_error_m"] == pytest.approx(direct["mean_error_m"]) and row["false_labels"] == direct["false_labels"]
    assert doc["targets"][SCENE]["best_non_oracle"] == min(
        (n for n in BASELINES if not n.startswith("oracle")),
        key=lambda n: doc["by_policy"][n][SCENE]["mean_error_cm"]["mean"])
    table = t.read_text()
    assert "| last | original |" in table and "| oracle-worst | worst |" in table


@pytest.mark.slow
def test_sb3_example_trains_and_reports_against_the_baselines(cache, tmp_path):
    pytest.importorskip("stable_baselines3")
    import importlib.util

    path = Path(__file__).parents[2] / "examples" / "train_sb3_policy.py"
    spec = importlib.util.spec_from_file_location("train_sb3_policy", path)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    report = example.run(SCENE, [0], [1], timesteps=256, duration=DURATION, detector="double", cache=str(cache),
                         out=tmp_path, n_envs=1, renderer="tiny")
    assert set(report["policies"]) == {"ppo", *BASELINES}
    assert report["policies"]["ppo"]["return"][0] is not None
    assert (tmp_path / "ppo_policy.pt").exists() and (tmp_path / "obs_normalisation.json").exists()
    import torch

    state = torch.load(tmp_path / "ppo_policy.pt", weights_only=True)
    assert any(k.endswith("weight") for k in state)


@pytest.mark.slow
def test_real_dope_detector_path_caches_every_stage_count(tmp_path):
    """The default detector is the real DopeDetector: here with small untrained weights (what it
    detects does not matter), to check the cache keeps every stage count and names the weights."""
    import torch

    from stack.dope.net import DopeNet, DopeNetConfig, save_weights

    torch.manual_seed(0)
    weights = tmp_path / "w" / "dope_rgb.pt"
    save_weights(weights, DopeNet(DopeNetConfig(width=0.125, stages=2)))
    env = gymnasium.make("DopeSlamLabelling-v0", scenario=SCENE, seeds=[0], duration=0.6, weights=str(weights),
                         stage_choice=True, cache_dir=str(tmp_path / "cache"), renderer="tiny")
    assert env.action_space.nvec.tolist() == [4] * 16 + [2]
    obs, info = env.reset(seed=0)
    spec = env.unwrapped.replay.perception.spec
    assert spec.stages == (1, 2) and spec.detector.startswith("dope:rgb:w" + pc.file_sha256(weights))
    meta = env.unwrapped.replay.perception.meta
    assert set(meta["stage_seconds"]) == {"1", "2"} and all(v > 0 for v in meta["stage_seconds"].values())
    obs, r, term, trunc, info = env.step(env.action_space.sample())
    assert env.observation_space.contains(obs)


@pytest.mark.slow
def test_a_dope_cache_build_renders_no_segmentation_and_shows_an_eta(tmp_path, monkeypatch, capsys):
    """DOPE reads only the images, so its cache build renders no segmentation image; a factory that
    does not say so (one reading the ground truth) keeps it. The build's bar has an ETA."""
    import torch

    from sim.episode import Episode
    from stack.dope.net import DopeNet, DopeNetConfig, save_weights
    from testbed import progress

    torch.manual_seed(0)
    weights = tmp_path / "w" / "dope_rgb.pt"
    save_weights(weights, DopeNet(DopeNetConfig(width=0.125, stages=2)))
    seen, init = [], Episode.__init__

    def recording_init(self, *a, **kw):
        seen.append(kw.get("segmentation", True))
        init(self, *a, **kw)

    monkeypatch.setattr(Episode, "__init__", recording_init)
    monkeypatch.setenv("DOPESLAM_PROGRESS", "1")
    monkeypatch.setattr(progress, "_quiet", False)
    factory, det_id, kept = pc.dope_factory("rgb", 2, str(weights))
    assert factory.images_only
    pc.build(pc.make_spec(SCENE, 0, 0.6, None, "rgb", kept, det_id, renderer="tiny"), factory, tmp_path / "a",
             scenario=SCENE)
    assert seen == [False]
    err = capsys.readouterr().err
    assert "caching labelling_small seed 0" in err and "0.6/0.6 s" in err
    pc.build(pc.make_spec(SCENE, 0, 0.6, None, "rgb", kept, "other", renderer="tiny"), lambda ep: factory(ep),
             tmp_path / "b", scenario=SCENE)
    assert seen == [False, True]


@pytest.mark.slow
def test_prebuild_builds_episode_caches_through_the_matrix_runner(tmp_path, monkeypatch):
    """evaluate-policy's cache builds: two episodes with the real detector in worker processes; the
    environment then reads both without a detector, and a second prebuild resumes (builds nothing)."""
    from testbed.commands.policy import prebuild

    monkeypatch.setenv("DOPESLAM_CACHE", str(tmp_path / "root"))
    kw = {"duration": 0.5, "cache_dir": str(tmp_path / "perception"), "renderer": "tiny"}
    stems = prebuild([SCENE], [7, 8], kw, jobs=2)
    assert len(set(stems)) == 2
    cells = sorted((tmp_path / "root" / "perception-cells" / "cells").iterdir())
    assert len(cells) == 2
    stamp = [(c / "report.json").stat().st_mtime_ns for c in cells]
    env = gymnasium.make("DopeSlamLabelling-v0", scenario=SCENE, seeds=[7, 8], build=False, **kw)
    for i in range(2):
        env.reset(options={"episode": i})  # build=False: both read from the cache the workers wrote
    env.close()
    assert prebuild([SCENE], [7, 8], kw, jobs=2) == stems
    assert [(c / "report.json").stat().st_mtime_ns for c in cells] == stamp  # resumed, not rebuilt
