"""Fits of a thrust-stand recording: thrust curve with its voltage dependence, k_eta and motor
speed range, k_m, tau_m; and the complete drone profile they make.

Models (the same the simulator uses, cfrace/sim/dynamics.py):
  rotor thrust      T = k_eta w^2,  yaw torque  k_m w^2 = (k_m / k_eta) T,  sign = spin direction
  motor lag         dw/dt = (w_des - w) / tau_m
  battery           at a fixed command, T ~ V^gamma: the curve is written at REFERENCE_VOLTS
"""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from cfrace.drone import DroneProfile
from cfrace.errors import CfraceError

REFERENCE_VOLTS = 4.0     #: V, battery voltage at which the written thrust curve holds
DEFAULT_GAMMA = 2.0       #: thrust ~ V^2 at a fixed command, assumed when the run cannot separate it
MIN_LOG_V_SPREAD = 2e-3   #: within-level spread of ln V needed to fit gamma


class FitError(CfraceError):
    """The recording cannot give a parameter (too few samples, a curve that does not increase)."""


@dataclass
class Hold:
    """A constant command held on the stand; ``t0..t1`` (host s) is its measuring window."""

    kind: str            #: "all" (the four motors) or "motor"
    motor: int | None    #: 0-3 for kind "motor"
    counts: int
    t0: float
    t1: float

    @property
    def active(self) -> int:
        return 4 if self.kind == "all" else 1


@dataclass
class Step:
    """A step of the lag test (all motors): command from -> to at host time t (window to t_end)."""

    t: float
    from_counts: int
    to_counts: int
    t_end: float


@dataclass
class Recording:
    host: np.ndarray          #: (n,) s, arrival time of each sensor sample (time.monotonic)
    stime: np.ndarray         #: (n,) s, sensor time (its counter / rate, else arrival)
    wrench: np.ndarray        #: (n, 6) body frame about the drone's centre, bias removed
    log_t: np.ndarray         #: (m,) s, arrival time of each log packet
    vbat: np.ndarray          #: (m,) V
    rpm: np.ndarray | None    #: (m, 4) rpm, None when the drone does not log motor speed
    holds: list[Hold] = field(default_factory=list)
    steps: list[Step] = field(default_factory=list)
    info: dict = field(default_factory=dict)   #: date, sensor, bus, uri, ...


@dataclass
class HoldStats:
    hold: Hold
    n: int                 #: sensor samples in the window
    fz: float              #: N, mean thrust
    fz_std: float
    tz: float              #: N m, mean yaw torque
    volts: float           #: V, mean pm.vbat
    omega2: float | None   #: (rad/s)^2, mean squared speed of the active rotors


def hold_stats(rec: Recording) -> list[HoldStats]:
    out = []
    for h in rec.holds:
        s = (rec.host >= h.t0) & (rec.host <= h.t1)
        lg = (rec.log_t >= h.t0) & (rec.log_t <= h.t1)
        if s.sum() < 3 or lg.sum() < 1:
            raise FitError(f"hold at {h.counts} counts ({h.kind}): only {int(s.sum())} sensor samples and "
                           f"{int(lg.sum())} log packets in its window; hold longer")
        w = rec.wrench[s]
        om2 = None
        if rec.rpm is not None:
            w_rad = rec.rpm[lg] * (2.0 * math.pi / 60.0)
            cols = w_rad if h.kind == "all" else w_rad[:, [h.motor]]
            om2 = float(np.mean(cols ** 2))
        out.append(HoldStats(h, int(s.sum()), float(w[:, 2].mean()), float(w[:, 2].std()), float(w[:, 5].mean()),
                             float(rec.vbat[lg].mean()), om2))
    return out


@dataclass
class Fit:
    counts: list[int]              #: thrust curve, counts
    newtons: list[float]           #: collective N at REFERENCE_VOLTS
    gamma: float
    gamma_fitted: bool
    curve_residual: float          #: N RMS, per-rotor thrust of the holds about the model
    k_eta: float | None
    k_eta_residual: float | None   #: relative RMS
    motor_speed_max: float | None
    k_m_ratio: float               #: m, yaw torque per N of thrust
    k_m_ratio_spread: float        #: m, std over single-motor holds
    spin_dirs: list[int]           #: measured spin direction of motors 1-4 (0: not measured)
    tau_m: float                   #: s, the step responses' median times the battery-sag factor
    tau_m_spread: float            #: s, std over steps
    sag: float                     #: the battery-sag factor applied to tau_m (1 + k, see sag_factor)
    tau_steps: list[dict]          #: per step: t (s, rel.), e (normalised error), fitted tau
    stats: list[HoldStats]
    samples: int
    log_packets: int

    def k_m(self, k_eta: float) -> float:
        return self.k_m_ratio * k_eta


def _curve(stats: list[HoldStats]) -> tuple[list[int], list[float], float, bool, float]:
    """Joint least squares: ln(T_rotor) = ln f(c) + gamma ln(V / V_ref) over the holds."""
    use = [s for s in stats if s.fz > 0.0 and s.hold.counts > 0]
    if not use:
        raise FitError("no hold produced thrust: were the propellers on and the drone armed?")
    levels = sorted({s.hold.counts for s in use})
    col = {c: k for k, c in enumerate(levels)}
    y = np.array([math.log(s.fz / s.hold.active) for s in use])
    lv = np.array([math.log(s.volts / REFERENCE_VOLTS) for s in use])
    a = np.zeros((len(use), len(levels)))
    for r, s in enumerate(use):
        a[r, col[s.hold.counts]] = 1.0
    # spread of ln V within each level decides whether gamma can be told apart from the command
    spread = _within_spread(lv, a)
    if spread >= MIN_LOG_V_SPREAD:
        sol, *_ = np.linalg.lstsq(np.column_stack([a, lv]), y, rcond=None)
        logf, gamma, fitted = sol[:-1], float(sol[-1]), True
    else:
        sol, *_ = np.linalg.lstsq(a, y - DEFAULT_GAMMA * lv, rcond=None)
        logf, gamma, fitted = sol, DEFAULT_GAMMA, False
    model = np.exp(a @ logf + gamma * lv)
    resid = float(np.sqrt(np.mean((np.exp(y) - model) ** 2)))
    newtons = [0.0] + [4.0 * math.exp(v) for v in logf]
    counts = [0] + levels
    for k in range(1, len(counts)):
        if newtons[k] <= newtons[k - 1]:
            raise FitError(f"the thrust did not increase from {counts[k - 1]} to {counts[k]} counts "
                           f"({newtons[k - 1]:.4f} -> {newtons[k]:.4f} N): check the sensor axes and the propellers")
    return counts, newtons, gamma, fitted, resid


def _within_spread(lv: np.ndarray, a: np.ndarray) -> float:
    dev = [lv[a[:, k] > 0] - lv[a[:, k] > 0].mean() for k in range(a.shape[1])]
    allv = np.concatenate(dev)
    return float(np.sqrt(np.mean(allv ** 2))) if allv.size else 0.0


def _k_eta(stats: list[HoldStats]) -> tuple[float | None, float | None]:
    pts = [(s.omega2, s.fz / s.hold.active) for s in stats if s.omega2 and s.fz > 0.0]
    if len(pts) < 2:
        return None, None
    x, y = np.array(pts).T
    k = float((x * y).sum() / (x * x).sum())
    return k, float(np.sqrt(np.mean(((y - k * x) / y) ** 2)))


def _k_m_ratio(stats: list[HoldStats], min_fz: float) -> tuple[float, float, list[int]]:
    single = [s for s in stats if s.hold.kind == "motor" and s.fz > min_fz]
    if not single:
        raise FitError("no single-motor hold with thrust: k_m needs the motors one at a time")
    ratios = np.array([s.tz / s.fz for s in single])
    dirs = [0] * 4
    for s, r in zip(single, ratios):
        dirs[s.hold.motor] = 1 if r > 0 else -1
    w = np.array([s.fz for s in single])
    mean = float((np.abs(ratios) * w).sum() / w.sum())
    return mean, float(np.abs(ratios).std()), dirs


def _step_lsq(t: np.ndarray, s: np.ndarray, taus: np.ndarray, t0s: np.ndarray) -> tuple[float, float, float, float, float]:
    """Least squares of s(t) = s1 + (s0 - s1) exp(-max(0, t - t0) / tau) over a (tau, t0) grid, s0 and s1
    solved in closed form at each point. -> (sse, tau, t0, s0, s1)."""
    g = np.exp(-np.clip(t[None, None, :] - t0s[None, :, None], 0.0, None) / taus[:, None, None])   # (T, T0, n)
    h = 1.0 - g
    a, b, c = (g * g).sum(-1), (g * h).sum(-1), (h * h).sum(-1)
    p, q = (g * s).sum(-1), (h * s).sum(-1)
    det = np.where(np.abs(a * c - b * b) < 1e-30, 1e-30, a * c - b * b)
    s0, s1 = (c * p - b * q) / det, (a * q - b * p) / det
    sse = (s * s).sum() - s0 * p - s1 * q
    k = np.unravel_index(int(np.argmin(sse)), sse.shape)
    return float(sse[k]), float(taus[k[0]]), float(t0s[k[1]]), float(s0[k]), float(s1[k])


def _tau(rec: Recording) -> tuple[float, float, list[dict]]:
    """tau_m from the lag test's steps: rotor speed ~ sqrt(thrust) follows a first-order step from an
    unknown instant t0 (when the command reached the motors); least squares over tau and t0 on the
    sensor's own time base, the levels before and after solved with them."""
    taus, curves = [], []
    for st in rec.steps:
        win = (rec.host >= st.t - 0.06) & (rec.host <= st.t_end)
        if win.sum() < 15:
            continue
        t, s = rec.stime[win], np.sqrt(np.maximum(rec.wrench[win, 2], 0.0))
        t = t - t[0]
        _, tau, t0, _, _ = _step_lsq(t, s, np.geomspace(5e-4, 0.3, 120), np.linspace(0.0, t[-1] * 0.6, 120))
        dt = max(t[-1] / 200.0, 2e-4)
        _, tau, t0, s0, s1 = _step_lsq(t, s, np.linspace(tau * 0.85, tau * 1.15, 61),
                                       np.linspace(max(0.0, t0 - 3 * dt), t0 + 3 * dt, 61))
        if not abs(s0 - s1) > 0 or tau >= 0.29:
            continue
        taus.append(tau)
        curves.append({"t": (t - t0).tolist(), "e": ((s - s1) / (s0 - s1)).tolist(), "tau": tau,
                       "from": st.from_counts, "to": st.to_counts})
    if not taus:
        raise FitError("the lag test gave no usable step (too few sensor samples around each step: "
                       "a faster sensor or longer steps)")
    return float(np.median(taus)), float(np.std(taus)), curves


def sag_factor(stats: list[HoldStats], steps: list[Step], gamma: float) -> float:
    """The battery makes a motor look faster: its voltage drops as the thrust rises, which lowers the
    speed the motor heads for (w_des ~ V^(gamma/2)). Linearised about the lag test's thrust T, the
    measured time constant is tau / (1 + k) with k = -gamma T (dV/dT) / V. -> 1 + k, from the
    all-motor holds' voltage against thrust (a parabola's slope at T)."""
    pts = np.array([(s.fz, s.volts) for s in stats if s.hold.kind == "all"])
    if len(pts) < 3 or not steps:
        return 1.0
    mid = np.mean([(st.from_counts + st.to_counts) / 2.0 for st in steps])
    near = min(stats, key=lambda s: abs(s.hold.counts - mid) + (0 if s.hold.kind == "all" else 1e9))
    t_mid = near.fz * (mid / near.hold.counts) if near.hold.counts else near.fz
    c = np.polyfit(pts[:, 0], pts[:, 1], 2)
    slope = 2 * c[0] * t_mid + c[1]
    volts = np.polyval(c, t_mid)
    return float(max(1.0, 1.0 - gamma * t_mid * slope / volts))


def fit_recording(rec: Recording) -> Fit:
    stats = hold_stats(rec)
    counts, newtons, gamma, fitted, resid = _curve(stats)
    k_eta, k_eta_res = _k_eta(stats)
    w_max = None if k_eta is None else math.sqrt(newtons[-1] / (4.0 * k_eta))
    ratio, spread, dirs = _k_m_ratio(stats, 0.05 * newtons[-1] / 4.0)
    tau_raw, tau_sd, curves = _tau(rec)
    sag = sag_factor(stats, rec.steps, gamma)
    tau, tau_sd = tau_raw * sag, tau_sd * sag
    return Fit(counts, newtons, gamma, fitted, resid, k_eta, k_eta_res, w_max, ratio, spread, dirs, tau, tau_sd, sag,
               curves, stats, int(len(rec.host)), int(len(rec.log_t)))


# ---------------------------------------------------------------------------------- the profile
def profile_dict(fit: Fit, base: DroneProfile, name: str, info: dict) -> dict:
    """The complete profile (as YAML data): base's values, the stand's where measured."""
    date = info.get("date") or _dt.date.today().isoformat()
    where = f"cfrace calibrate thrust on {date} (sensor {info.get('sensor', '?')}, {info.get('bus', '?')})"
    single = [s for s in fit.stats if s.hold.kind == "motor"]
    k_eta = fit.k_eta if fit.k_eta is not None else base.k_eta
    w_max = fit.motor_speed_max if fit.motor_speed_max is not None else math.sqrt(fit.newtons[-1] / (4 * k_eta))
    d = {
        "name": name,
        "description": f"{base.name} identified on a thrust stand ({date}): "
                       f"{fit.newtons[-1]:.3f} N collective at {fit.counts[-1]} counts and {REFERENCE_VOLTS:g} V",
        "mass": base.mass, "inertia": list(base.inertia), "arm_length": base.arm_length,
        "rotor_dirs": list(base.rotor_dirs), "k_eta": float(f"{k_eta:.5g}"),
        "k_m": float(f"{fit.k_m(k_eta):.5g}"), "tau_m": float(f"{fit.tau_m:.4g}"),
        "motor_speed": [0.0, float(f"{w_max:.5g}")], "max_thrust_weights": base.max_thrust_weights,
        "max_rates_deg": list(base.max_rates_deg),
        "pid_roll_pitch": dict(vars(base.pid_roll_pitch)), "pid_yaw": dict(vars(base.pid_yaw)),
        "k_aero": list(base.k_aero), "collision_box": list(base.collision_box),
        "thrust_curve": {"counts": list(fit.counts), "newtons": [float(f"{v:.5g}") for v in fit.newtons]},
    }
    sources = dict(base.sources)
    n_all = sum(s.n for s in fit.stats if s.hold.kind == "all")
    gamma_text = (f"thrust ~ V^{fit.gamma:.2f} fitted" if fit.gamma_fitted else
                  f"thrust ~ V^{fit.gamma:g} assumed (the run's voltages did not separate it)")
    sources["thrust_curve"] = (f"measured with {where}: {len([s for s in fit.stats if s.hold.kind == 'all'])} "
                               f"all-motor and {len(single)} single-motor holds, {n_all} samples all-motor, fit residual "
                               f"{fit.curve_residual * 1e3:.2f} mN RMS per rotor; written at {REFERENCE_VOLTS:g} V, "
                               f"{gamma_text}")
    if fit.k_eta is not None:
        sources["k_eta"] = (f"measured with {where}: thrust against logged motor speed (rpm.m1-m4) over "
                            f"{len([s for s in fit.stats if s.omega2])} holds, {fit.log_packets} log packets, fit "
                            f"residual {fit.k_eta_residual * 100:.2f} % RMS")
        sources["motor_speed"] = ("measured with " + where + ": max = the speed that gives the curve's top "
                                  f"thrust with the measured k_eta (4 k_eta w_max^2 = {fit.newtons[-1]:.4g} N)")
    else:
        sources["k_eta"] = f"{base.name} (the drone logs no motor speed, the stand cannot separate k_eta)"
        sources["motor_speed"] = f"derived: 4 k_eta w_max^2 = the measured curve's top ({where})"
    sources["k_m"] = (f"measured with {where}: yaw torque per thrust {fit.k_m_ratio * 1e3:.3f} mm over "
                      f"{len(single)} single-motor holds ({sum(s.n for s in single)} samples), spread "
                      f"{fit.k_m_ratio_spread * 1e3:.3f} mm, times k_eta")
    sources["tau_m"] = (f"measured with {where}: {len(fit.tau_steps)} step responses, median, spread "
                        f"{fit.tau_m_spread * 1e3:.2f} ms, x {fit.sag:.3f} for the battery's sag")
    d["sources"] = sources
    return d


def write_profile(path: Path, data: dict) -> None:
    header = ("# Drone profile written by `cfrace calibrate thrust` (docs/calibration.md). Measured values\n"
              "# say so in `sources:`; the others are the base profile's.\n")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    body = {k: v for k, v in data.items() if k != "sources"}
    text = yaml.safe_dump(body, sort_keys=False, default_flow_style=None, width=200)
    text += yaml.safe_dump({"sources": data["sources"]}, sort_keys=False, default_flow_style=False, width=100000)
    Path(path).write_text(header + text)


def compare(recovered: DroneProfile, true: DroneProfile, step: int = 500) -> dict:
    """Errors of a recovered profile against the true one: thrust curve (max over the recovered
    curve's command range, % of the true full-scale thrust there), k_m, tau_m, k_eta (%)."""
    top = recovered.thrust_curve.counts[-1]
    grid = np.arange(0, top + 1, step, dtype=np.float64)
    full = float(true.thrust_curve.to_newtons(top))
    err = np.abs(recovered.thrust_curve.to_newtons(grid) - true.thrust_curve.to_newtons(grid))
    pct = lambda a, b: 100.0 * abs(a - b) / abs(b)  # noqa: E731
    return {"curve_max_err_pct_fs": float(100.0 * err.max() / full), "curve_full_scale_n": full,
            "curve_worst_counts": int(grid[int(err.argmax())]),
            "k_m_err_pct": pct(recovered.k_m, true.k_m), "tau_m_err_pct": pct(recovered.tau_m, true.tau_m),
            "k_eta_err_pct": pct(recovered.k_eta, true.k_eta),
            "max_thrust_err_pct": pct(recovered.max_collective_thrust, true.max_collective_thrust)}
