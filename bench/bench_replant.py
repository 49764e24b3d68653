"""All four legs on the mock robot on tilted floors, with and without re-planting the feet
between lifts (``a2i-deploy --no-replant``): how many runs and lifts hold.

    .venv/bin/python bench/bench_replant.py [--slopes 0,3,5] [--azimuths 0,90,180,270]
        [--workers 2] [--out docs/results/replant.md]

Each run is ``a2i-deploy --leg all --sim --sim-seed 101`` with the mock's floor tilted
``floor_slope_deg`` and falling away towards ``floor_slope_azimuth_deg`` (the robot starts facing
0 deg; 90 is its left), the deploy policy, the full schedule: lockstep, so a run's outcome is
deterministic. A flat floor is run once. A lift holds when its calibration is accepted; a run
that tips over is damped by the safety supervisor (tilt beyond 30 deg) and its remaining legs
count as lost. Writes the table (markdown) atomically.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from calib.atomic import write_text_atomic
from calib.joints import LEGS
from hw.mock.config import MockConfig

SIM_SEED = 101


def _floats(text: str) -> list[float]:
    try:
        return [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected numbers separated by commas, got {text!r}")


def run_one(slope: float, azimuth: float, replant: bool) -> dict:
    """One ``a2i-deploy --leg all`` on the mock: the legs accepted, the fault if any."""
    with tempfile.TemporaryDirectory(prefix="replant-") as tmp:
        cfg = Path(tmp) / "mock.json"
        cfg.write_text(json.dumps({"floor_slope_deg": slope, "floor_slope_azimuth_deg": azimuth}))
        out = Path(tmp) / "out"
        cmd = [sys.executable, "-m", "deploy.cli", "--leg", "all", "--sim", "--sim-seed",
               str(SIM_SEED), "--sim-config", str(cfg), "--out", str(out)]
        if not replant:
            cmd.append("--no-replant")
        t0 = time.time()
        p = subprocess.run(cmd, check=False, cwd=ROOT, capture_output=True, text=True)
        accepted = [g for g in LEGS if (out / f"{g}.json").is_file()
                    and json.loads((out / f"{g}.json").read_text()).get("verdict") == "accepted"]
        lines = p.stdout.splitlines()
        fault = next((ln.split("FAULT:", 1)[1].strip() for ln in lines
                      if ln.startswith("FAULT:")), None)
        # the final table's verdicts of the legs it did not accept
        lost = {ln[:4].strip(): ln.split("FAILED:", 1)[-1].split("NOT WRITTEN:", 1)[-1].strip()
                for ln in lines if ln[:4].strip() in LEGS and ("FAILED:" in ln
                                                               or "NOT WRITTEN:" in ln)}
    if p.returncode == 2:
        raise SystemExit(f"a2i-deploy refused to start: {p.stderr.strip().splitlines()[-1]}")
    return {"slope": slope, "azimuth": azimuth, "replant": replant, "rc": p.returncode,
            "accepted": accepted, "fault": fault, "lost": lost, "wall_s": time.time() - t0}


def render(rows: list[dict], argv: list[str]) -> str:
    lines = ["# All four legs on tilted floors, re-planting the feet between lifts or not", "",
             (f"Produced by `.venv/bin/python bench/bench_replant.py {' '.join(argv)}`: each row "
              f"is `a2i-deploy --leg all --sim --sim-seed {SIM_SEED}` (lockstep, the deploy "
              "policies, the full schedule) on the mock with its floor tilted "
              "(`floor_slope_deg`, falling away towards `floor_slope_azimuth_deg`: 0 ahead of "
              "the robot, 90 its left), with `--no-replant` or without. Legs in the order RL, "
              "RR, FL, FR; a run the safety supervisor damped loses its remaining legs."), "",
             "| floor | re-plant | accepted legs | why the others were not |",
             "| --- | --- | --- | --- |"]
    for r in rows:
        floor = "flat" if r["slope"] == 0 else f"{r['slope']:g} deg, down towards {r['azimuth']:g} deg"
        legs = " ".join(g if g in r["accepted"] else f"~~{g}~~" for g in LEGS)
        why = "; ".join(f"{g}: {e}" for g, e in r["lost"].items()) or "-"
        lines.append(f"| {floor} | {'yes' if r['replant'] else 'no'} | {legs} "
                     f"({len(r['accepted'])}/4) | {why} |")
    lines.append("")
    for mode in (True, False):
        rs = [r for r in rows if r["replant"] is mode]
        n_all = sum(len(r["accepted"]) == 4 for r in rs)
        n_legs = sum(len(r["accepted"]) for r in rs)
        falls = sum(r["fault"] is not None for r in rs)
        lines.append(f"- re-plant {'on' if mode else 'off'}: {n_all} of {len(rs)} runs with every "
                     f"leg accepted, {n_legs} of {4 * len(rs)} legs, {falls} runs damped")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--slopes", type=_floats, default=[0.0, 3.0, 5.0], help="deg")
    p.add_argument("--azimuths", type=_floats, default=[0.0, 90.0, 180.0, 270.0], help="deg")
    # one at a time: in lockstep the foot IMUs' frames are read by a thread and stamped on the
    # host clock; two runs on two cores starved it (legs lost on flat ground, before the
    # silence check needed wall time too) and moved the solver's figures
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--out", default=None, help="markdown table (default: print only)")
    a = p.parse_args(argv)
    if a.workers < 1:
        p.error("workers must be >= 1")
    try:  # the mock's own check of its floor settings, before a run starts
        for s in a.slopes:
            MockConfig(listen=[], floor_slope_deg=s).validate()
    except ValueError as e:
        p.error(str(e))
    jobs = [(s, az, rp) for s in a.slopes for az in (a.azimuths if s else [0.0])
            for rp in (True, False)]
    rows: list[dict] = []
    t0 = time.time()
    with ThreadPoolExecutor(a.workers) as pool:
        for i, r in enumerate(pool.map(lambda j: run_one(*j), jobs), 1):
            rows.append(r)
            print(f"  {i}/{len(jobs)} runs, {time.time() - t0:.0f} s: slope {r['slope']:g}, "
                  f"azimuth {r['azimuth']:g}, re-plant {r['replant']}: "
                  f"{len(r['accepted'])}/4 accepted{', ' + r['fault'] if r['fault'] else ''}",
                  flush=True)
    table = render(rows, sys.argv[1:] if argv is None else list(argv))
    print(table)
    if a.out:
        write_text_atomic(a.out, table)
        print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
