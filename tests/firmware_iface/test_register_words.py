"""Round trips of register words and the CiA 402 state machine under any command sequence."""

from hypothesis import given
from hypothesis import strategies as st

from firmware_iface.modbus import decode, encode
from firmware_iface.register_map import Register
from sim.servers.canopen_node import STATE_BITS, next_state

INT32 = Register("target", 18, "int32", "rw")
UINT32 = Register("counts_per_rev", 4, "uint32", "r")
UINT16 = Register("status", 17, "uint16", "r")


@given(st.integers(-(2**31), 2**31 - 1))
def test_int32_round_trip_high_word_first(value):
    words = encode(INT32, value)
    assert all(0 <= w <= 0xFFFF for w in words) and len(words) == 2
    assert words[0] == (value & 0xFFFFFFFF) >> 16
    assert decode(INT32, words) == value


@given(st.integers(0, 2**32 - 1))
def test_uint32_round_trip(value):
    assert decode(UINT32, encode(UINT32, value)) == value


@given(st.integers(0, 0xFFFF))
def test_uint16_round_trip(value):
    assert decode(UINT16, encode(UINT16, value)) == value


#: The commanded transitions of the CiA 402 state diagram (numbers as in the standard).
DIAGRAM = {
    ("SWITCH ON DISABLED", "READY TO SWITCH ON"),  # 2
    ("READY TO SWITCH ON", "SWITCHED ON"),  # 3
    ("SWITCHED ON", "OPERATION ENABLED"),  # 4
    ("READY TO SWITCH ON", "OPERATION ENABLED"),  # 3 + 4: "switch on" with bit 3 set (0x0F)
    ("OPERATION ENABLED", "SWITCHED ON"),  # 5
    ("SWITCHED ON", "READY TO SWITCH ON"),  # 6
    ("READY TO SWITCH ON", "SWITCH ON DISABLED"),  # 7
    ("OPERATION ENABLED", "READY TO SWITCH ON"),  # 8
    ("OPERATION ENABLED", "SWITCH ON DISABLED"),  # 9
    ("SWITCHED ON", "SWITCH ON DISABLED"),  # 10
    ("OPERATION ENABLED", "QUICK STOP ACTIVE"),  # 11
    ("QUICK STOP ACTIVE", "SWITCH ON DISABLED"),  # 12
    ("FAULT", "SWITCH ON DISABLED"),  # 15
}


@given(st.sampled_from(sorted(STATE_BITS)), st.lists(st.integers(0, 0xFFFF), max_size=30))
def test_any_controlword_sequence_only_walks_the_diagram(state, words):
    previous = 0
    for word in words:
        following = next_state(state, previous, word)
        assert following == state or (state, following) in DIAGRAM, (state, hex(word))
        if state == "FAULT" and following != state:
            assert word & 0x80 and not previous & 0x80  # only on the rising edge of bit 7
        state, previous = following, word
