"""Which opponent should a two-drone policy observe in an N-drone race? Races under each rule.

    .venv/bin/python studies/evaluation/opponent_rules.py [--races 50] [--seeds 1,2] [--lineups ours,ours,ds,ds;ours,ds,ss,dm]
                                                 [--track lemniscate] [--json FILE]

For every lineup, opponent rule (cfrace.contract.observations.OPPONENT_RULES) and seed: the share of
races won by each policy, races without a winner, crashes, crashes while touching another drone
and drone-drone contacts (cfrace.evaluate.field.race_field; one thread). Prints a markdown table
and one JSON document; records the machine's load.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import torch


def main() -> None:
    from cfrace.contract.observations import OPPONENT_RULES
    from cfrace.evaluate.field import race_field

    ap = argparse.ArgumentParser()
    ap.add_argument("--races", type=int, default=50)
    ap.add_argument("--seeds", default="1,2")
    ap.add_argument("--lineups", default="ours,ours,ds,ds;ours,ds,ss,dm")
    ap.add_argument("--track", default="lemniscate")
    ap.add_argument("--rules", default=",".join(OPPONENT_RULES))
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = []
    print("| lineup | rule | seed | first place by policy | no winner | crashes | touching a drone | contacts | cpu s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for lineup in args.lineups.split(";"):
        for rule in args.rules.split(","):
            for seed in (int(s) for s in args.seeds.split(",")):
                c0 = time.process_time()
                r = race_field(args.track, lineup.split(","), races=args.races, seed=seed, opponent_rule=rule)
                causes = r.crash_causes()
                row = {"lineup": lineup, "rule": rule, "seed": seed, "races": args.races,
                       "policy_win_rate": r.policy_win_rates(), "no_winner_rate": float((r.winner < 0).mean()),
                       "crashes": int(r.crashed.sum()),
                       "crashes_touching": int(sum(c["while_touching_a_drone"] for c in causes)),
                       "contacts": int(r.pair_contacts.sum()), "cpu_s": round(time.process_time() - c0, 1)}
                rows.append(row)
                won = ", ".join(f"{p.replace('_' + args.track, '')} {v:.0%}" for p, v in row["policy_win_rate"].items())
                print(f"| {lineup} | {rule} | {seed} | {won} | {row['no_winner_rate']:.0%} | {row['crashes']} | "
                      f"{row['crashes_touching']} | {row['contacts']} | {row['cpu_s']} |", flush=True)
    print("\nover all seeds:\n")
    print("| lineup | rule | races | first place by policy | no winner | crashes per race | touching a drone |")
    print("|---|---|---|---|---|---|---|")
    for lineup in args.lineups.split(";"):
        for rule in args.rules.split(","):
            mine = [r for r in rows if r["lineup"] == lineup and r["rule"] == rule]
            n = sum(r["races"] for r in mine)
            won = {p: sum(r["policy_win_rate"][p] * r["races"] for r in mine) / n for p in mine[0]["policy_win_rate"]}
            won_txt = ", ".join(f"{p.replace('_' + args.track, '')} {v:.1%}" for p, v in won.items())
            nowin = sum(r["no_winner_rate"] * r["races"] for r in mine) / n
            crashes = sum(r["crashes"] for r in mine)
            touching = sum(r["crashes_touching"] for r in mine)
            print(f"| {lineup} | {rule} | {n} | {won_txt} | {nowin:.1%} | {crashes / n:.2f} | {touching / max(crashes, 1):.0%} |")
    doc = {"rows": rows, "load_avg": os.getloadavg(), "track": args.track}
    print(json.dumps(doc))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(doc, f, indent=1)


if __name__ == "__main__":
    main()
