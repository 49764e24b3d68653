"""The tip guard: a lift that tips the body is called off before the robot falls.

While the lifted foot leaves the floor and is carried to the excitation's start (the schedule's
``lift`` and ``hold`` phases) the body's tilt from the vertical is compared with its tilt when
the lift began, each phase against its own limit (:class:`TipLimits`, default
:data:`DEFAULT_TIP_LIMITS`: 5 deg lifting, 8 deg holding).

Why those two numbers (v26, the guard off and the tilt logged: on MuJoCo Menagerie's Go2 all 880
lifts of the transfer check, on the URDF's 400 of its scenarios; ``docs/policy-training.md``,
"The tip guard by phase"):

* A lift the tripod cannot carry tips the body as the foot leaves the floor. The seven lifts
  that fell there (FR: five on the tilted floor, one quiet, one with joint friction) passed
  5 deg 0.20-0.34 s into the 0.6 s lift, at 22-29 deg/s, and 50 deg by the end of the hold;
  the foot, still below the body, can catch it if it goes back down at once. Called off at
  5 deg the five tilted-floor ones all stood again on four feet; at 8 deg (lowered in 0.6 s)
  two of five fell all the same, at 10 deg four.
* In the hold the leg swings out to the excitation's first pose and the tripod leans with it
  as it was trained to: RL's lifts leaned the body by up to 6.9 deg there on Menagerie's model
  (median 5.0) and 7.6 deg on the URDF's, in every scenario, and held. Lifting, RL's lean
  passed 5 deg in 3 of 220 lifts on Menagerie's model and 7 of 100 on the URDF's, RR's in one
  of 100 there; the held front lifts stayed within 4.3 deg in both phases. Neither the tilt's
  rate (RL's lean passes 5 deg at up to 23 deg/s) nor its direction (towards the lifted
  corner, as a fall's) tells that lean from a fall; the phase it comes in mostly does.

One limit for both phases (5 deg, this guard until the phases were told apart, then off by
default) called off 115 of Menagerie's 220 RL lifts and 67 of the URDF's 100.

A lift called off is tried once more (the session: after sitting down and standing up again),
its shift :data:`RETRY_SHIFT_S` longer: the policy then has more time to move the body over the
three feet it will stand on. The five tilted-floor lifts, from a stand-up with the shift 1 s
longer (3 s), all held.

Not in the excitation: the falls there (shoves) tip the body over the other side of the tripod,
which the lifted foot cannot reach, and the excitation's own sway is larger.

Pure logic on the body quaternion; the caller does the lowering (the session's abort, the
free-base runner's).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from deploy.supervisor import tilt_rad

__all__ = ["DEFAULT_TIP_LIMITS", "GUARDED_PHASES", "RETRY_SHIFT_S", "TipGuard", "TipLimits"]

RETRY_SHIFT_S = 1.0  # s more shift for a lift's second try (above)
GUARDED_PHASES = ("lift", "hold")


@dataclass(frozen=True)
class TipLimits:
    """deg the body may tip from its tilt at the lift's first tick: ``lift`` while the foot
    leaves the floor, ``hold`` while the leg is carried to the excitation's start."""

    lift: float
    hold: float

    def __post_init__(self) -> None:
        for name in ("lift", "hold"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) \
                    or not (math.isfinite(v) and 0 < v < 90):
                raise ValueError(f"the tip limit ({name}) must be in (0, 90) deg, got {v!r}")

    @classmethod
    def of(cls, value) -> TipLimits | None:
        """From a :class:`TipLimits`, one number (both phases), a (lift, hold) pair, or None
        (off: None). ValueError (one line) otherwise."""
        if value is None or isinstance(value, TipLimits):
            return value
        if isinstance(value, (list, tuple)):
            if len(value) != 2:
                raise ValueError(f"tip limits are (lift, hold) deg, got {value!r}")
            return cls(*value)
        return cls(value, value)

    @classmethod
    def parse(cls, text: str) -> TipLimits | None:
        """``"LIFT[,HOLD]"`` deg (one number: both phases); ``"0"``: off (None)."""
        parts = [p.strip() for p in str(text).split(",")]
        try:
            nums = [float(p) for p in parts]
        except ValueError:
            raise ValueError(f"tip limits are LIFT[,HOLD] deg, got {text!r}") from None
        if len(nums) == 1 and nums[0] == 0:
            return None
        if len(nums) not in (1, 2):
            raise ValueError(f"tip limits are LIFT[,HOLD] deg, got {text!r}")
        return cls.of(nums[0] if len(nums) == 1 else tuple(nums))

    def __str__(self) -> str:
        return f"{self.lift:g}" if self.lift == self.hold else f"{self.lift:g},{self.hold:g}"

    def to_json(self):
        """One number when both phases share it, else [lift, hold] (:meth:`of` reads either)."""
        return self.lift if self.lift == self.hold else [self.lift, self.hold]


DEFAULT_TIP_LIMITS = TipLimits(5.0, 8.0)  # measured above; a2i-deploy's default


class TipGuard:
    """``check(phase, quat)`` once per tick of a lift: the abort's cause (one line) once the
    body has tipped more than the phase's limit from its tilt at the first guarded tick, else
    None. limits: anything :meth:`TipLimits.of` takes (None: never). :meth:`reset` before each
    lift."""

    def __init__(self, limits=None):
        self.limits = TipLimits.of(limits)
        self.tilt0: float | None = None  # rad, at the first guarded tick

    def reset(self) -> None:
        self.tilt0 = None

    def check(self, phase: str, quat_wxyz) -> str | None:
        if self.limits is None or phase not in GUARDED_PHASES or quat_wxyz is None:
            return None
        tilt = tilt_rad(quat_wxyz)
        if self.tilt0 is None:
            self.tilt0 = tilt
        tip = math.degrees(tilt - self.tilt0)
        limit = getattr(self.limits, phase)
        if tip > limit:
            return (f"the body tipped {tip:.2f} deg in {phase} (from {math.degrees(self.tilt0):.1f}"
                    f" deg, limit {limit:g}): foot back down")
        return None
