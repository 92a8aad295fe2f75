"""Shared test fixtures."""
import pytest
import torch


@pytest.fixture(autouse=True)
def signal_handlers_back():
    """A command run in-process (`fly`, `sim dry-run`) ignores SIGINT/SIGTERM after its race, as the
    process is about to exit (cfrace.flight.loop.race.SignalGuard): put them back after each test, so
    that later tests and the subprocesses they start get the usual ones."""
    import signal
    import threading

    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    yield
    if threading.current_thread() is threading.main_thread():
        for s, h in saved.items():
            if h is not None:
                signal.signal(s, h)


@pytest.fixture
def one_torch_thread():
    """Shared 2-core machine: one intra-op thread avoids oversubscription (10x slower otherwise)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture
def ppo_batch():
    """make(seed, n, obs_dim, critic_dim, actor_hidden, critic_hidden) -> (fresh AgentModels, a flat PPO
    batch sampled from it): advantages favour a0 > 0, returns depend on the critic input."""
    import torch

    from cfrace.rl.models import AgentModels

    def make(seed=0, n=512, obs_dim=6, critic_dim=12, actor_hidden=(32, 32), critic_hidden=(32,)):
        gen = torch.Generator().manual_seed(seed)
        torch.manual_seed(seed)
        model = AgentModels(obs_dim, critic_dim, actor_hidden, critic_hidden, 1.0)
        obs = torch.randn(n, obs_dim, generator=gen)
        critic = torch.randn(n, critic_dim, generator=gen)
        with torch.no_grad():
            dist = model.actor(model.obs_norm(obs))
            actions = dist.sample()
            batch = {"obs": obs, "critic": critic, "actions": actions, "log_prob": dist.log_prob(actions).sum(-1),
                     "values": model.critic(model.critic_norm(critic)), "mu": dist.mean, "sigma": dist.stddev}
        batch["advantages"] = actions[:, 0] - actions[:, 0].mean()
        batch["returns"] = critic[:, 0] * 2.0 + 1.0
        return model, batch

    return make


@pytest.fixture
def spot_work(monkeypatch):
    """The work of cfrace.flight.landing.spots' landing-spot choice, counted (what bounds its CPU time in the
    tick, the same on every machine): {"path_rule": candidates the rule on other drones' paths looked
    at, "paths_clear": candidates checked for a straight clear way}."""
    import cfrace.flight.landing.spots as ld

    work = {"path_rule": 0, "paths_clear": 0}
    apart, paths_clear = ld._apart, ld.paths_clear

    def counted_apart(start, ends, paths, still, separation):
        if paths:
            work["path_rule"] += len(ends)
        return apart(start, ends, paths, still, separation)

    def counted_paths_clear(track, start, ends, clearance):
        work["paths_clear"] += len(ends)
        return paths_clear(track, start, ends, clearance)

    monkeypatch.setattr(ld, "_apart", counted_apart)
    monkeypatch.setattr(ld, "paths_clear", counted_paths_clear)
    return work
