"""The lift gate: the foot leaves the floor only once the body stands over the other three.

The schedule gives the policy a fixed shift (2 s) to move the body over the three feet it will
stand on before the foot is lifted. At the tick the lift would begin, the gate estimates the
centre of mass's margin in the triangle of the stance feet from the joint angles and the body
IMU's gravity (:meth:`calib.support.SupportModel.margin`, the URDF's masses). Below
``margin_m`` the shift is held longer, tick by tick, the policy still shifting under its lift
command, for at most ``wait_s``; a margin that does not come calls the lift off before the
foot leaves the floor, as the tip guard does once it has (``deploy.tip_guard``: the session
tries the leg once more after REPLANT, with a longer shift).

Why (v43, the URDF's `slope` transfer scenario, 80 lifts on floors tilted 2-5 deg;
``docs/policy-training.md``, "Stop 66"): the one lift that fell began with the centre of mass
38 mm outside the triangle (the floor falling away towards the lifted corner, the shift moving
the body the wrong way); every lift that held began 33 mm inside or more. That lift tipped
2.5 deg in 0.26 s and 5 deg in 0.36 s, and called off by the tip guard at 5 deg it fell all the
same. Gated at 20 mm, its shift was held 0.44 s longer and the lift held.

Why 20 mm and 2 s: over 960 lifts of twelve transfer scenarios (the URDF's and Menagerie's
models) the estimate was within 20 mm of the simulator's truth (median 4-6 mm: randomised
masses, payloads, an IMU mounted off, which the estimate cannot know) and under 40 mm only for
that fall, so at 20 mm the gate held no lift that held. 2 s more is the shift once again; the
fall needed 0.44 s of it.

Pure logic on a margin; the caller measures it (:class:`SupportModel`) and holds or calls off.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["DEFAULT_GATE", "GATE_CAUSE", "GateLimits", "LiftGate"]

GATE_CAUSE = "centre of mass"  # how every call-off of the gate begins


@dataclass(frozen=True)
class GateLimits:
    """margin_m: m the estimated centre of mass must lie inside the stance triangle when the
    foot leaves the floor. wait_s: s the shift may be held longer for it."""

    margin_m: float = 0.02
    wait_s: float = 2.0

    def __post_init__(self) -> None:
        for name, lo, hi in (("margin_m", -0.2, 0.2), ("wait_s", 0.0, 30.0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) \
                    or not (math.isfinite(v) and lo <= v <= hi):
                raise ValueError(f"the lift gate's {name} must be in [{lo:g}, {hi:g}], got {v!r}")

    @classmethod
    def of(cls, value) -> GateLimits | None:
        """From a :class:`GateLimits`, a margin in m (the default wait), a (margin m, wait s)
        pair, or None (off). ValueError (one line) otherwise."""
        if value is None or isinstance(value, GateLimits):
            return value
        pair = isinstance(value, (list, tuple))
        if pair and len(value) != 2:
            raise ValueError(f"the lift gate is (margin m, wait s), got {value!r}")
        return cls(*value) if pair else cls(value)

    @classmethod
    def parse(cls, text: str) -> GateLimits | None:
        """``"MM[,S]"``: the margin in mm, the wait in s (default 2); ``"off"``: None."""
        if str(text).strip().lower() == "off":
            return None
        parts = [p.strip() for p in str(text).split(",")]
        try:
            nums = [float(p) for p in parts]
        except ValueError:
            raise ValueError(f"the lift gate is MM[,S] or off, got {text!r}") from None
        if len(nums) > 2:
            raise ValueError(f"the lift gate is MM[,S] or off, got {text!r}")
        return cls(nums[0] / 1e3, *nums[1:])

    def __str__(self) -> str:
        """As :meth:`parse` reads it: mm, s."""
        return f"{self.margin_m * 1e3:g},{self.wait_s:g}"

    def to_json(self) -> list[float]:
        """[margin m, wait s] (:meth:`of` reads it)."""
        return [self.margin_m, self.wait_s]


DEFAULT_GATE = GateLimits()


class LiftGate:
    """One lift's gate. :meth:`check` at each tick the lift would begin: ``"go"`` (and from
    then on), ``"wait"`` (hold the shift one more tick), or why the lift is called off."""

    def __init__(self, limits: GateLimits | None) -> None:
        self.limits = GateLimits.of(limits)
        self.reset()

    def reset(self) -> None:
        self.waited_s = 0.0
        self.passed = False

    def check(self, margin_m: float, dt: float) -> str:
        """``margin_m``: the estimated margin now, m; ``dt``: s one more wait would last."""
        if self.limits is None or self.passed:
            return "go"
        if margin_m >= self.limits.margin_m:
            self.passed = True
            return "go"
        if self.waited_s + dt <= self.limits.wait_s + 1e-9:
            self.waited_s += dt
            return "wait"
        if not math.isfinite(margin_m):  # e.g. no body attitude: nothing to stand on
            return (f"{GATE_CAUSE} unknown (no body attitude) after {self.waited_s:.1f} s more "
                    "shift")
        return (f"{GATE_CAUSE} {margin_m * 1e3:+.0f} mm in the stance triangle "
                f"after {self.waited_s:.1f} s more shift (needs {self.limits.margin_m * 1e3:+.0f})")
