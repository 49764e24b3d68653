"""Human-facing output of a deploy run: one block per leg and the final table.

Degrees and milliseconds appear here only (human output); the files keep SI units.
"""

from __future__ import annotations

from calib.result import format_report
from deploy.session import LegOutcome

__all__ = ["leg_summary", "results_table"]


def _retried(o: LegOutcome) -> str:
    held = (f"\n  (its shift was held {o.lift_wait_s:.2f} s longer, until the centre of mass stood "
            "over the other three feet)" if o.lift_wait_s > 0 else "")
    return held + (f"\n  (its first lift was called off: {o.retried}; lifted again with a longer "
                   "shift)" if o.retried else "")


def _delay(o: LegOutcome) -> str:
    """The command path's delay, where the lift read it, against the policy's training."""
    d = o.command_delay_s
    if d is None:
        return ""
    line = f"\n  command delay {d * 1e3:.0f} ms (the motors' torque against the commands)"
    if o.trained_delay_s is None:
        return line
    lo, hi = o.trained_delay_s
    trained = f"{lo * 1e3:.0f}-{hi * 1e3:.0f} ms"
    if d <= hi + 1e-9:
        return f"{line}, within the {trained} the policy was trained at"
    return (f"{line}: OVER the {trained} the policy was trained at; the body rocks more than "
            "its evaluation says: look at the command path (bridge, network, its load)")


def leg_summary(o: LegOutcome) -> str:
    """The report of one leg, as printed when its SOLVE ends."""
    out = o.payload
    if out is None or getattr(out, "result", None) is None:
        return (f"Leg {o.leg}: NO CALIBRATION WRITTEN: {o.error or 'no result'}" + _retried(o)
                + _delay(o))
    text = format_report(out.result, out.truth) + _retried(o) + _delay(o)
    if out.accepted:
        files = ", ".join(str(p) for p in out.files)
        return f"{text}\n  written: {files}"
    return (f"{text}\n  NOT WRITTEN AS A CALIBRATION: {out.error}"
            + (f"\n  figure: {out.files[0]}" if out.files else ""))


def results_table(outcomes: list[LegOutcome]) -> str:
    """The final table: R (matrix and RPY), time offset, CN, CC, uncertainty, verdict; and the
    error against the simulated truth when there is one."""
    head = (f"{'leg':<4} {'roll/pitch/yaw (deg)':<26} {'t_d (ms)':>9} {'CN':>7} {'CC':>8} "
            f"{'std R (deg)':>11} {'std t_d (ms)':>12}  verdict")
    lines = [head, "-" * len(head)]
    for o in outcomes:
        out = o.payload
        res = getattr(out, "result", None)
        if res is None:
            lines.append(f"{o.leg:<4} {'-':<26} {'-':>9} {'-':>7} {'-':>8} {'-':>11} {'-':>12}"
                         f"  FAILED: {o.error or 'no result'}")
            continue
        rpy = " ".join(f"{v:+8.3f}" for v in res.rpy_deg)
        verdict = "accepted" if out.accepted else f"NOT WRITTEN: {out.error}"
        lines.append(
            f"{o.leg:<4} {rpy:<26} {res.time_offset_s * 1e3:+9.3f} {res.condition_number:7.3f} "
            f"{res.correlation:8.5f} {res.rotation_std_deg:11.4f} "
            f"{res.time_offset_std_s * 1e3:12.4f}  {verdict}")
        for i, row in enumerate(res.rotation_matrix):
            lead = "     R = " if i == 0 else "         "
            lines.append(lead + "[" + " ".join(f"{v:+.6f}" for v in row) + "]")
        err = out.errors_vs_truth()
        if err is not None:
            lines.append(f"     vs simulated truth: rotation {err[0]:.4f} deg (geodesic), "
                         f"time offset {err[1] * 1e3:.4f} ms "
                         f"(truth {out.truth[1] * 1e3:+.3f} ms)")
    return "\n".join(lines)
