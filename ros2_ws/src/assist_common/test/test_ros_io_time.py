"""ros_io.sec_to_stamp: float seconds -> builtin_interfaces/Time (sim_node's /clock and image stamps)."""
from assist_common.ros_io import sec_to_stamp, stamp_to_sec


def test_a_time_just_below_a_whole_second_rounds_up_into_the_next_second():
    # 240 Hz steps add up to 6.9999999999..., whose fraction alone rounds to 1e9 ns: the old
    # /clock code wrapped that to 0 ns in the same second, stamping one frame a second 1 s early
    s = sec_to_stamp(6.9999999999)
    assert (s.sec, s.nanosec) == (7, 0)


def test_accumulated_240_hz_steps_give_monotonic_stamps_that_round_trip():
    t, last = 0.0, -1
    for _ in range(240 * 20):
        t += 1.0 / 240.0
        s = sec_to_stamp(t)
        assert 0 <= s.nanosec < 1_000_000_000
        ns = s.sec * 1_000_000_000 + s.nanosec
        assert ns > last
        last = ns
        assert abs(stamp_to_sec(s) - t) < 1e-9


def test_fills_a_given_stamp_in_place():
    from rosgraph_msgs.msg import Clock
    msg = Clock()
    assert sec_to_stamp(12.25, msg.clock) is msg.clock
    assert (msg.clock.sec, msg.clock.nanosec) == (12, 250_000_000)
