"""`cfrace eval`, `cfrace race`, `cfrace tournament`: thin commands over cfrace.evaluate."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import List, Optional

import typer

from cfrace.cli.common import check_folder, check_writable, write_json
from rich.console import Console
from rich.table import Table

from cfrace.contract.observations import DEFAULT_OPPONENT_RULE

# tables are wide: piped output gets 160 columns unless COLUMNS says otherwise
console = Console(width=None if sys.stdout.isatty() or os.environ.get("COLUMNS") else 160)

_TRACK = typer.Option(..., "--track", help="track name (tracks/NAME.yaml) or path")
_OBST = typer.Option(False, "--obstacles", help="race with the track's obstacles")
_LAPS = typer.Option(3, "--laps", min=1, help="laps per run / race")
_SEED = typer.Option(0, "--seed", help="seed of the start poses")
_LIMIT = typer.Option(None, "--time-limit", min=0.1, help="s per run / race (default 15 s per lap)")
_PROFILE = typer.Option(None, "--profile", help="drone profile (default: the one the policies name)")
_JSON = typer.Option(None, "--json", help="write the results to this JSON file")


def _write_json(path: Optional[Path], data: dict) -> None:
    write_json(data, path, console, indent=2)


def _check_outputs(json_out: Optional[Path] = None, md: Optional[Path] = None, plot: Optional[Path] = None,
                   heatmap: Optional[Path] = None) -> None:
    """One line (ConfigError) before any race flies when an output cannot be written."""
    check_writable(json_out, "--json")
    check_writable(md, "--md")
    check_writable(heatmap, "--heatmap")
    check_folder(plot, "--plot")


def _f(v, spec: str = ".2f") -> str:
    return "–" if v is None else format(v, spec)


def eval_cmd(
    policies: List[str] = typer.Argument(..., help="policy paths or short names (ours, ds, ss, dm)"),
    track: str = _TRACK, obstacles: bool = _OBST,
    runs: int = typer.Option(50, "--runs", min=1, help="runs per policy"),
    laps: int = _LAPS, seed: int = _SEED, time_limit: Optional[float] = _LIMIT, profile: Optional[str] = _PROFILE,
    json_out: Optional[Path] = _JSON,
    md_out: Optional[Path] = typer.Option(None, "--md", help="write the table as markdown to this file"),
    plot: Optional[Path] = typer.Option(None, "--plot", help="folder for trajectory PNGs (one per policy)"),
    start: str = typer.Option("gate", "--start", help="gate: in the air before a random gate (the paper's "
                                                      "benchmark); ground: on the floor before gate 0"),
) -> None:
    """Single-agent benchmark (paper Table I): N runs of L laps per policy from random gate starts."""
    from cfrace.evaluate.single import evaluate, markdown_table

    _check_outputs(json_out=json_out, md=md_out, plot=plot)

    r = evaluate(list(policies), track, obstacles, runs, laps, seed, time_limit, profile, plot, start=start)
    t = Table(title=f"single-agent benchmark: {r.track}{' with obstacles' if r.obstacles else ''}, {r.runs} runs x "
                    f"{r.laps} laps, seed {r.seed} ({r.wall_s:.1f} s)")
    for col in ("policy", "method", "Avg. TTC [s]", "Avg. speed [m/s]", "Collisions", "Success [%]", "best lap [s]",
                "max speed [m/s]", "crashes", "time-outs"):
        t.add_column(col, justify="left" if col in ("policy", "method") else "right")
    for row in r.rows:
        t.add_row(row["name"], row["method"], _f(row["lap_time_s"]), _f(row["avg_speed_mps"]), str(row["collisions"]),
                  f"{100 * row['success_rate']:.0f}", _f(row["best_lap_s"]), _f(row["max_speed_mps"]),
                  str(row["crashes"]), str(row["timeouts"]))
    console.print(t)
    _write_json(json_out, r.to_json())
    if md_out is not None:
        md_out.parent.mkdir(parents=True, exist_ok=True)
        md_out.write_text(markdown_table(r))
        console.print(f"wrote {md_out}")
    for p in r.plots:
        console.print(f"wrote {p}")


def race_cmd(
    track: str = _TRACK,
    ego: Optional[str] = typer.Option(None, "--ego", help="ego policy (drone 0): path or short name"),
    opp: Optional[str] = typer.Option(None, "--opp", help="opponent policy (drone 1): path or short name"),
    entrants: Optional[str] = typer.Option(None, "--entrants",
                                           help="N-drone race instead of --ego/--opp: A,B,C,D (paths or short "
                                                "names, repeats allowed; drone k flies the k-th)"),
    opponent_rule: str = typer.Option(DEFAULT_OPPONENT_RULE, "--opponent-rule",
                                      help="with --entrants (more than 2): which drone a policy without its own "
                                           "rule observes: nearest | ahead | track"),
    obstacles: bool = _OBST,
    races: int = typer.Option(50, "--races", min=1, help="races (half of them swap the starting slots)"),
    laps: int = _LAPS, seed: int = _SEED, time_limit: Optional[float] = _LIMIT, profile: Optional[str] = _PROFILE,
    json_out: Optional[Path] = _JSON,
    plot: Optional[Path] = typer.Option(None, "--plot", help="folder for trajectory and speed-profile PNGs"),
    start: str = typer.Option("gate", "--start", help="gate: in the air before a random gate (the paper's "
                                                      "races); ground: side by side on the floor before gate 0"),
) -> None:
    """Head-to-head races: the first to complete the laps wins; a crash of both is a draw. With
    --entrants: races of N drones, finishing order, win rates, crash causes, contacts by pair."""
    from cfrace.errors import ConfigError
    from cfrace.evaluate.race import race

    _check_outputs(json_out=json_out, plot=plot)
    if entrants is not None:
        if ego is not None or opp is not None:
            raise ConfigError("give either --entrants A,B,... or --ego and --opp, not both")
        names = [x.strip() for x in entrants.split(",")]
        if any(not x for x in names):
            raise ConfigError(f"--entrants {entrants!r}: an empty name in the list")
        _field_race(track, names, obstacles, races, laps, seed, time_limit, profile, json_out, plot, start,
                    opponent_rule)
        return
    if ego is None or opp is None:
        raise ConfigError("give --ego and --opp (two drones) or --entrants A,B,C,... (N drones)")

    r = race(track, ego, opp, obstacles, races, laps, seed, time_limit, profile, plot, start=start)
    rates = r.rates()
    c = rates["counts"]
    t = Table(title=f"{r.ego} (ego) vs {r.opp} (opp) on {r.track}{' with obstacles' if r.obstacles else ''}: "
                    f"{r.races} races x {r.laps} laps ({r.wall_s:.1f} s)")
    t.add_column("figure")
    t.add_column(r.ego, justify="right")
    t.add_column(r.opp, justify="right")
    t.add_row("win rate", f"{rates['ego_win_rate']:.0%}", f"{rates['opp_win_rate']:.0%}")
    t.add_row("lap time [s]", _f(r.ego_stats["lap_time_s"]), _f(r.opp_stats["lap_time_s"]))
    t.add_row("avg speed [m/s]", _f(r.ego_stats["avg_speed_mps"]), _f(r.opp_stats["avg_speed_mps"]))
    t.add_row("crashes", str(r.ego_stats["crashes"]), str(r.opp_stats["crashes"]))
    t.add_row("collisions", str(r.ego_stats["collisions"]), str(r.opp_stats["collisions"]))
    console.print(t)
    console.print(f"draws {rates['draw_rate']:.0%}: both crashed {c['draw_both_crashed']}, time-out "
                  f"{c['draw_timeout']}, tie {c['draw_tie']}")
    if r.speed_profile:
        for key, label in (("vs_live_opponent", "vs live opponent"), ("vs_crashed_opponent", "vs crashed opponent")):
            s = r.speed_profile[key]
            console.print(f"{r.ego} speed {label}: max {_f(s['max_mps'])} m/s, mean {_f(s['mean_mps'])} m/s, "
                          f"at the finish {_f(s['finish_speed_mps'])} m/s")
    _write_json(json_out, r.to_json())
    for p in r.plots:
        console.print(f"wrote {p}")


def _field_race(track, names, obstacles, races, laps, seed, time_limit, profile, json_out, plot, start,
                rule) -> None:
    from cfrace.evaluate.field import race_field

    r = race_field(track, names, obstacles, races, laps, seed, time_limit, profile, plot, start=start,
                   opponent_rule=rule)
    n = len(r.entrants)
    t = Table(title=f"{n}-drone races on {r.track}{' with obstacles' if r.obstacles else ''}: {r.races} races x "
                    f"{r.laps} laps, opponent rule {r.opponent_rule} ({r.wall_s:.1f} s)")
    for col in ("drone", "policy", "win rate", "mean place", *(f"P{p}" for p in range(1, n + 1)), "lap time [s]",
                "crashes", "crash causes"):
        t.add_column(col, justify="left" if col in ("drone", "policy", "crash causes") else "right")
    causes = r.crash_causes()
    for k, name in enumerate(r.entrants):
        cells = [str(int((r.places[:, k] == p).sum())) for p in range(1, n + 1)]
        why = ", ".join(f"{c} {v}" for c, v in causes[k].items() if v)
        t.add_row(f"{k} {name}", r.policies[k], f"{r.win_rates()[k]:.0%}", f"{r.places[:, k].mean():.2f}", *cells,
                  _f(r.stats[k]["lap_time_s"]), str(r.stats[k]["crashes"]), why or "–")
    console.print(t)
    won = "; ".join(f"{p} {v:.0%}" for p, v in r.policy_win_rates().items())
    console.print(f"first place by policy: {won}; no winner {(r.winner < 0).mean():.0%}")
    pairs = ", ".join(f"{a}-{b} {c['contacts']} ({c['crashes_in_contact']} crashes)"
                      for c in r.contacts_by_pair() for a, b in [c["pair"]])
    console.print(f"drone-drone contacts by pair: {pairs}")
    _write_json(json_out, r.to_json())
    for p in r.plots:
        console.print(f"wrote {p}")


def tournament_cmd(
    policies: List[str] = typer.Argument(..., help="two or more policy paths or short names"),
    track: str = _TRACK, obstacles: bool = _OBST,
    races: int = typer.Option(50, "--races", min=1, help="races per pair (half swap the starting slots)"),
    laps: int = _LAPS, seed: int = _SEED, time_limit: Optional[float] = _LIMIT, profile: Optional[str] = _PROFILE,
    json_out: Optional[Path] = _JSON,
    heatmap: Optional[Path] = typer.Option(None, "--heatmap", help="write the win-rate heatmap PNG here"),
    ray: bool = typer.Option(False, "--ray", help="spread the pairs over Ray workers (a local instance by default)"),
    address: Optional[str] = typer.Option(None, "--address", help="with --ray: the Ray cluster's address"),
    field_size: Optional[int] = typer.Option(None, "--field", min=2,
                                             help="free-for-all: every FIELD-subset of the policies races "
                                                  "--races times; ratings from the placings"),
    opponent_rule: str = typer.Option(DEFAULT_OPPONENT_RULE, "--opponent-rule",
                                      help="with --field > 2: nearest | ahead | track"),
) -> None:
    """Every pair races; a matrix of win rates (row vs column), draws apart, like the paper's Fig. 6.
    With --field N: a free-for-all of N-drone races with an Elo-scale rating."""
    from cfrace.evaluate.race import tournament

    _check_outputs(json_out=json_out, heatmap=heatmap)
    if field_size is not None:
        if ray or address:
            from cfrace.errors import ConfigError

            raise ConfigError("--field races in one process; drop --ray/--address")
        _free_for_all(list(policies), track, field_size, obstacles, races, laps, seed, time_limit, profile,
                      json_out, heatmap, opponent_rule)
        return

    runner = None
    if ray or address:
        from cfrace.sweep.ray_exec import require_ray
        from cfrace.evaluate.ray_tournament import ray_pair_runner

        require_ray()
        runner = ray_pair_runner(address)
    r = tournament(list(policies), track, obstacles, races, laps, seed, time_limit, profile, heatmap,
                   pair_runner=runner)
    t = Table(title=f"tournament on {r.track}{' with obstacles' if r.obstacles else ''}: {r.races} races x {r.laps} "
                    f"laps per pair, win rate of row vs column (draws) ({r.wall_s:.1f} s)")
    t.add_column("policy")
    for n in r.policies:
        t.add_column(n, justify="right")
    t.add_column("average", justify="right")
    for i, n in enumerate(r.policies):
        cells = ["–" if r.win_rate[i][j] is None else f"{r.win_rate[i][j]:.0%} ({r.draw_rate[i][j]:.0%})"
                 for j in range(len(r.policies))]
        t.add_row(n, *cells, _f(r.average_win_rate()[i], ".0%"))
    console.print(t)
    _write_json(json_out, r.to_json())
    for p in r.plots:
        console.print(f"wrote {p}")


def _free_for_all(policies, track, field_size, obstacles, races, laps, seed, time_limit, profile, json_out, plot,
                  rule) -> None:
    from cfrace.evaluate.field import free_for_all

    r = free_for_all(policies, track, field_size, obstacles, races, laps, seed, time_limit, profile, plot,
                     opponent_rule=rule)
    t = Table(title=f"free-for-all on {r.track}: fields of {r.field_size}, {len(r.heats)} heats x {r.races} races, "
                    f"{r.laps} laps, opponent rule {r.opponent_rule} ({r.wall_s:.1f} s)")
    for col in ("policy", "rating", "races", "wins", "mean place"):
        t.add_column(col, justify="left" if col == "policy" else "right")
    for i in sorted(range(len(r.policies)), key=lambda i: -r.rating[i]):
        t.add_row(r.policies[i], f"{r.rating[i]:.0f}", str(r.starts[i]), str(r.wins[i]), f"{r.mean_place[i]:.2f}")
    console.print(t)
    _write_json(json_out, r.to_json())
    for p in r.plots:
        console.print(f"wrote {p}")


def register(app: typer.Typer) -> None:
    """Add `eval`, `race` and `tournament`."""
    app.command("eval")(eval_cmd)
    app.command("race")(race_cmd)
    app.command("tournament")(tournament_cmd)
