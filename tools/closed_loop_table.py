#!/usr/bin/env python3
"""The closed-loop table (issue: image-driven planner + the paper's Table 3 with a ground-truth row): the
image-reading planner (models/e2e-planner, python/b2dr_ref/e2e_planner.py) under each renderer on held-out
synthetic scenarios, R-CLS (IDM agents) and CLS-NR (replayed agents), plus the box-reading planners for
reference. Every number comes from `b2dr run`; this script only runs it and joins the tables.

    ~/.cache/b2dr-venv/bin/python tools/closed_loop_table.py --out out/closed_loop [--scenario LIST | --seeds 100-102]
        [--model PACKAGE] [--resume]

Writes OUT/table.md and OUT/table.json; each run's own folders (comparison.md, per-scenario metrics, mosaics,
diverged/ dumps) stay under OUT/<planner>-<agents>/. Run it with the Python that has torch (the planner's).

One collision moves a six-scenario mean by ~0.17, so a table alone cannot say whether one renderer drives better
than another. With several renderers the table adds, per agents setting, the paired difference of b2dr's score
against each other renderer over the same scenarios: its mean, a bootstrap 95 % interval (resampling scenarios)
and the wins / losses / ties; `--seeds` widens the set (the six layouts at each seed) until the interval can
exclude 0.
"""
import argparse
import json
import os
import shlex
import subprocess
import sys
import time

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LAYOUTS = ["town", "cross", "tjunction", "straight", "curve", "multilane"]
# Held-out (planner trained on seeds 0-23, renderer on 0-3), dense traffic (60 vehicles): a lead vehicle to
# follow or stop behind, which a planner can only see in the image.
DEFAULT_SCENARIOS = ",".join(f"builtin:{l}:100:60" for l in LAYOUTS)
RENDERERS = ["groundtruth", "b2dr", "b2dr-noref-noprev", "log-replay"]
REFERENCE_PLANNERS = ["expert", "idm", "cv"]
METRICS = ["no_ego_at_fault_collisions", "drivable_area_compliance", "driving_direction_compliance",
           "ego_is_making_progress", "time_to_collision_within_bound", "speed_limit_compliance",
           "ego_progress_along_expert_route", "ego_is_comfortable"]


def b2dr(args, log):
    exe = os.path.join(REPO, "target", "release", "b2dr")
    if not os.path.exists(exe):
        sys.exit(f"{exe} is missing: run `cargo build --release` first")
    cmd = [exe, "run"] + args
    print("+ " + " ".join(shlex.quote(c) for c in cmd), file=sys.stderr, flush=True)
    t0 = time.time()
    with open(log, "a") as f:
        r = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, cwd=REPO)
    if r.returncode != 0:
        sys.exit(f"b2dr run failed ({r.returncode}); see {log}")
    print(f"  {time.time() - t0:.0f} s", file=sys.stderr, flush=True)


def seed_scenarios(spec):
    """`--seeds` "A-B" or "A,B,...": the six layouts at each seed, dense traffic, in seed-major order."""
    try:
        if "-" in spec:
            a, b = (int(x) for x in spec.split("-"))
            seeds = list(range(a, b + 1))
        else:
            seeds = [int(x) for x in spec.split(",")]
    except ValueError:
        raise SystemExit(f"--seeds {spec!r}: expected A-B or a comma-separated list of integers")
    if not seeds:
        raise SystemExit(f"--seeds {spec!r}: no seed (A-B needs A <= B)")
    return ",".join(f"builtin:{lay}:{s}:60" for s in seeds for lay in LAYOUTS)


def paired_difference(a, b, resamples=10000, seed=0):
    """Paired comparison of two renderers' per-scenario scores (same scenarios, same order): the mean of a - b,
    its percentile-bootstrap 95 % interval over scenarios (resampled with replacement; fixed seed, so a table
    is reproducible), and the wins / losses / ties of a (|d| <= 1e-9 a tie)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.ndim != 1 or a.shape != b.shape or len(a) == 0:
        raise ValueError("paired_difference: two equal-length, non-empty score lists")
    d = a - b
    rng = np.random.default_rng(seed)
    means = d[rng.integers(0, len(d), size=(resamples, len(d)))].mean(axis=1)
    lo, hi = np.percentile(means, [2.5, 97.5])
    return {"n": len(d), "mean": float(d.mean()), "lo": float(lo), "hi": float(hi),
            "wins": int((d > 1e-9).sum()), "losses": int((d < -1e-9).sum()), "ties": int((abs(d) <= 1e-9).sum())}


def verdict(p):
    """What a paired interval says about "a above b"."""
    if p["lo"] > 0:
        return "above (interval excludes 0)"
    if p["hi"] < 0:
        return "below (interval excludes 0)"
    return "not separable (interval contains 0)"


def paired_rows(scores, first="b2dr"):
    """scores: renderer -> per-scenario scores. The paired comparison of `first` against every other renderer."""
    if first not in scores:
        return []
    return [dict(renderer=r, **paired_difference(scores[first], s)) for r, s in scores.items() if r != first]


def mean_metrics(metrics_json):
    sc = metrics_json["scenarios"]
    return {k: sum(s["metrics"][k] for s in sc) / max(1, len(sc)) for k in METRICS}


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--out", required=True)
    p.add_argument("--scenario", default=None, help=f"scenario list (default: {DEFAULT_SCENARIOS})")
    p.add_argument("--seeds", default=None,
                   help="instead of --scenario: the six layouts, dense, at each seed of A-B or A,B,... (held-out: >= 100)")
    p.add_argument("--planner-model", default=os.path.join(REPO, "models", "e2e-planner"))
    p.add_argument("--renderers", default=",".join(RENDERERS))
    p.add_argument("--model", help="model package of the b2dr renderers (b2dr run --model; default: its built-in)")
    p.add_argument("--resume", action="store_true", help="skip scenarios already done (b2dr run --resume)")
    a = p.parse_args()
    if a.scenario and a.seeds:
        sys.exit("--scenario and --seeds: give one of them")
    a.scenario = seed_scenarios(a.seeds) if a.seeds else (a.scenario or DEFAULT_SCENARIOS)
    os.makedirs(a.out, exist_ok=True)
    log = os.path.join(a.out, "runs.log")
    e2e = (f"cmd:cd {shlex.quote(os.path.join(REPO, 'python'))} && exec {shlex.quote(sys.executable)} "
           f"-m b2dr_ref.e2e_planner serve --weights {shlex.quote(os.path.abspath(a.planner_model))}")
    common = ["--scenario", a.scenario, "--no-gif"] + (["--resume"] if a.resume else [])
    model = []
    if a.model:
        model = ["--model", a.model if a.model.startswith("builtin:") else os.path.abspath(a.model)]
    rows, paired = [], {}
    for agents, kind in [("idm", "R-CLS"), ("replay", "CLS-NR")]:
        out = os.path.join(a.out, f"e2e-{agents}")
        b2dr(common + model + ["--renderer", a.renderers, "--planner", e2e, "--cameras", "CAM_FRONT",
                               "--agents", agents, "--out", out], log)
        if "," in a.renderers:
            comp = json.load(open(os.path.join(out, "comparison.json")))
            for r in comp["rows"]:
                m = json.load(open(os.path.join(out, r["renderer"], "metrics.json")))
                rows.append({"planner": "e2e (images)", "renderer": r["renderer"], "kind": kind, "cls": r["cls"],
                             "metrics": mean_metrics(m), "failures": r["failures"],
                             "scenarios": len(m["scenarios"]), "diverged": comp.get("diverged", [])})
            per = {}
            for r in comp["rows"]:
                sc = json.load(open(os.path.join(out, r["renderer"], "metrics.json")))["scenarios"]
                per[r["renderer"]] = [s["score"] for s in sc]
                if [s["scenario"] for s in sc] != [s["scenario"] for s in m["scenarios"]]:
                    sys.exit(f"{out}: the renderers' scenario lists differ; cannot pair them")
            paired[kind] = paired_rows(per)
        else:
            m = json.load(open(os.path.join(out, "metrics.json")))
            rows.append({"planner": "e2e (images)", "renderer": a.renderers, "kind": kind, "cls": m["cls"],
                         "metrics": mean_metrics(m), "failures": sum(s["failure"] is not None for s in m["scenarios"]),
                         "scenarios": len(m["scenarios"]), "diverged": []})
        for pl in REFERENCE_PLANNERS:
            out = os.path.join(a.out, f"{pl}-{agents}")
            b2dr(common + ["--renderer", "none", "--planner", pl, "--agents", agents, "--out", out], log)
            m = json.load(open(os.path.join(out, "metrics.json")))
            rows.append({"planner": f"{pl} (boxes)", "renderer": "none", "kind": kind, "cls": m["cls"],
                         "metrics": mean_metrics(m), "failures": sum(s["failure"] is not None for s in m["scenarios"]),
                         "scenarios": len(m["scenarios"]), "diverged": []})
    json.dump({"scenario": a.scenario, "rows": rows, "paired": paired}, open(os.path.join(a.out, "table.json"), "w"), indent=1)
    n = rows[0]["scenarios"]
    keys = []
    for r in rows:
        if (r["planner"], r["renderer"]) not in keys:
            keys.append((r["planner"], r["renderer"]))
    md = [f"# Closed-loop table ({n} held-out scenarios: `{a.scenario}`)", "",
          f"Renderer model: `{a.model or 'builtin:b2dr-nano'}`.", "",
          "| planner | renderer | R-CLS | CLS-NR | " + " | ".join(METRICS) + " (R-CLS runs) |",
          "|---|---|---|---|" + "---|" * len(METRICS)]
    for pl, rd in keys:
        by = {r["kind"]: r for r in rows if r["planner"] == pl and r["renderer"] == rd}
        rc, nr = by.get("R-CLS"), by.get("CLS-NR")
        cells = [f"{rc['metrics'][k]:.3f}" for k in METRICS] if rc else ["-"] * len(METRICS)
        md.append(f"| {pl} | {rd} | {rc['cls']:.4f} | {nr['cls']:.4f} | " + " | ".join(cells) + " |")
    for kind in ["R-CLS", "CLS-NR"]:
        div = next((r["diverged"] for r in rows if r["kind"] == kind and r["diverged"]), [])
        if div:
            md += ["", f"Scenarios where the renderer changed the e2e planner's score ({kind}; "
                   f"{', '.join(a.renderers.split(','))}):", ""]
            md += [f"- {d['scenario']}: " + ", ".join(f"{s:.3f}" for s in d["scores"]) for d in div]
    for kind, prs in paired.items():
        if prs:
            md += ["", f"Paired per-scenario difference, b2dr minus each renderer ({kind}, {prs[0]['n']} scenarios; "
                   "bootstrap 95 % interval over scenarios; with few scenarios a percentile bootstrap's interval is too "
                   "narrow: widen the set with --seeds before reading a verdict):", "",
                   "| against | mean difference | 95 % interval | b2dr wins / losses / ties | b2dr is |", "|---|---|---|---|---|"]
            md += [f"| {q['renderer']} | {q['mean']:+.4f} | [{q['lo']:+.4f}, {q['hi']:+.4f}] | "
                   f"{q['wins']} / {q['losses']} / {q['ties']} | {verdict(q)} |" for q in prs]
    open(os.path.join(a.out, "table.md"), "w").write("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
