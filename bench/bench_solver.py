"""Benchmark: calib.solver.solve against the paper's plain method, same process, same data.

The plain method (``paper_grid_solve`` below, the authors' approach plus the 3-point parabola
of a published third-party implementation): resample the encoder-side angular velocity onto a
uniform grid at the IMU's median rate (linear interpolation), and for every candidate offset on
that one-sample grid interpolate the gyro at grid + offset and recompute all covariances and r;
refine the best offset with a 3-point parabola; rotation by SVD of S_FF^-1 S_FI with the
determinant fix.

For every case (noise level, rates, offset, jitter, drops) and a few seeds it prints the CPU
time (time.process_time) of both, the speed ratio, and the RMS offset and rotation errors
(geodesic, degrees) over the seeds. At the noise floor both methods are limited by the same
gyro noise, so the verdict is a paired test on the squared errors, seed by seed: "better"
(ours significantly smaller, > 2 standard errors), "tie", or "WORSE" (significantly larger),
for offset / rotation.

    .venv/bin/python bench/bench_solver.py [--seeds N] [--quick]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from calib.metrics import geodesic_error_deg
from calib.solver import SolverConfig, solve
from calib.synthetic import make_case

DEG_S = np.pi / 180.0  # noise densities below are quoted in deg/s/sqrt(Hz), as in the paper


def _project_so3(m: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(m)
    return u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt


def _trace_corr(wi: np.ndarray, wf: np.ndarray) -> float:
    c = np.cov(np.hstack([wi, wf]), rowvar=False)
    s_ii, s_if, s_ff = c[:3, :3], c[:3, 3:], c[3:, 3:]
    m = np.linalg.solve(s_ii, s_if) @ np.linalg.solve(s_ff, s_if.T)
    return float(np.sqrt(max(np.trace(m) / 3.0, 0.0)))


def _interp3(tq, t, w):
    return np.stack([np.interp(tq, t, w[:, k]) for k in range(3)], axis=1)


def paper_grid_solve(t_enc, omega_foot, t_imu, omega_imu, max_offset=0.5):
    """The plain method: one-sample grid, covariances recomputed per offset, 3-point parabola.
    Returns (R_I^F, t_d)."""
    dt = float(np.median(np.diff(t_imu)))
    lo = max(t_enc[0], t_imu[0] + max_offset)
    hi = min(t_enc[-1], t_imu[-1] - max_offset)
    grid = np.arange(lo, hi, dt)  # encoder clock
    wf = _interp3(grid, t_enc, omega_foot)
    k_max = int(np.floor(max_offset / dt))
    ks = np.arange(-k_max, k_max + 1)
    r = np.array([_trace_corr(_interp3(grid + k * dt, t_imu, omega_imu), wf) for k in ks])
    i = int(np.argmax(r))
    frac = 0.0
    if 0 < i < r.size - 1:
        den = r[i - 1] - 2.0 * r[i] + r[i + 1]
        if den < 0:
            frac = 0.5 * (r[i - 1] - r[i + 1]) / den
    t_d = (ks[i] + frac) * dt
    wi = _interp3(grid + t_d, t_imu, omega_imu)
    c = np.cov(np.hstack([wi, wf]), rowvar=False)
    s_ff, s_fi = c[3:, 3:], c[3:, :3]
    return _project_so3(np.linalg.solve(s_ff, s_fi)), t_d


N06 = 0.06 * DEG_S
CASES = [
    # name, make_case keyword arguments
    ("noise-free", {"noise_density": 0.0}),
    ("nav-grade 0.006", {"noise_density": 0.006 * DEG_S}),
    ("paper 0.03", {"noise_density": 0.03 * DEG_S}),
    ("paper 0.06", {"noise_density": N06}),
    ("cheap 0.3", {"noise_density": 0.3 * DEG_S}),
    ("enc100 imu100", {"enc_rate": 100, "imu_rate": 100, "noise_density": N06}),
    ("enc1000 imu1000", {"enc_rate": 1000, "imu_rate": 1000, "noise_density": N06}),
    ("enc100 imu1000", {"enc_rate": 100, "imu_rate": 1000, "noise_density": N06}),
    ("enc1000 imu100", {"enc_rate": 1000, "imu_rate": 100, "noise_density": N06}),
    ("offset +0.45", {"time_offset": 0.45, "noise_density": N06}),
    ("offset -0.45", {"time_offset": -0.45, "noise_density": N06}),
    ("jitter 0.3 ms", {"jitter_s": 3e-4, "noise_density": N06}),
    ("jitter 1 ms", {"jitter_s": 1e-3, "noise_density": N06}),
    ("drops 5 %", {"drop_fraction": 0.05, "noise_density": N06}),
    ("5 Hz content", {"max_frequency": 5.0, "noise_density": N06}),
    ("all at once", {"enc_rate": 500, "imu_rate": 200, "time_offset": -0.43, "jitter_s": 2e-4,
                     "drop_fraction": 0.05, "noise_density": 0.1 * DEG_S,
                     "bias": (0.02, -0.03, 0.01)}),
]


def _rms(v) -> float:
    return float(np.sqrt(np.mean(np.square(v))))


def _paired(ours, plain) -> str:
    """Paired verdict on squared errors: better / tie / WORSE at 2 standard errors."""
    d = np.square(ours) - np.square(plain)
    se = np.std(d, ddof=1) / np.sqrt(d.size) if d.size > 1 else 0.0
    if np.mean(d) > 2 * se:
        return "WORSE"
    return "better" if np.mean(d) < -2 * se else "tie"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--quick", action="store_true", help="first 4 cases only")
    args = ap.parse_args()
    cfg = SolverConfig(min_correlation=0.0)  # compare estimates, not gates
    cases = CASES[:4] if args.quick else CASES
    print(f"{'case':17s} {'ours ms':>8s} {'plain ms':>9s} {'ratio':>6s} "
          f"{'ours off us':>11s} {'plain off us':>12s} {'ours rot deg':>12s} "
          f"{'plain rot deg':>13s}  offset / rotation")
    all_ok, t_ours_all, t_plain_all = True, 0.0, 0.0
    for ci, (name, kw) in enumerate(cases):
        kw = dict(kw)
        base_offset = kw.pop("time_offset", None)
        t_o = t_p = 0.0
        e_o, e_p, r_o, r_p = [], [], [], []
        for s in range(args.seeds):
            off = base_offset if base_offset is not None else 0.37 * np.sin(1.3 * s + ci)
            case = make_case(1000 * ci + s, time_offset=off, **kw)
            t0 = time.process_time()
            res = solve(case.t_enc, case.omega_foot, case.t_imu, case.omega_imu, cfg)
            t1 = time.process_time()
            rot_p, off_p = paper_grid_solve(case.t_enc, case.omega_foot, case.t_imu,
                                            case.omega_imu)
            t2 = time.process_time()
            t_o += t1 - t0
            t_p += t2 - t1
            e_o.append(res.time_offset - off)
            e_p.append(off_p - off)
            r_o.append(geodesic_error_deg(res.rotation, case.rotation))
            r_p.append(geodesic_error_deg(rot_p, case.rotation))
        eo, ep, ro, rp = _rms(e_o) * 1e6, _rms(e_p) * 1e6, _rms(r_o), _rms(r_p)
        v_off, v_rot = _paired(e_o, e_p), _paired(r_o, r_p)
        all_ok &= "WORSE" not in (v_off, v_rot)
        t_ours_all += t_o
        t_plain_all += t_p
        n = args.seeds
        print(f"{name:17s} {t_o / n * 1e3:8.1f} {t_p / n * 1e3:9.1f} {t_p / t_o:6.1f} "
              f"{eo:11.2f} {ep:12.2f} {ro:12.4f} {rp:13.4f}  {v_off} / {v_rot}")
    print(f"\noverall CPU time: ours {t_ours_all:.2f} s, plain {t_plain_all:.2f} s, "
          f"ratio {t_plain_all / t_ours_all:.1f}x; ours never significantly less accurate: "
          f"{'yes' if all_ok else 'NO'}")


if __name__ == "__main__":
    main()
