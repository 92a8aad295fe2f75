"""Plots of every stand fit (matplotlib Agg, PNG): thrust curve, voltage dependence, k_eta, k_m, tau_m."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from cfrace.calibrate.fit import REFERENCE_VOLTS, Fit, Recording
from cfrace.drone import DroneProfile


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_fits(fit: Fit, rec: Recording, folder: Path, true: DroneProfile | None = None) -> list[Path]:
    """Write thrust_curve.png, voltage.png, k_eta.png (when rotor speeds were logged), k_m.png and
    tau_m.png to ``folder``; each figure is drawn by one of the functions below."""
    plt = _plt()
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    figures = [_thrust_curve_fig, _voltage_fig] + ([_k_eta_fig] if fit.k_eta is not None else []) + [_k_m_fig, _tau_m_fig]
    paths = []
    for draw in figures:
        fig, ax = plt.subplots(figsize=(6.4, 4.2))
        xlabel, ylabel, title, name, legend = draw(ax, fit, true)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.set_title(title)
        ax.grid(alpha=0.3, which="both")
        ax.legend(**({"fontsize": 8} | legend))
        fig.tight_layout()
        fig.savefig(folder / name, dpi=110)
        plt.close(fig)
        paths.append(folder / name)
    return paths


def _thrust_curve_fig(ax, fit: Fit, true: DroneProfile | None):
    """Each hold scaled to the reference voltage and to four rotors, the fitted and the true curve."""
    for kind, marker, label in (("all", "o", "all motors"), ("motor", "x", "one motor x 4")):
        pts = [(s.hold.counts, 4.0 / s.hold.active * s.fz * (REFERENCE_VOLTS / s.volts) ** fit.gamma)
               for s in fit.stats if s.hold.kind == kind]
        if pts:
            ax.plot(*np.array(pts).T, marker, ms=5, label=f"{label} (at {REFERENCE_VOLTS:g} V)", alpha=0.8)
    ax.plot(fit.counts, fit.newtons, "-", color="k", lw=1.2, label=f"fit, residual {fit.curve_residual * 1e3:.2f} mN/rotor")
    if true is not None:
        c = np.linspace(0, fit.counts[-1], 200)
        ax.plot(c, true.thrust_curve.to_newtons(c), "--", color="tab:red", lw=1, label=f"true ({true.name})")
    return "motor command (counts)", "collective thrust (N)", "thrust curve", "thrust_curve.png", {}


def _voltage_fig(ax, fit: Fit, true: DroneProfile | None):
    """Per-rotor thrust over the curve's value at the reference voltage."""
    curve = dict(zip(fit.counts, fit.newtons))
    pts = np.array([(s.volts / REFERENCE_VOLTS, s.fz / s.hold.active / (curve[s.hold.counts] / 4.0))
                    for s in fit.stats if s.hold.counts in curve and s.fz > 0])
    ax.plot(pts[:, 0], pts[:, 1], "o", ms=4, label="holds")
    v = np.linspace(pts[:, 0].min(), pts[:, 0].max(), 50)
    ax.plot(v, v ** fit.gamma, "k-", label=f"(V / V_ref)^{fit.gamma:.2f} ({'fitted' if fit.gamma_fitted else 'assumed'})")
    return (f"battery voltage / {REFERENCE_VOLTS:g} V", "thrust / thrust at the reference voltage",
            "voltage dependence", "voltage.png", {})


def _k_eta_fig(ax, fit: Fit, true: DroneProfile | None):
    """Thrust per rotor against the logged rotor speed squared."""
    x = np.array([s.omega2 for s in fit.stats if s.omega2])
    y = np.array([s.fz / s.hold.active for s in fit.stats if s.omega2])
    ax.plot(x, y, "o", ms=4, label="holds (thrust per rotor)")
    xx = np.linspace(0, x.max(), 50)
    ax.plot(xx, fit.k_eta * xx, "k-", label=f"k_eta = {fit.k_eta:.4g} N/(rad/s)^2, residual "
                                            f"{fit.k_eta_residual * 100:.2f} %")
    return ("rotor speed^2 from rpm.m1-m4 ((rad/s)^2)", "thrust per rotor (N)", "thrust coefficient",
            "k_eta.png", {})


def _k_m_fig(ax, fit: Fit, true: DroneProfile | None):
    """Yaw torque against the thrust of the one running motor, with the fitted ratio."""
    st = fit.stats
    for s in st:
        if s.hold.kind == "motor":
            ax.plot(s.fz, s.tz * 1e3, "o", ms=4, color=f"C{s.hold.motor}")
    for m in range(4):
        if fit.spin_dirs[m]:
            ax.plot([], [], "o", color=f"C{m}", label=f"M{m + 1} (spin {fit.spin_dirs[m]:+d})")
    f = np.linspace(0, max(s.fz for s in st if s.hold.kind == "motor"), 20)
    for sign in (1, -1):
        ax.plot(f, sign * fit.k_m_ratio * f * 1e3, "k-", lw=0.8)
    return ("thrust of the one running motor (N)", "yaw torque (mN m)",
            f"yaw torque per thrust {fit.k_m_ratio * 1e3:.3f} mm (k_m = that x k_eta)", "k_m.png", {})


def _tau_m_fig(ax, fit: Fit, true: DroneProfile | None):
    """The step responses' normalised errors on a log scale, with the fitted lag."""
    for k, c in enumerate(fit.tau_steps):
        t, e = np.array(c["t"]), np.array(c["e"])
        ok = e > 0
        ax.semilogy(t[ok] * 1e3, e[ok], ".", ms=3, color=f"C{k % 10}",
                    label=f"{c['from']} -> {c['to']}: {c['tau'] * 1e3:.1f} ms")
    tt = np.linspace(0, 4 * fit.tau_m, 20)
    ax.semilogy(tt * 1e3, np.exp(-tt * fit.sag / fit.tau_m), "k-", lw=1.5,
                label=f"median {fit.tau_m / fit.sag * 1e3:.1f} ms (tau_m {fit.tau_m * 1e3:.1f} ms after the sag)")
    ax.set_ylim(0.02, 1.5)
    ax.set_xlim(-3 * fit.tau_m * 1e3, 5 * fit.tau_m * 1e3)
    return ("time from the fitted start of the step (ms)", "normalised error of sqrt(thrust)",
            "motor lag (step responses)", "tau_m.png", {"fontsize": 7, "ncol": 2})


def summary_lines(fit: Fit) -> list[str]:
    lines = [f"thrust curve: {len(fit.counts)} points, {fit.newtons[-1]:.4f} N at {fit.counts[-1]} counts "
             f"({REFERENCE_VOLTS:g} V), residual {fit.curve_residual * 1e3:.2f} mN per rotor; thrust ~ V^{fit.gamma:.2f} "
             f"({'fitted' if fit.gamma_fitted else 'assumed'})"]
    if fit.k_eta is not None:
        lines.append(f"k_eta {fit.k_eta:.4g} N/(rad/s)^2 (residual {fit.k_eta_residual * 100:.2f} %), "
                     f"motor speed max {fit.motor_speed_max:.0f} rad/s ({fit.motor_speed_max * 60 / (2 * math.pi):.0f} rpm)")
    lines.append(f"yaw torque per thrust {fit.k_m_ratio * 1e3:.3f} mm (spread {fit.k_m_ratio_spread * 1e3:.3f}), "
                 f"spin directions M1-M4 {fit.spin_dirs} (0: not measured)")
    lines.append(f"tau_m {fit.tau_m * 1e3:.2f} ms over {len(fit.tau_steps)} steps (spread {fit.tau_m_spread * 1e3:.2f} ms; "
                 f"x {fit.sag:.3f} for the battery's sag)")
    return lines
