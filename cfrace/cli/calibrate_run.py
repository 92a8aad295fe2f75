"""One thrust-stand identification: run the stand's plan (a real stand or a simulated one in this
process), fit, write the profile, plot, and report (what `cfrace calibrate thrust` does)."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Callable

from cfrace.calibrate.fit import compare, fit_recording, profile_dict, write_profile
from cfrace.calibrate.plots import plot_fits, summary_lines
from cfrace.calibrate.procedure import Plan, run_stand
from cfrace.calibrate.sensor import SensorSpec
from cfrace.drone import DroneProfile, load_profile


def calibrate_thrust(out_path: Path, spec: SensorSpec, plan: Plan, base: DroneProfile, truth: DroneProfile | None,
                     folder: Path, *, uri: str | None, bus: str | None, simulate: str | None = None, seed: int = 0,
                     confirmed: bool = False, say: Callable[[str], None] = print) -> dict:
    """Identify the drone at ``uri`` (its sensor ``spec`` on ``bus``) or, with ``simulate`` (a profile
    name), a simulated Crazyflie whose true parameters are ``truth`` on a simulated stand (bus
    can://virtual/stand unless ``bus``). Writes the profile ``out_path`` (unmeasured values from
    ``base``), the plots and ``folder``/report.json; returns the report (compared with ``truth`` when
    given)."""
    say(f"stand plan: {len(plan.levels)} levels up and down, all motors then M"
        + ", M".join(str(m + 1) for m in plan.motors) + f" alone, {plan.tau_repeats} lag-step pairs; about "
        f"{plan.duration():.0f} s")
    t0 = time.monotonic()
    if simulate is not None:
        from cfrace.rehearsal.thrust_stand import SimStand   # the simulated drone and stand: only when asked for

        bus = bus or "can://virtual/stand"
        with SimStand(profile=truth, sensor=spec, bus=bus, seed=seed) as stand:
            say(f"simulated stand: {simulate} on {stand.uri}, sensor {spec.name} on {bus}")
            rec = run_stand(stand.uri, spec, bus, plan, confirmed=confirmed, out=say)
    else:
        rec = run_stand(uri, spec, bus, plan, confirmed=confirmed, out=say)
    run_s = time.monotonic() - t0
    fit = fit_recording(rec)
    write_profile(out_path, profile_dict(fit, base, out_path.stem, rec.info))
    written = load_profile(out_path)       # the strict loader: what train / eval / sim / fly will read
    plots = plot_fits(fit, rec, folder, truth)
    for line in summary_lines(fit):
        say(line)
    result = {"profile": str(out_path), "run_s": run_s, "samples": fit.samples, "log_packets": fit.log_packets,
              "info": rec.info, "gamma": fit.gamma, "gamma_fitted": fit.gamma_fitted, "k_eta": written.k_eta,
              "k_m": written.k_m, "tau_m": written.tau_m, "motor_speed": list(written.motor_speed),
              "thrust_curve": {"counts": list(written.thrust_curve.counts), "newtons": list(written.thrust_curve.newtons)},
              "plots": [str(p) for p in plots]}
    if truth is not None:
        cmp = compare(written, truth)
        result["compare"] = {"truth": truth.name, **cmp}
        say(f"against {truth.name}: thrust curve within {cmp['curve_max_err_pct_fs']:.2f} % of full scale "
            f"(worst at {cmp['curve_worst_counts']} counts), k_m {cmp['k_m_err_pct']:.2f} %, tau_m "
            f"{cmp['tau_m_err_pct']:.2f} %, k_eta {cmp['k_eta_err_pct']:.2f} %")
    (folder / "report.json").write_text(json.dumps(result, indent=1) + "\n")
    return result
