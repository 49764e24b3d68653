"""deploy.tip_guard: the tilt a lift adds, watched over lift and hold only, each its own limit."""

import math

import numpy as np
import pytest

from deploy.tip_guard import DEFAULT_TIP_LIMITS, TipGuard, TipLimits


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


def test_lift_and_hold_have_their_own_limits():
    g = TipGuard(DEFAULT_TIP_LIMITS)  # 5 deg lifting, 8 holding
    assert g.check("lift", _pitch(1.0)) is None
    assert g.check("lift", _pitch(5.9)) is None
    assert "tipped 5.10 deg in lift" in g.check("lift", _pitch(6.1))
    g.reset()
    g.check("lift", _pitch(1.0))
    assert g.check("hold", _pitch(8.9)) is None  # the leg's swing to the excitation: a lean
    assert "limit 8" in g.check("hold", _pitch(9.1))


def test_levelling_is_not_tipping_and_none_is_off():
    g = TipGuard(DEFAULT_TIP_LIMITS)
    g.check("lift", _pitch(6.0))
    assert g.check("hold", _pitch(0.0)) is None
    off = TipGuard()  # off unless given limits
    off.check("lift", _pitch(0.0))
    assert off.check("hold", _pitch(60.0)) is None
    assert g.check("hold", None) is None  # no body quaternion this tick


def test_limits_from_numbers_pairs_and_text():
    assert TipLimits.of(6) == TipLimits(6, 6) and TipLimits.of((5, 8)) == DEFAULT_TIP_LIMITS
    assert TipLimits.of(None) is None and TipLimits.of(DEFAULT_TIP_LIMITS) is DEFAULT_TIP_LIMITS
    assert TipLimits.parse("5,8") == DEFAULT_TIP_LIMITS and TipLimits.parse(" 6 ") == TipLimits(6, 6)
    assert TipLimits.parse("0") is None  # off
    assert str(DEFAULT_TIP_LIMITS) == "5,8" and str(TipLimits(6, 6)) == "6"
    assert DEFAULT_TIP_LIMITS.to_json() == [5.0, 8.0] and TipLimits(6, 6).to_json() == 6
    for x in (DEFAULT_TIP_LIMITS, TipLimits(6, 6)):
        assert TipLimits.of(x.to_json()) == x and TipLimits.parse(str(x)) == x


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf"), 90.0, (5.0,),
                                 (5.0, 0.0), "5", True])
def test_bad_limits_are_refused(bad):
    with pytest.raises(ValueError, match="tip limit"):
        TipGuard(bad)


@pytest.mark.parametrize("text", ["x", "5,", "5,8,9", "", "0,8"])
def test_bad_text_is_refused(text):
    with pytest.raises(ValueError, match="tip limit"):
        TipLimits.parse(text)


def test_a_turn_that_does_not_tilt_the_body_further_is_no_tip():
    # RR's lift turns the shifted body (4-7 deg of tilt) by 5-6 deg without tipping it further,
    # and holds: watched as an attitude change, 149 of Menagerie's 220 RR lifts were called off
    # (docs/deploy.md, "Why the tilt's growth")
    def tilted(deg, azimuth_deg):
        a, az = math.radians(deg) / 2, math.radians(azimuth_deg)
        return np.array([math.cos(a), math.sin(a) * math.cos(az), math.sin(a) * math.sin(az), 0])

    g = TipGuard(DEFAULT_TIP_LIMITS)
    assert g.check("lift", tilted(4.1, 90.0)) is None  # pitched 4.1 deg
    assert g.check("lift", tilted(4.1, 10.0)) is None  # rolled 4.1 deg: turned 5.3 deg
    assert "tipped 5.10 deg in lift" in g.check("lift", tilted(9.2, 10.0))
