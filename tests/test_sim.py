"""Simulator physics, contacts, gate passing and batching, on both backends (C kernel, torch)."""

from __future__ import annotations

import math

import pytest
import torch

from cfrace.drone import GRAVITY, load_profile
from cfrace.sim import ckernel
from cfrace.sim.simulator import ARENA, CEILING, FLOOR, GATE_FRAME, LONG_CONTACT, NONE, CrashRules, Simulator
from cfrace.track import load_track

BACKENDS = ["torch"] + (["c"] if ckernel.available() else [])
PROFILE = load_profile("cf2x_paper")
LEM = load_track("lemniscate")
CPX = load_track("complex")


def make(backend, track=LEM, worlds=1, drones=1, obstacles=True, **kw) -> Simulator:
    return Simulator(track, PROFILE, worlds, drones, obstacles=obstacles, backend=backend, **kw)


def put(sim, pos, vel=None, target=None, yaw=0.0):
    w, d = sim.num_worlds, sim.num_drones
    pos = torch.as_tensor(pos, dtype=torch.float32).reshape(1, -1, 3).expand(w, d, 3).clone()
    vel = None if vel is None else torch.as_tensor(vel, dtype=torch.float32).reshape(1, -1, 3).expand(w, d, 3).clone()
    q = torch.tensor([math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)]).expand(w, d, 4).clone()
    tgt = None if target is None else torch.full((w, d), target, dtype=torch.int64)
    sim.reset(torch.arange(w), pos, vel=vel, quat=q, target=tgt)


def hover(sim):
    return torch.full((sim.num_worlds, sim.num_drones), PROFILE.weight), torch.zeros(sim.num_worlds, sim.num_drones, 3)


def fly(sim, steps, thrust=None, rates=None, substeps=10):
    th, r = hover(sim)
    th = th if thrust is None else thrust
    r = r if rates is None else rates
    events = []
    for _ in range(steps):
        events.append(sim.step(th, r, substeps))
    return events


@pytest.mark.parametrize("backend", BACKENDS)
def test_hover_holds_altitude(backend):
    sim = make(backend)
    put(sim, [1.0, 5.0, 1.0])
    zs = []
    for _ in range(100):  # 2 s
        fly(sim, 1)
        zs.append(sim.pos[0, 0, 2].item())
    assert max(abs(z - 1.0) for z in zs) < 0.01
    assert not sim.crashed.any()


@pytest.mark.parametrize("backend", BACKENDS)
def test_free_fall_matches_g(backend):
    sim = make(backend)
    put(sim, [1.0, 5.0, 2.5])
    sim.state.motor.zero_()
    t = 0.3
    fly(sim, int(round(t / 0.02)), thrust=torch.zeros(1, 1))
    drop = 2.5 - sim.pos[0, 0, 2].item()
    assert drop == pytest.approx(0.5 * GRAVITY * t * t, rel=0.02)
    assert sim.vel[0, 0, 2].item() == pytest.approx(-GRAVITY * t, rel=0.01)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_rate_step_settles_with_right_sign(backend, axis, sign):
    sim = make(backend)
    put(sim, [1.0, 5.0, 1.5])
    rates = torch.zeros(1, 1, 3)
    rates[0, 0, axis] = sign * 1.0  # rad/s
    fly(sim, 15, rates=rates, substeps=1)  # 30 ms: already the right sign
    assert sign * sim.omega[0, 0, axis].item() > 0.2
    fly(sim, 10, rates=rates, substeps=10)  # 0.2 s more: settled
    assert sim.omega[0, 0, axis].item() == pytest.approx(sign * 1.0, abs=0.05)
    others = [k for k in range(3) if k != axis]
    assert sim.omega[0, 0, others].abs().max().item() < 0.05
    # a positive roll rate rolls right: body y axis tilts down (world z of body y < 0)
    if axis == 0:
        assert sign * sim.rot()[0, 0, 2, 1].item() > 0.0


@pytest.mark.parametrize("backend", BACKENDS)
def test_motor_lag_time_constant(backend):
    sim = make(backend)
    put(sim, [1.0, 5.0, 1.5])
    w0 = sim.motor[0, 0, 0].item()
    th = torch.full((1, 1), 1.5 * PROFILE.weight)
    w_target = math.sqrt(1.5 * PROFILE.weight / 4 / PROFILE.k_eta)
    tau = PROFILE.tau_m
    steps = 5  # 10 ms = 2 tau
    fly(sim, steps, thrust=th, substeps=1)
    # first order: 1 - exp(-t / tau) of the way (PID torques are ~0 in level hover)
    frac = (sim.motor[0, 0].mean().item() - w0) / (w_target - w0)
    assert frac == pytest.approx(1 - math.exp(-steps * 0.002 / tau), abs=0.02)


@pytest.mark.parametrize("backend", BACKENDS)
def test_drag_slows_coasting_drone(backend):
    sim = make(backend)
    put(sim, [-1.5, 4.2, 1.5], vel=[2.0, 0.0, 0.0])
    fly(sim, 25)
    vx = sim.vel[0, 0, 0].item()
    assert 0.5 < vx < 2.0
    # expected deceleration ~ sum(rotor speeds) K_aero v / m
    w_h = math.sqrt(PROFILE.weight / 4 / PROFILE.k_eta)
    k = 4 * w_h * PROFILE.k_aero[0] / PROFILE.mass
    assert vx == pytest.approx(2.0 * math.exp(-k * 0.5), rel=0.1)


# ----------------------------------------------------------------------------- gates
def gate_world(track, idx, local):
    x, y, z, yaw = track.gates[idx]
    c, s = math.cos(yaw), math.sin(yaw)
    return [x + c * local[0] - s * local[1], y + s * local[0] + c * local[1], z + local[2]]


def along(track, idx, speed):
    yaw = track.gates[idx][3]
    return [-speed * math.cos(yaw), -speed * math.sin(yaw), 0.0]


@pytest.mark.parametrize("backend", BACKENDS)
def test_gate_pass_through(backend):
    sim = make(backend)
    put(sim, gate_world(LEM, 0, [0.4, 0.1, 0.05]), vel=along(LEM, 0, 3.0), target=0)
    ev = fly(sim, 10)
    assert sum(int(e.gates[0, 0]) for e in ev) == 1
    assert sim.gates_passed[0, 0].item() == 1 and sim.target[0, 0].item() == 1
    assert not sim.crashed.any()


@pytest.mark.parametrize("backend", BACKENDS)
def test_gate_around_and_backwards_do_not_count(backend):
    sim = make(backend, worlds=2)
    # world 0 flies past beside the gate (outside the frame), world 1 through it backwards
    pos = torch.tensor([gate_world(LEM, 0, [0.4, -1.2, 0.0]), gate_world(LEM, 0, [-0.4, 0.0, 0.0])]).unsqueeze(1)
    vel = torch.tensor([along(LEM, 0, 3.0), along(LEM, 0, -3.0)]).unsqueeze(1)
    sim.reset(torch.arange(2), pos, vel=vel, target=torch.zeros(2, 1, dtype=torch.int64))
    fly(sim, 10)
    assert sim.gates_passed.sum().item() == 0
    assert not sim.crashed.any()


@pytest.mark.parametrize("backend", BACKENDS)
def test_split_s_stacked_gates(backend):
    """Complex track gates 2 (upper, yaw +90 deg) and 3 (lower, yaw -90 deg) share x, y."""
    sim = make(backend, track=CPX, obstacles=False)
    put(sim, gate_world(CPX, 2, [0.4, 0.0, 0.0]), vel=along(CPX, 2, 3.0), target=2)
    fly(sim, 10)
    assert sim.gates_passed[0, 0].item() == 1 and sim.target[0, 0].item() == 3
    # flying through the lower gate in gate 2's direction is backwards for gate 3: no pass
    put(sim, gate_world(CPX, 3, [-0.4, 0.0, 0.0]), vel=along(CPX, 3, -3.0), target=3)
    fly(sim, 10)
    assert sim.gates_passed[0, 0].item() == 0
    # and in its own direction it counts
    put(sim, gate_world(CPX, 3, [0.4, 0.0, 0.0]), vel=along(CPX, 3, 3.0), target=3)
    fly(sim, 10)
    assert sim.gates_passed[0, 0].item() == 1 and sim.target[0, 0].item() == 4
    assert not sim.crashed.any()


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("bar", ["top", "bottom", "left", "right"])
def test_each_frame_bar_is_a_crash(backend, bar):
    local = {"top": [0.3, 0.0, 0.6], "bottom": [0.3, 0.0, -0.6], "left": [0.3, 0.6, 0.0],
             "right": [0.3, -0.6, 0.0]}[bar]
    sim = make(backend, worlds=1)
    put(sim, gate_world(LEM, 3, local), vel=along(LEM, 3, 3.0), target=0)  # not the target gate
    ev = fly(sim, 10)
    assert sim.crashed[0, 0] and sim.reason[0, 0].item() == GATE_FRAME
    assert sum(int(e.crashed_now[0, 0]) for e in ev) == 1  # reported once


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("track", [LEM, CPX], ids=["lemniscate", "complex"])
def test_each_obstacle_is_contact_then_long_contact_crash(backend, track):
    for k, ob in enumerate(track.obstacles):
        sim = make(backend, track=track, worlds=1, obstacles=True)
        # approach the wall through its thin side: the box's local x or y axis
        axis = 0 if ob.size[0] <= ob.size[1] else 1
        yaw = ob.yaw + (0.0 if axis == 0 else math.pi / 2)
        c, s = math.cos(yaw), math.sin(yaw)
        d = ob.size[axis] / 2 + 0.3
        put(sim, [ob.center[0] + c * d, ob.center[1] + s * d, 1.0], vel=[-2.0 * c, -2.0 * s, 0.0])
        ev = fly(sim, 8)
        contact = [bool(e.contact[0, 0]) for e in ev]
        assert any(contact), f"obstacle {k}: no contact"
        assert not sim.crashed[0, 0], f"obstacle {k}: a short contact is not a crash"
        # pushed out: the drone is not inside the box
        p = sim.pos[0, 0]
        depth = c * (p[0] - ob.center[0]) + s * (p[1] - ob.center[1])
        assert depth.item() >= ob.size[axis] / 2, f"obstacle {k}: inside"
        # keep pushing: a long contact ends in a crash
        fly(sim, 30, thrust=torch.full((1, 1), PROFILE.weight), rates=torch.zeros(1, 1, 3))
        put_vel = torch.tensor([-2.0 * c, -2.0 * s, 0.0])
        for _ in range(40):
            sim.state.vel[0, 0] = put_vel
            sim.step(*hover(sim))
            if sim.crashed[0, 0]:
                break
        assert sim.crashed[0, 0] and sim.reason[0, 0].item() == LONG_CONTACT, f"obstacle {k}"


@pytest.mark.parametrize("backend", BACKENDS)
def test_obstacles_off_means_no_contact(backend):
    ob = LEM.obstacles[0]
    sim = make(backend, obstacles=False)
    put(sim, [ob.center[0] + 0.4, ob.center[1], 1.0], vel=[-2.0, 0.0, 0.0])
    ev = fly(sim, 10)
    assert not any(bool(e.contact[0, 0]) for e in ev)


@pytest.mark.parametrize("backend", BACKENDS)
def test_floor_rest_takeoff_and_crashes(backend):
    sim = make(backend, worlds=3)
    z0 = sim.z_rest
    pos = torch.tensor([[[0.0, 5.0, z0]], [[0.0, 5.0, 0.3]], [[1.0, 5.0, 1.0]]])
    vel = torch.tensor([[[0.0, 0.0, 0.0]], [[0.0, 0.0, -4.0]], [[0.0, 0.0, 0.0]]])
    sim.reset(torch.arange(3), pos, vel=vel)
    # world 0 rests with zero thrust for 0.5 s, world 1 slams the floor, world 2 hovers
    thrust = torch.tensor([[0.0], [0.0], [PROFILE.weight]])
    fly(sim, 25, thrust=thrust)
    assert not sim.crashed[0, 0] and abs(sim.pos[0, 0, 2].item() - z0) < 1e-6
    assert sim.crashed[1, 0] and sim.reason[1, 0].item() == FLOOR
    # world 0 takes off
    fly(sim, 20, thrust=torch.full((3, 1), 1.5 * PROFILE.weight))
    assert sim.pos[0, 0, 2].item() > 0.2 and not sim.crashed[0, 0]
    # resting on the floor after the 1 s grace is a crash; without the rule it is not
    sim.reset(torch.arange(3), torch.tensor([1.0, 5.0, z0]).expand(3, 1, 3))
    fly(sim, 60, thrust=torch.zeros(3, 1))
    assert sim.crashed.all() and (sim.reason == FLOOR).all()
    lenient = make(backend, rules=CrashRules(floor_grace_s=None))
    put(lenient, [1.0, 5.0, z0])
    fly(lenient, 60, thrust=torch.zeros(1, 1))
    assert not lenient.crashed.any()


@pytest.mark.parametrize("backend", BACKENDS)
def test_ceiling_and_arena(backend):
    sim = make(backend, worlds=2)
    pos = torch.tensor([[[1.0, 5.0, 2.9]], [[2.4, 5.0, 1.0]]])
    vel = torch.tensor([[[0.0, 0.0, 2.0]], [[2.0, 0.0, 0.0]]])
    sim.reset(torch.arange(2), pos, vel=vel)
    fly(sim, 10)
    assert sim.reason[0, 0].item() == CEILING and sim.reason[1, 0].item() == ARENA


@pytest.mark.parametrize("backend", BACKENDS)
def test_drone_drone_contact(backend):
    sim = make(backend, worlds=1, drones=2)
    pos = torch.tensor([[[0.5, 5.5, 1.5], [1.5, 5.5, 1.5]]])
    vel = torch.tensor([[[2.0, 0.0, 0.0], [-2.0, 0.0, 0.0]]])
    sim.reset(torch.arange(1), pos, vel=vel)
    ev = fly(sim, 20)
    assert any(bool(e.contact[0, 0]) and bool(e.contact[0, 1]) for e in ev)
    d = (sim.pos[0, 0] - sim.pos[0, 1]).norm().item()
    assert d >= 2 * sim.radius - 1e-3  # pushed apart, not through each other
    assert sim.pos[0, 0, 0].item() < sim.pos[0, 1, 0].item()
    assert not sim.crashed.any()  # a short bump is a contact, not a crash


@pytest.mark.parametrize("backend", BACKENDS)
def test_crashed_drone_is_frozen(backend):
    sim = make(backend, worlds=1, drones=2)
    pos = torch.tensor([[[1.0, 5.0, 2.95], [1.5, 5.0, 1.0]]])
    vel = torch.tensor([[[0.0, 0.0, 2.0], [0.0, 0.0, 0.0]]])
    sim.reset(torch.arange(1), pos, vel=vel)
    fly(sim, 5)
    assert sim.crashed[0, 0] and not sim.crashed[0, 1]
    frozen = sim.pos[0, 0].clone()
    ev = fly(sim, 5)
    assert torch.equal(sim.pos[0, 0], frozen) and sim.motor[0, 0].abs().sum() == 0
    assert not any(bool(e.crashed_now[0, 0]) for e in ev)


# ----------------------------------------------------------------------------- batching
def random_run(backend, worlds, seed=0, steps=30):
    g = torch.Generator().manual_seed(seed)
    sim = make(backend, worlds=worlds, drones=2)
    pos = torch.tensor([-1.0, 3.0, 0.5]) + torch.rand(worlds, 2, 3, generator=g) * torch.tensor([2.0, 5.0, 1.5])
    sim.reset(torch.arange(worlds), pos, target=torch.randint(0, 6, (worlds, 2), generator=g))
    cmds = [(PROFILE.weight * (0.6 + 1.2 * torch.rand(worlds, 2, generator=g)),
             (torch.rand(worlds, 2, 3, generator=g) - 0.5) * 3) for _ in range(steps)]
    for th, r in cmds:
        sim.step(th, r)
    return sim, pos, cmds


@pytest.mark.parametrize("backend", BACKENDS)
def test_batched_equals_one_by_one(backend):
    sim, pos, cmds = random_run(backend, 6)
    for w in range(6):
        one = make(backend, worlds=1, drones=2)
        one.reset(torch.arange(1), pos[w:w + 1], target=sim_target0(w))
        for th, r in cmds:
            one.step(th[w:w + 1], r[w:w + 1])
        for name in ("pos", "vel", "quat", "omega", "motor"):
            assert torch.equal(getattr(one, name)[0], getattr(sim, name)[w]), (w, name)
        assert torch.equal(one.crashed[0], sim.crashed[w]) and torch.equal(one.gates_passed[0], sim.gates_passed[w])


def sim_target0(w, seed=0, worlds=6):
    g = torch.Generator().manual_seed(seed)
    torch.rand(worlds, 2, 3, generator=g)
    return torch.randint(0, 6, (worlds, 2), generator=g)[w:w + 1]


@pytest.mark.parametrize("backend", BACKENDS)
def test_partial_reset_leaves_other_worlds_bit_identical(backend):
    a, _, cmds = random_run(backend, 4)
    b, _, _ = random_run(backend, 4)
    b.reset(torch.tensor([1, 3]), torch.tensor([1.0, 5.0, 1.0]).expand(2, 2, 3))
    for th, r in cmds[:5]:
        a.step(th, r)
        b.step(th, r)
    for name in ("pos", "vel", "quat", "omega", "motor"):
        for w in (0, 2):
            assert torch.equal(getattr(a, name)[w], getattr(b, name)[w])
    for field in ("target", "gates_passed", "crashed", "time"):
        for w in (0, 2):
            assert torch.equal(getattr(a, field)[w], getattr(b, field)[w])


@pytest.mark.skipif("c" not in BACKENDS, reason="no C compiler")
def test_c_kernel_matches_torch_reference():
    a, _, _ = random_run("torch", 32, steps=10)
    b, _, _ = random_run("c", 32, steps=10)
    assert torch.equal(a.crashed, b.crashed) and torch.equal(a.reason, b.reason)
    assert torch.equal(a.gates_passed, b.gates_passed) and torch.equal(a.target, b.target)
    live = ~a.crashed
    for name, tol in (("pos", 1e-3), ("vel", 1e-2), ("quat", 1e-3), ("omega", 1e-2)):
        diff = (getattr(a, name) - getattr(b, name))[live].abs().max().item()
        assert diff < tol, (name, diff)


def test_deterministic_given_seed():
    a, _, _ = random_run(BACKENDS[-1], 8)
    b, _, _ = random_run(BACKENDS[-1], 8)
    assert torch.equal(a.pos, b.pos) and torch.equal(a.quat, b.quat)


def test_reason_codes_none_for_live():
    sim = make(BACKENDS[-1])
    put(sim, [1.0, 5.0, 1.0])
    ev = fly(sim, 3)
    assert all(int(e.reason[0, 0]) == NONE for e in ev)


@pytest.mark.parametrize("backend", BACKENDS)
def test_non_finite_command_means_motors_off(backend):
    sim = make(backend, worlds=2)
    put(sim, [1.0, 5.0, 1.0])
    thrust = torch.tensor([[float("nan")], [PROFILE.weight]])
    rates = torch.zeros(2, 1, 3)
    fly(sim, 5, thrust=thrust, rates=rates)
    assert torch.isfinite(sim.pos).all() and torch.isfinite(sim.quat).all()
    assert sim.pos[0, 0, 2].item() < 0.97 and abs(sim.pos[1, 0, 2].item() - 1.0) < 0.01


# ----------------------------------------------------------------------------- C kernel vs torch, contacts
def contact_scenarios(worlds, drones, seed):
    """(W, D, 3) positions and velocities: per world one of gate pass, gate bar, obstacle, floor
    (slow and fast), drone-drone head-on, free flight; drones 0.25 m apart side by side."""
    g = torch.Generator().manual_seed(seed)
    pos, vel = torch.zeros(worlds, drones, 3), torch.zeros(worlds, drones, 3)
    side = (torch.arange(drones) - (drones - 1) / 2) * 0.25
    for w in range(worlds):
        kind, gate = w % 7, int(torch.randint(0, len(LEM.gates), (1,), generator=g))
        j = (torch.rand(drones, 3, generator=g) - 0.5) * 0.1      # jitter, m
        for d in range(drones):
            if kind in (0, 1):       # through the gate opening, or into its bottom bar
                p = gate_world(LEM, gate, [0.8, side[d].item(), 0.0 if kind == 0 else -0.55])
                v = along(LEM, gate, 3.0)
            elif kind == 2:          # into an obstacle wall
                ob = LEM.obstacles[w % len(LEM.obstacles)]
                c, s = math.cos(ob.yaw), math.sin(ob.yaw)
                p = [ob.center[0] + c * (ob.size[0] / 2 + 0.25) - s * side[d].item(),
                     ob.center[1] + s * (ob.size[0] / 2 + 0.25) + c * side[d].item(), 1.0]
                v = [-2.0 * c, -2.0 * s, 0.0]
            elif kind in (3, 4):     # onto the floor, slowly or fast
                p, v = [side[d].item(), 5.0, 0.25], [0.0, 0.0, -1.0 if kind == 3 else -4.0]
            elif kind == 5:          # head-on, drone d from either side
                p, v = [(-0.5 if d % 2 else 0.5), 5.5, 1.0 + 0.06 * d], [(1.5 if d % 2 else -1.5), 0.0, 0.0]
            else:                    # free flight
                p, v = [side[d].item(), 4.0 + 2.0 * d, 1.5], [0.5, 0.5, 0.0]
            pos[w, d], vel[w, d] = torch.tensor(p) + j[d], torch.tensor(v)
    return pos, vel


@pytest.mark.skipif("c" not in BACKENDS, reason="no C kernel")
@pytest.mark.parametrize("drones", [2, 3])
def test_c_kernel_matches_torch_with_contacts(drones):
    """50 policy steps through gates, into bars, obstacles, the floor and each other: the C kernel
    gives the torch reference's events exactly and its positions within 1 mm."""
    worlds = 21
    pos, vel = contact_scenarios(worlds, drones, seed=drones)
    g = torch.Generator().manual_seed(1)
    sims = [make(b, worlds=worlds, drones=drones) for b in ("torch", "c")]
    for sim in sims:
        sim.reset(torch.arange(worlds), pos, vel=vel)
    seen = torch.zeros(5, dtype=torch.bool)
    for step in range(50):
        th = PROFILE.weight * (0.8 + 0.4 * torch.rand(worlds, drones, generator=g))
        rates = (torch.rand(worlds, drones, 3, generator=g) - 0.5) * 2.0
        ev_t, ev_c = (sim.step(th, rates) for sim in sims)
        for name in ev_t._fields:
            assert torch.equal(getattr(ev_t, name), getattr(ev_c, name)), (step, name)
        live = ~sims[0].crashed
        assert torch.equal(sims[0].crashed, sims[1].crashed)
        assert (sims[0].pos - sims[1].pos)[live].abs().max().item() < 1e-3, step
        seen |= torch.stack([ev_t.gates.sum() > 0, ev_t.contact.any(), (ev_t.reason == GATE_FRAME).any(),
                             (ev_t.reason == FLOOR).any(), (ev_t.reason == LONG_CONTACT).any()])
    assert seen.all(), seen  # every kind of event happened


@pytest.mark.skipif("c" not in BACKENDS, reason="no C kernel")
def test_c_kernel_same_with_two_threads_and_one_by_one(monkeypatch):
    """Blocks of whole worlds: 3 drones (5 worlds and a spare lane per block), 11 worlds (a partial
    last block), 1 or 2 threads, batched or world by world: bit-identical."""
    monkeypatch.setattr(ckernel, "MIN_DRONES_PER_THREAD", 1)   # let two threads share 33 drones
    worlds, drones = 11, 3
    pos, vel = contact_scenarios(worlds, drones, seed=5)
    g = torch.Generator().manual_seed(2)
    cmds = [(PROFILE.weight * (0.8 + 0.4 * torch.rand(worlds, drones, generator=g)),
             (torch.rand(worlds, drones, 3, generator=g) - 0.5) * 2.0) for _ in range(30)]
    runs = []
    for threads in (1, 2):
        sim = make("c", worlds=worlds, drones=drones, threads=threads)
        assert sim._kernel.threads == threads
        sim.reset(torch.arange(worlds), pos, vel=vel)
        for th, r in cmds:
            sim.step(th, r)
        runs.append(sim)
    for w in range(worlds):
        one = make("c", worlds=1, drones=drones, threads=1)
        one.reset(torch.arange(1), pos[w:w + 1], vel=vel[w:w + 1])
        for th, r in cmds:
            one.step(th[w:w + 1], r[w:w + 1])
        for name in ("pos", "vel", "quat", "omega", "motor", "crashed", "reason", "gates_passed", "time"):
            for sim in runs:
                assert torch.equal(getattr(one, name)[0], getattr(sim, name)[w]), (w, name)
