"""The tip guard: a lift that tips the body is called off before the robot falls (opt-in).

While the lifted foot leaves the floor (the schedule's ``lift`` and ``hold`` phases) the body's
tilt from the vertical is compared with its tilt when the lift began. A lift the tripod cannot
carry tips the body within a few tenths of a second, and the foot, still below the body, can
catch it if it goes back down at once. On MuJoCo Menagerie's Go2 on floors tilted 2-5 deg
(v26, 40 front lifts; ``docs/policy-training.md``, "The tip guard"), the front lifts that held
tipped the body 2.8 deg at most over lift and hold; each of the five that fell there passed
5 deg within 0.35 s of the lift's start and 50 deg by the end of the hold. Called off at 5 deg,
the same five stood again on four feet, the body 10-14 deg from the vertical at worst; at
8 deg (the foot lowered in 0.6 s instead of 0.9) two of five fell all the same, at 10 deg four.

A lift called off is tried once more (the session: after sitting down and standing up
again), its shift :data:`RETRY_SHIFT_S` longer: the policy then has more time to move the
body over the three feet it will stand on. The same five FR lifts, from a stand-up with the
shift 1 s longer (3 s), all held.

Why it is off by default: on that model v26's RL lifts lean the body by up to 6.3 deg (median
5) during the hold as a matter of course, in every scenario (RR's under 1 deg). A limit that
catches the falls (5 deg) called off 115 of 220 RL lifts that would have held; their second
lifts held but four. A plain tilt limit cannot tell that lean from the start of a fall, so the guard is for a
floor known to be tilted (``a2i-deploy --max-tip 5``), where a called-off lift costs a sit,
a stand and a second lift, and a fall costs the robot.

Not in the excitation: the falls there (shoves) tip the body over the other side of the tripod,
which the lifted foot cannot reach, and the excitation's own sway is larger.

Pure logic on the body quaternion; the caller does the lowering (the session's abort, the
free-base runner's).
"""

from __future__ import annotations

import math

from deploy.supervisor import tilt_rad

__all__ = ["GUARDED_PHASES", "MAX_TIP_DEG", "RETRY_SHIFT_S", "TipGuard"]

MAX_TIP_DEG = 5.0  # the limit measured above: what --max-tip suggests, not a default
RETRY_SHIFT_S = 1.0  # s more shift for a lift's second try (above)
GUARDED_PHASES = ("lift", "hold")


class TipGuard:
    """``check(phase, quat)`` once per tick of a lift: the abort's cause (one line) once the
    body has tipped more than ``max_tip_deg`` from its tilt at the first guarded tick, else
    None. ``max_tip_deg`` None: never. :meth:`reset` before each lift."""

    def __init__(self, max_tip_deg: float | None = None):
        if max_tip_deg is not None and not (math.isfinite(max_tip_deg) and max_tip_deg > 0):
            raise ValueError(f"max_tip_deg must be a positive number of degrees or None, "
                             f"got {max_tip_deg!r}")
        self.max_tip_deg = max_tip_deg
        self.tilt0: float | None = None  # rad, at the first guarded tick

    def reset(self) -> None:
        self.tilt0 = None

    def check(self, phase: str, quat_wxyz) -> str | None:
        if self.max_tip_deg is None or phase not in GUARDED_PHASES or quat_wxyz is None:
            return None
        tilt = tilt_rad(quat_wxyz)
        if self.tilt0 is None:
            self.tilt0 = tilt
        tip = math.degrees(tilt - self.tilt0)
        if tip > self.max_tip_deg:
            return (f"the body tipped {tip:.2f} deg in {phase} (from {math.degrees(self.tilt0):.1f}"
                    f" deg, limit {self.max_tip_deg:g}): foot back down")
        return None
