"""The reproduction report's claims and its markdown (cfrace.reproduction.evidence makes the data)."""

from __future__ import annotations

from cfrace.reproduction import paper
from cfrace.reproduction.paper import SETTINGS, setting_name


def claims(report: dict) -> list[dict]:
    """The paper's claims, each with the measured figure and whether its trend holds here."""
    out = []
    rows = {(r["scheme"], r["setting"]): r for r in report["table_i"] if r["success"] is not None}

    def add(text: str, measured, paper_value, holds) -> None:
        out.append({"claim": text, "measured": measured, "paper": paper_value, "holds": holds})

    for track, obstacles in SETTINGS:
        name = setting_name(track, obstacles)
        sec = report["settings"].get(name)
        if sec is None:
            continue
        ovd = sec.get("ours_vs_ds")
        ref = paper.H2H.get(("ours", "ds", track, obstacles))
        if ovd is not None:
            add(f"ours beats DS on the {name}", f"{ovd['default_seed']:.0%} (seed {report['config']['seed']}), "
                f"{ovd['fresh_mean']:.0%} (mean of fresh seeds {ovd['fresh_seeds']})" if ovd["fresh_mean"] is not None
                else f"{ovd['default_seed']:.0%}", f"{ref:.0f} %" if ref is not None else "wins (matrix figure)",
                ovd["default_seed"] > 0.5 and (ovd["fresh_mean"] is None or ovd["fresh_mean"] > 0.5))
        mat = sec.get("matrix")
        if mat is not None and "ours" in mat["average_win_rate"]:
            avg = mat["average_win_rate"]
            best = max(v for v in avg.values() if v is not None)
            add(f"ours has the highest average win rate on the {name}", f"{avg['ours']:.0%}",
                f"{paper.OURS_AVERAGE_WIN:.0f} % (all settings)", avg["ours"] == best)
    ds_obs = {t: rows.get(("ds", setting_name(t, True))) for t in ("lemniscate", "complex")}
    ds_obs = {t: r for t, r in ds_obs.items() if r}
    if ds_obs:
        add(f"the dense reward fails with obstacles ({', '.join(ds_obs)})",
            ", ".join(f"{r['success']:.0%}" for r in ds_obs.values()), ", ".join("0 %" for _ in ds_obs),
            all(r["success"] < 0.5 for r in ds_obs.values()))
    ss_obs = rows.get(("ss", setting_name("lemniscate", True)))
    if ss_obs:
        add("the sparse reward gets through the lemniscate's obstacles", f"{ss_obs['success']:.0%}", "98 %",
            ss_obs["success"] >= 0.5)
    for track in ("lemniscate", "complex"):
        ds, ss = rows.get(("ds", track)), rows.get(("ss", track))
        if ds and ss and ds["ttc_s"] and ss["ttc_s"]:
            add(f"SS laps slower than DS on the {track}", f"{ss['ttc_s']:.2f} vs {ds['ttc_s']:.2f} s",
                {"lemniscate": "5.29 vs 4.76 s", "complex": "6.42 vs 5.68 s"}[track], ss["ttc_s"] > ds["ttc_s"])
    gaps = {(r["track"], r["policy"]): r for r in report.get("transfer", [])}
    for track in ("lemniscate", "complex"):
        o, d = gaps.get((track, "ours")), gaps.get((track, "ds"))
        if o and d and o["speed_gap_mps"] is not None and d["speed_gap_mps"] is not None:
            add(f"ours keeps more of its simulated speed than DS through the flight stack ({track}, speed gap)",
                f"{o['speed_gap_mps']:.2f} vs {d['speed_gap_mps']:.2f} m/s", "0.43 vs 0.76 m/s (real drones)",
                o["speed_gap_mps"] < d["speed_gap_mps"])
            add(f"ours fails less often than DS through the flight stack ({track}, failures per attempted lap)",
                f"{o['stack_failure_rate']:.2f} vs {d['stack_failure_rate']:.2f}", "lower for ours (real drones)",
                o["stack_failure_rate"] <= d["stack_failure_rate"])
    comp = report.get("competition")
    if comp is not None:
        live, dead = comp["measured"]["vs_live_opponent"], comp["measured"]["vs_crashed_opponent"]
        fmt = lambda d: (f"{d.get('max_mps') or float('nan'):.1f} / {d.get('mean_mps') or float('nan'):.1f}"
                         " m/s")
        add("ours flies faster against a live opponent than after it crashed (complex, self-play, max / mean)",
            f"{fmt(live)} vs {fmt(dead)}", "9.9 / 5.9 vs 8.7 / 5.3 m/s", comp["trend_holds"])
    return out


def _f(v, spec=".2f", none="–") -> str:
    return none if v is None else format(v, spec)


def _yes(v) -> str:
    return "–" if v is None else ("yes" if v else "**no**")


def _md_head(report: dict) -> list[str]:
    """Title, what was run, and the claims table."""
    c = report["config"]
    lines: list[str] = []
    size = "quick (a few runs per cell: figures are indicative only)" if c["quick"] else "full"
    lines += [f"# cfrace reproduction report", "",
             f"`cfrace reproduce{' --quick' if c['quick'] else ''}`, commit {report['commit']}, {report['date']}, "
             f"{size}: {c['runs']} runs x {c['laps']} laps per policy, {c['races']} races per pair, seed {c['seed']}, "
             f"fresh seeds {list(c['test_seeds'])}; {report['wall_s']} s. Paper figures: the paper (Table I, "
             "Sec. IV-B and IV-E). A trend holds when the measured figure lands on the same side as the paper's.", ""]
    lines += ["## Claims", "", "| the paper's claim | measured here | paper | trend holds |", "|---|---|---|---|"]
    lines += [f"| {x['claim']} | {x['measured']} | {x['paper']} | {_yes(x['holds'])} |" for x in report["claims"]]
    return lines


def _md_table_i(report: dict) -> list[str]:
    """Table I beside the paper's rows."""
    lines: list[str] = []
    lines += ["", "## Table I: single-agent benchmark", "",
              "| setting | scheme | Avg. TTC [s] | Avg. speed [m/s] | Collisions | Success | paper: TTC, speed, "
              "collisions, success | succeeds/fails as in the paper |", "|---|---|---|---|---|---|---|---|"]
    for r in report["table_i"]:
        p = r["paper"]
        ref = "not in the paper" if p is None else (f"{_f(p['ttc_s'])}, {_f(p['speed_mps'])}, {p['collisions']}, "
                                                    f"{p['success_pct']} %")
        if r["success"] is None:
            lines.append(f"| {r['setting']} | {r['scheme']} | no shipped policy | | | | {ref} | – |")
            continue
        lines.append(f"| {r['setting']} | {r['scheme']} | {_f(r['ttc_s'])} | {_f(r['speed_mps'])} | {r['collisions']} | "
                     f"{r['success']:.0%} | {ref} | {_yes(r['trend_holds'])} |")
    missing = {k: v for k, v in report["missing"].items() if v}
    if missing:
        lines += ["", "No shipped policy (not measured): " +
                  "; ".join(f"{k}: {', '.join(v)}" for k, v in missing.items()) + "."]
    return lines


def _md_matrices(report: dict) -> list[str]:
    """The head-to-head matrices and ours against DS on fresh seeds."""
    c = report["config"]
    lines: list[str] = []
    lines += ["", "## Head-to-head matrices", "", "Win rate of the row policy against the column policy "
              "(draws in the heatmaps); paper cells from its text."]
    for name, sec in report["settings"].items():
        mat = sec["matrix"]
        if mat is None:
            continue
        pols = mat["policies"]
        lines += ["", f"### {name}", "", f"![{name}]({mat['heatmap']})", "",
                  "| | " + " | ".join(pols) + " | average |", "|---" * (len(pols) + 2) + "|"]
        for i, p in enumerate(pols):
            cells = ["–" if v is None else f"{v:.0%}" for v in mat["win_rate"][i]]
            lines.append(f"| {p} | " + " | ".join(cells) + f" | {_f(mat['average_win_rate'][p], '.0%')} |")
        ovd = sec.get("ours_vs_ds")
        if ovd is not None:
            by = ", ".join(f"seed {s}: {w:.0%}" for s, w in ovd["by_seed"].items())
            lines += ["", f"ours vs DS, {c['races']} races each: {by}."]
    return lines


def _md_competition(report: dict) -> list[str]:
    """Ours in self-play on the complex track."""
    lines: list[str] = []
    comp = report.get("competition")
    lines += ["", "## Competition behaviour (complex track, ours in self-play)", ""]
    if comp is None:
        lines.append("No shipped ours policy for the complex track.")
    else:
        m = comp["measured"]
        lines += ["| opponent | max speed [m/s] | mean speed [m/s] | final-gate speed [m/s] | races | paper (max / mean "
                  "/ final gate) |", "|---|---|---|---|---|---|"]
        for key, label in (("vs_live_opponent", "live"), ("vs_crashed_opponent", "crashed")):
            d, p = m[key], comp["paper"][key]
            lines.append(f"| {label} | {_f(d.get('max_mps'))} | {_f(d.get('mean_mps'))} | "
                         f"{_f(d.get('finish_speed_mps'))} | {d.get('races')} | {p['max']} / {p['mean']} / "
                         f"{p['final_gate']} |")
        lines += [""] + [f"![speed]({p})" for p in comp["plots"]]
    return lines


def _md_transfer(report: dict) -> list[str]:
    """DS and ours through the flight stack against the training simulator."""
    lines = ["", "## Transfer through the flight stack (sim-to-sim)", ""]
    t = report.get("transfer_setup")
    if not report.get("transfer") or t is None:
        return lines + ["No track with both a shipped DS and ours policy."]
    lines += [f"DS and ours race each other through the whole flight stack (lockstep dry-run: simulated firmware and "
              f"link, mocap noise {t['noise_m'] * 1e3:.1f} mm, latency {t['latency_s'] * 1e3:.0f} ms compensated) "
              f"on the {t['profile']} profile, against the same number of races from ground starts in the training "
              "simulator on the profile they trained on. Paper (real drones): speed gap DS 0.76, ours 0.43 m/s.", "",
              "| track | policy | races | speed sim [m/s] | speed flight stack [m/s] | gap [m/s] | failures / lap, sim "
              "| failures / lap, stack | collisions / lap, sim | stops in the stack |", "|---" * 10 + "|"]
    for r in report["transfer"]:
        stops = ", ".join(f"{k or 'none'} {v}" for k, v in r["stack_stops"].items()) or "none"
        lines.append(f"| {r['track']} | {r['policy']} | {r['races']} | {_f(r['sim_speed_mps'])} | "
                     f"{_f(r['stack_speed_mps'])} | {_f(r['speed_gap_mps'])} | {r['sim_failure_rate']:.2f} | "
                     f"{r['stack_failure_rate']:.2f} | {r['sim_collision_rate']:.2f} | {stops} |")
    return lines


def _md_robustness(report: dict) -> list[str]:
    """The robustness grid (`cfrace sim robustness`): its table and heat map."""
    from cfrace.evaluate.robustness import markdown_table
    lines = ["", "## Robustness through the flight stack (latency x drone profile x mocap noise)", ""]
    rob = report.get("robustness")
    if not rob:
        return lines + ["No shipped lemniscate ours and DS."]
    g = rob["grid"]
    lines += [f"{g['ego']} and {g['opp']} on the {g['track']}, each alone ({g['laps']} laps, the other stopped at "
              f"once) and head to head ({g['duels']} races per seed), lockstep dry-runs on seeds "
              f"{', '.join(str(s) for s in g['seeds'])}; latency compensated as the dry-run does by default "
              "(docs/robustness.md).", "", markdown_table(rob).rstrip("\n"), "", f"![robustness]({rob['png']})"]
    return lines


def _md_curves(report: dict) -> list[str]:
    """The training curves' PNGs."""
    lines: list[str] = []
    lines += ["", "## Training curves", ""]
    if not report["curves"]:
        lines.append("No training curves in policies/curves/.")
    for cur in report["curves"]:
        runs = "; ".join(f"{k}: {len(v)} run(s)" for k, v in cur["runs"].items())
        lines += [f"![{cur['setting']} {cur['y']}]({cur['png']})", "", f"{cur['setting']}, {cur['y']} ({runs})", ""]
    return lines


def markdown(report: dict) -> str:
    """The report as markdown (tables beside the paper's figures, images by relative path)."""
    parts = (_md_head, _md_table_i, _md_matrices, _md_competition, _md_transfer, _md_robustness, _md_curves)
    return "\n".join(line for part in parts for line in part(report)) + "\n"
