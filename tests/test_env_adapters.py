"""The race behind PettingZoo and Gymnasium: the libraries' own API tests, a vector-env check in
the style of gymnasium's checker, and the adapters agreeing with RaceEnv itself step for step."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

pytest.importorskip("gymnasium")
pytest.importorskip("pettingzoo")

from gymnasium.utils.env_checker import check_env  # noqa: E402
from pettingzoo.test import parallel_api_test, parallel_seed_test  # noqa: E402

from cfrace.rl.adapters import make_race_env  # noqa: E402
from cfrace.rl.adapters.gymnasium_env import RaceGymEnv, RaceVectorEnv  # noqa: E402
from cfrace.rl.adapters.pettingzoo_env import RaceParallelEnv  # noqa: E402
from cfrace.errors import ConfigError  # noqa: E402


@pytest.mark.parametrize("method", ["ours", "dm", "ds"])
def test_pettingzoo_parallel_api(method):
    env = RaceParallelEnv(method)
    assert env.possible_agents == [f"drone_{i}" for i in range(2 if method in ("ours", "dm") else 1)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")       # the API test reports some problems only as warnings
        parallel_api_test(env, num_cycles=400)
    parallel_seed_test(lambda: RaceParallelEnv(method), num_cycles=50)


def test_pettingzoo_episode_ends_and_matches_raceenv():
    """Full-thrust climbs crash both drones into the ceiling/arena: each leaves `agents` on its
    crash step, the rewards are RaceEnv's, and the last observations are pre-reset states."""
    env = RaceParallelEnv("ours", seed=5)
    native, _ = make_race_env("ours", num_envs=1, seed=5)
    obs, _ = env.reset(seed=7)
    native.gen.manual_seed(7), native.sim.generator.manual_seed(7)
    nobs, _ = native.reset()
    assert np.array_equal(obs["drone_0"], nobs[0, 0].numpy()) and np.array_equal(obs["drone_1"], nobs[0, 1].numpy())
    gone = {}
    for step in range(600):
        act = {a: np.array([1.0, 0.3, 0.0, 0.0], np.float32) for a in env.agents}
        obs, rew, term, trunc, info = env.step(act)
        r = native.step(torch.tensor([[[1.0, 0.3, 0.0, 0.0]] * 2]))
        for a, i in (("drone_0", 0), ("drone_1", 1)):
            if a in rew:
                assert rew[a] == pytest.approx(float(r.reward[0, i]))
                assert term[a] == bool(r.terminated[0, i]) and trunc[a] == bool(r.truncated[0, i])
                if term[a] or trunc[a]:
                    gone[a] = step
        if not env.agents:
            break
    assert set(gone) == {"drone_0", "drone_1"} and not env.agents
    assert all(v.shape == (env.race.obs_dim,) for v in obs.values())
    assert env.state().shape == (2 * env.race.obs_dim,)


def test_gymnasium_env_checker():
    env = RaceGymEnv("ds")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # raw observations have no guaranteed bounds (velocities, distances): the Box is unbounded
        warnings.filterwarnings("ignore", message=".*Box observation space (minimum|maximum) value is .?infinity")
        check_env(env, skip_render_check=True)
    with pytest.raises(ConfigError, match="RaceParallelEnv"):
        RaceGymEnv("ours")


def test_gymnasium_vector_env():
    """The checks of gymnasium's checker, applied to the batch: spaces, dtypes, shapes, seeded
    determinism, fresh arrays per call, same-step autoreset with final_obs, and equality with
    the native batched RaceEnv at the same world count."""
    n = 16
    venv = RaceVectorEnv(n, "ds", seed=2)
    assert venv.metadata["autoreset_mode"].value == "SameStep"
    assert venv.observation_space.shape == (n, venv.race.obs_dim) and venv.action_space.shape == (n, 4)
    o1, info = venv.reset(seed=11)
    o2, _ = venv.reset(seed=11)
    assert isinstance(info, dict) and np.array_equal(o1, o2) and o1 is not o2
    assert o1 in venv.observation_space
    native, _ = make_race_env("ds", num_envs=n, seed=2)
    native.gen.manual_seed(11), native.sim.generator.manual_seed(11)
    nobs, _ = native.reset()
    assert np.array_equal(o1, nobs[:, 0].numpy())
    venv.action_space.seed(3)
    finals = 0
    for _ in range(120):
        a = venv.action_space.sample()
        obs, rew, term, trunc, infos = venv.step(a)
        r = native.step(torch.as_tensor(a).reshape(n, 1, 4))
        assert obs.dtype == np.float32 and obs.shape == (n, venv.race.obs_dim) and obs in venv.observation_space
        assert rew.dtype == np.float32 and rew.shape == (n,) and term.dtype == bool and trunc.dtype == bool
        assert np.array_equal(obs, r.obs[:, 0].numpy()) and np.array_equal(rew, r.reward[:, 0].numpy())
        done = term | trunc
        if done.any():
            assert np.array_equal(infos["_final_obs"], done)
            for i in np.flatnonzero(done):
                assert infos["final_obs"][i] in venv.single_observation_space
                assert np.array_equal(infos["final_obs"][i], r.final_critic[i, 0].numpy())
            finals += int(done.sum())
        else:
            assert "final_obs" not in infos
    assert finals > 0       # random actions crash: the autoreset path ran
    with pytest.raises(ConfigError):
        RaceVectorEnv(4, "dm")
    with pytest.raises(ConfigError, match="num_envs"):
        RaceVectorEnv(0, "ds")
    with pytest.raises(ConfigError, match="episode_s"):
        RaceVectorEnv(2, "ds", episode_s=-1.0)


def test_parallel_vector_env_matches_raceenv():
    """The vectorized multi-agent form: dicts of batches equal to RaceEnv's step for step; the
    reset mask is exactly the worlds RaceEnv restarted (their step counter back to 0)."""
    from cfrace.rl.adapters.pettingzoo_env import RaceParallelVectorEnv

    n = 32
    venv = RaceParallelVectorEnv(n, "ours", seed=4)
    native, _ = make_race_env("ours", num_envs=n, seed=4)
    obs, _ = venv.reset(seed=9)
    native.gen.manual_seed(9), native.sim.generator.manual_seed(9)
    nobs, _ = native.reset()
    assert venv.agents == ["drone_0", "drone_1"]
    assert all(np.array_equal(obs[a], nobs[:, i].numpy()) for i, a in enumerate(venv.agents))
    rng = np.random.default_rng(0)
    resets = dead = 0
    for _ in range(150):
        act = rng.uniform(-1, 1, (n, 2, 4)).astype(np.float32)
        obs, rew, term, trunc, info = venv.step({a: act[:, i] for i, a in enumerate(venv.agents)})
        r = native.step(torch.as_tensor(act))
        restarted = (native.steps == 0).numpy()
        for i, a in enumerate(venv.agents):
            assert obs[a].shape == (n, native.obs_dim) and obs[a].dtype == np.float32
            assert np.array_equal(obs[a], r.obs[:, i].numpy()) and np.array_equal(rew[a], r.reward[:, i].numpy())
            assert np.array_equal(term[a], r.terminated[:, i].numpy())
            assert np.array_equal(trunc[a], r.truncated[:, i].numpy())
            assert np.array_equal(info[a]["alive"], r.alive[:, i].numpy())
            assert np.array_equal(info[a]["_final_obs"], restarted)
            m = restarted
            assert np.array_equal(info[a]["final_obs"][m], r.final_critic[m, i, :native.obs_dim].numpy())
        resets += int(restarted.sum())
        dead += int((~info["drone_0"]["alive"]).sum())
    assert resets > 0 and dead > 0   # both paths ran: worlds restarted, drones sat out crashed
