"""deploy.tip_guard: the tilt a lift adds, watched over lift and hold only."""

import math

import numpy as np
import pytest

from deploy.tip_guard import MAX_TIP_DEG, TipGuard


def _pitch(deg):
    a = math.radians(deg) / 2
    return np.array([math.cos(a), 0.0, math.sin(a), 0.0])


def test_measures_from_the_tilt_at_the_first_guarded_tick():
    g = TipGuard(5.0)
    assert g.check("shift", _pitch(30.0)) is None  # not watched, and not the reference
    assert g.check("lift", _pitch(4.0)) is None  # the reference: a floor tilted 4 deg
    assert g.check("hold", _pitch(8.9)) is None
    why = g.check("hold", _pitch(9.2))
    assert why is not None and "tipped 5.20 deg in hold" in why and "from 4.0 deg" in why
    # the excitation and the lowering are not watched
    assert g.check("excite", _pitch(40.0)) is None and g.check("lower", _pitch(40.0)) is None
    g.reset()
    assert g.check("lift", _pitch(9.2)) is None  # a new lift, a new reference


def test_levelling_is_not_tipping_and_none_is_off():
    g = TipGuard(MAX_TIP_DEG)
    g.check("lift", _pitch(6.0))
    assert g.check("hold", _pitch(0.0)) is None
    off = TipGuard()  # off unless given a limit
    off.check("lift", _pitch(0.0))
    assert off.check("hold", _pitch(60.0)) is None
    assert g.check("hold", None) is None  # no body quaternion this tick


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_bad_limits_are_refused(bad):
    with pytest.raises(ValueError, match="max_tip_deg"):
        TipGuard(bad)
