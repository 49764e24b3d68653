"""Remote keys and sticks: bit map, byte layout, edges and combos."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hw import go2_msgs as g
from hw import joystick as js

FACTS_ORDER = ["R1", "L1", "Start", "Select", "R2", "L2", "F1", "F2",
               "A", "B", "X", "Y", "Up", "Right", "Down", "Left"]


def S(*keys: str, **sticks) -> js.JoystickState:
    return js.JoystickState(js.key_mask(*keys), **sticks)


def test_bit_map():
    for i, name in enumerate(FACTS_ORDER):
        assert js.key_mask(name) == 1 << i
    assert js.key_names(0b1010_0000) == {"L2", "F2"}
    with pytest.raises(ValueError, match="unknown key"):
        js.key_mask("Home")


def test_wireless_remote_byte_layout():
    keys = js.key_mask("L2", "A", "Left")
    raw = js.encode_wireless_remote(keys, lx=0.25, ly=-0.5, rx=0.75, ry=-1.0, l2=0.125)
    assert len(raw) == 40
    assert struct.unpack_from("<H", raw, 2)[0] == keys
    got = [struct.unpack_from("<f", raw, off)[0] for off in (4, 8, 12, 16, 20)]
    assert got == [0.25, 0.75, -1.0, 0.125, -0.5]  # lx, rx, ry, L2, ly
    assert raw[24:] == bytes(16)
    s = js.JoystickState.from_wireless_remote(raw)
    assert s == js.JoystickState(keys, 0.25, -0.5, 0.75, -1.0, 0.125)
    assert s.names == {"L2", "A", "Left"} and s.held("L2", "A") and not s.held("B")
    with pytest.raises(ValueError):
        js.JoystickState.from_wireless_remote(raw[:39])
    with pytest.raises(ValueError):
        js.encode_wireless_remote(1 << 16)


def test_from_lowstate_and_wireless_controller():
    keys = js.key_mask("R1", "Down")
    b = g.LowStateBuffer()
    b.set_wireless_remote(js.encode_wireless_remote(keys, lx=0.5))
    v = g.decode_lowstate(b.finalize())
    assert js.JoystickState.from_wireless_remote(v.wireless_remote) == js.JoystickState(keys, 0.5)
    for pad in (True, False):
        frame = js.encode_wireless_controller(keys=keys, lx=0.5, ry=-0.25, pad=pad)
        s = js.JoystickState.from_wireless_controller(frame)
        assert s == js.JoystickState(keys, lx=0.5, ry=-0.25)
        assert js.JoystickState.from_wireless_controller(js.decode_wireless_controller(frame)) == s


def test_edges():
    j = js.Joystick()
    e = j.update(S("A"))
    assert e.pressed == {"A"} and not e.released and not e.combos
    assert not j.update(S("A", lx=0.3))  # sticks alone are no event
    e = j.update(S("B"))
    assert e.pressed == {"B"} and e.released == {"A"}
    j2 = js.Joystick(initial=S("A"))
    assert not j2.update(S("A"))


def test_combo_fires_once_on_press_edge():
    j = js.Joystick()
    assert not j.update(S("L2")).combos
    assert j.update(S("L2", "A")).combos == (js.COMBO_STAND,)
    assert not j.update(S("L2", "A")).combos  # held: no repeat
    assert not j.update(S("L2")).combos
    assert j.update(S("L2", "A")).fired(js.COMBO_STAND)  # re-press fires again
    # extra keys do not block; damp fires while stand is held, stand does not re-fire
    assert j.update(S("L2", "A", "B")).combos == (js.COMBO_DAMP,)
    j = js.Joystick()
    assert j.update(S("A", "L2")).combos == (js.COMBO_STAND,)  # simultaneous press
    j = js.Joystick()
    j.update(S("A"))
    assert j.update(S("A", "L2")).combos == (js.COMBO_STAND,)  # modifier pressed last
    j = js.Joystick()
    assert j.update(S("L2", "A", "B")).combos == (js.COMBO_DAMP, js.COMBO_STAND)  # damp first


@pytest.mark.parametrize("leg, keys", [("FL", ("L1", "Up")), ("FR", ("R1", "Up")),
                                       ("RL", ("L1", "Down")), ("RR", ("R1", "Down"))])
def test_calibration_combos(leg, keys):
    assert set(js.COMBO_CALIB) == {"FL", "FR", "RL", "RR"}
    j = js.Joystick()
    j.update(S(keys[0]))
    assert j.update(S(*keys)).combos == (js.COMBO_CALIB[leg],)


def test_combos_are_distinct():
    masks = [c.mask for c in js.DEFAULT_COMBOS]
    assert len(set(masks)) == len(masks)
    assert len({c.name for c in js.DEFAULT_COMBOS}) == len(masks)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(0, 0xFFFF), min_size=1, max_size=30))
def test_combo_is_rising_edge_of_all_held(seq):
    j = js.Joystick()
    prev = 0
    for keys in seq:
        e = j.update(js.JoystickState(keys))
        assert e.pressed == js.key_names(keys & ~prev)
        assert e.released == js.key_names(prev & ~keys)
        want = tuple(c for c in js.DEFAULT_COMBOS
                     if (keys & c.mask) == c.mask and (prev & c.mask) != c.mask)
        assert e.combos == want
        prev = keys


def test_key_names_from_numpy_record():
    frame = js.encode_wireless_controller(keys=js.key_mask("Start"))
    rec = js.decode_wireless_controller(frame)
    assert rec.shape == () and rec.dtype == g.WIRELESS_CDR
    assert js.JoystickState.from_wireless_controller(rec).names == {"Start"}
