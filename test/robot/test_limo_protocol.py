"""LIMO protocol: the doc's worked frames (§7) as test vectors, saturation, and the stream parser."""

import math
import random

from hypothesis import given, settings
from hypothesis import strategies as st
import pytest

from gsrmr_robot.limo import kinematics as kin
from gsrmr_robot.limo import protocol as p

A = "55 0E 01 11 00 C8 FE 0C 00 00 00 00 00 D2"
B = "55 0E 04 21 01 00 00 00 00 00 00 00 00 01"
B_MECANUM = "55 0E 04 21 01 00 01 00 00 00 00 00 00 02"
C = "55 0E 02 21 01 5E FF 06 00 00 00 64 00 C8"
D = "55 0E 01 11 01 2C 00 00 00 00 00 96 00 C3"
E = "55 0E 02 11 00 01 00 7B 00 00 01 00 00 7D"


def h(s: str) -> bytes:
    return bytes.fromhex(s)


def test_doc_example_a_diff_motion_command():
    cmd = kin.command_to_wire(p.MotionMode.DIFF, 0.2, -0.5)
    assert p.encode_message(cmd) == h(A)
    assert p.MotionCommand.from_data(p.decode_frame(h(A)).data) == p.MotionCommand(0.2, -0.5, 0.0, 0.0)


def test_doc_example_b_enable_frames():
    assert p.encode_message(p.ControlModeConfig()) == h(B)
    assert p.encode_message(p.ControlModeConfig(p.ControlMode.COMMANDED, mecanum_switch=True)) == h(B_MECANUM)
    assert p.decode_message(p.decode_frame(h(B_MECANUM))) == p.ControlModeConfig(1, True)


def test_doc_example_c_motion_state_decode_in_diff_and_ackermann():
    frame = p.decode_frame(h(C))
    assert frame.can_id == p.ID_MOTION_STATE and frame.count == 0
    msg = p.decode_message(frame)
    assert msg == p.MotionState(0.350, -0.250, 0.0, 0.100)
    assert p.encode_message(msg) == h(C)
    diff = kin.feedback_to_body(p.MotionMode.DIFF, msg)
    assert (diff.vx_mps, diff.vy_mps, diff.wz_radps) == (0.35, 0.0, -0.25)
    ack = kin.feedback_to_body(p.MotionMode.ACKERMANN, msg)
    assert ack.wz_radps == pytest.approx(0.3981, abs=1e-4)  # same yaw rate as the doc's AgileX formula
    assert ack.vx_mps == pytest.approx(0.35) and ack.vy_mps == 0.0  # rigid model at the rear-axle centre


def test_doc_example_d_ackermann_command():
    assert kin.ackermann_inner_angle(0.3, 0.5) == pytest.approx(0.37108, abs=1e-5)
    cmd = kin.command_to_wire(p.MotionMode.ACKERMANN, 0.3, 0.5)
    assert p.encode_message(cmd) == h(D)


def test_doc_example_e_system_state():
    msg = p.decode_message(p.decode_frame(h(E)))
    assert msg == p.SystemState(p.VehicleState.NORMAL, p.ControlMode.COMMANDED, 12.3, 0, p.MotionMode.ACKERMANN, 0)
    assert p.encode_message(msg) == h(E)
    assert msg.errors == []


def test_error_bits_decoded():
    assert p.decode_error_bits(0x0001 | 0x0004 | 0x0100) == ["battery_low_fault", "rc_signal_lost",
                                                             "drive_status_error"]
    assert p.decode_error_bits(0x8000) == ["bit_0x8000"]


def test_int16_fields_saturate_never_wrap():
    data = p.MotionCommand(40.0, -40.0, math.nan, math.inf).data()
    assert data == bytes.fromhex("7FFF 8000 0000 7FFF")
    assert p.saturate_int16(-math.inf) == p.INT16_MIN
    assert p.saturate_int16(32.7675, 1000) == 32767  # rounds to 32768 → saturates
    assert p.saturate_int16(1.005, 1000) == 1005  # nearest, not truncated (pylimo gave 1004)
    gyro = p.ImuGyro.from_data(p.ImuGyro(100.0, -100.0, 0.5).data())
    assert gyro.x_radps == pytest.approx(327.67 * math.pi / 180)
    assert gyro.y_radps == pytest.approx(-327.68 * math.pi / 180)
    assert gyro.z_radps == pytest.approx(0.5, abs=1e-3)


@pytest.mark.parametrize("msg", [
    p.MotionCommand(-0.123, 0.456, -0.789, 0.15),
    p.ControlModeConfig(p.ControlMode.UART, False),
    p.SystemState(p.VehicleState.EXCEPTION, p.ControlMode.STANDBY, 11.9, 0x0105, p.MotionMode.MECANUM, 7),
    p.MotionState(-1.0, -2.5, 0.3, -0.2),
    p.WheelOdometry(-123456, 2**31 - 1),
    p.ImuAccel(-9.81, 0.25, 3.5, 9),
    p.ImuGyro(-0.5, 0.25, 1.0, 3),
    p.ImuEuler(-3.0, 0.5, -1.2, 200),
])
def test_every_message_round_trips(msg):
    frame = p.decode_frame(p.encode_message(msg))
    assert frame.can_id == msg.ID
    back = p.decode_message(frame)
    assert type(back) is type(msg)
    for name, value in msg.__dict__.items():
        assert getattr(back, name) == pytest.approx(value, abs=2e-4), name


def test_imu_values_are_signed_and_converted():
    # negative −1.00 must not wrap to 654.36 (pylimo bug); gyro deg/s → rad/s; Euler order yaw, pitch, roll
    data = bytes.fromhex("FF9C 0064 0000 00 05")  # −100, +100, 0 → ×0.01
    assert p.ImuAccel.from_data(data).x_mps2 == -1.0
    gyro = p.ImuGyro.from_data(data)
    assert gyro.x_radps == pytest.approx(math.radians(-1.0)) and gyro.y_radps == pytest.approx(math.radians(1.0))
    euler = p.ImuEuler.from_data(data)
    assert euler.yaw_rad == pytest.approx(math.radians(-1.0)) and euler.pitch_rad == pytest.approx(math.radians(1))
    assert euler.count == 5


@pytest.mark.parametrize("raw, why", [(h(A)[:-1], "14 bytes"), (b"\x54" + h(A)[1:], "header"),
                                      (h(A)[:1] + b"\x0d" + h(A)[2:], "length"),
                                      (h(A)[:-1] + b"\xd3", "checksum")])
def test_decode_frame_rejects(raw, why):
    with pytest.raises(p.ProtocolError, match=why):
        p.decode_frame(raw)


def test_implausible_payloads_rejected():
    with pytest.raises(p.ProtocolError):
        p.decode_message(p.Frame(p.ID_MOTION_STATE, p.MotionState(9.0).data()))
    with pytest.raises(p.ProtocolError):
        p.decode_message(p.Frame(p.ID_SYSTEM_STATE, bytes.fromhex("00 07 00 7B 00 00 01 00")))  # control 7
    assert p.decode_message(p.Frame(0x251, bytes(8))) is None  # known, not decoded


def stream(*msgs, count=0) -> bytes:
    return b"".join(p.encode_message(m, count) for m in msgs)


def plain_parser() -> p.FrameParser:
    return p.FrameParser(confirm_frames=1, check_count=False)


def test_parser_byte_by_byte_and_in_one_chunk():
    data = h(A) + h(C) + h(E)
    for chunks in ([data], [bytes([b]) for b in data], [data[:5], data[5:20], data[20:]]):
        parser = plain_parser()
        frames = [f for c in chunks for f in parser.feed(c)]
        assert [f.to_bytes() for f in frames] == [h(A), h(C), h(E)]
        assert parser.stats.errors() == 0 and parser.stats.skipped_bytes == 0


def test_bad_length_byte_is_rechecked_as_header():
    # "55 55 0E …": the official parser loses this frame
    parser = plain_parser()
    frames = parser.feed(b"\x55" + h(C))
    assert [f.to_bytes() for f in frames] == [h(C)]
    assert parser.stats.bad_length == 1


def test_header_hidden_inside_a_corrupted_frame_is_found():
    # a truncated frame (bytes lost) followed by a good one: the good header sits inside the first 14 bytes
    parser = plain_parser()
    frames = parser.feed(h(A)[:9] + h(C))
    assert [f.to_bytes() for f in frames] == [h(C)]
    assert parser.stats.bad_checksum == 1


def test_checksum_failure_counted_and_dropped():
    bad = bytearray(h(C))
    bad[6] ^= 0x10
    parser = plain_parser()
    assert parser.feed(bytes(bad) + h(E))[0].to_bytes() == h(E)
    assert parser.stats.bad_checksum == 1 and parser.stats.frames_ok == 1


def test_unknown_ids_ignored_and_counted():
    parser = plain_parser()
    out = parser.feed(p.encode_frame(0x777, bytes(8)) + p.encode_frame(0x777, bytes(8)) + h(C))
    assert [f.can_id for f in out] == [p.ID_MOTION_STATE]
    assert parser.stats.unknown_id == 2 and parser.stats.unknown_ids == {0x777: 2}


def test_id_confirmation_drops_isolated_ids():
    parser = p.FrameParser(confirm_frames=3, confirm_window_s=0.5)
    state = p.MotionState(0.3)
    accepted = [len(parser.feed(stream(state), t_s=0.02 * i)) for i in range(5)]
    assert accepted == [0, 0, 1, 1, 1]
    # an isolated 0x321 (a 0x221 whose ID bit 8 flipped) is never dispatched
    frame = bytearray(stream(state))
    frame[2] ^= 0x01
    assert parser.feed(bytes(frame), t_s=0.2) == []
    # frames of one ID spread wider than the window do not confirm it
    slow = p.FrameParser(confirm_frames=3, confirm_window_s=0.5)
    assert sum(len(slow.feed(stream(p.ImuAccel()), t_s=1.0 * i)) for i in range(5)) == 0


def test_count_byte_learns_constant_or_rolling_counter():
    parser = p.FrameParser(confirm_frames=1)
    m = p.MotionState(0.1)
    ok = [len(parser.feed(stream(m, count=c))) for c in (0, 0, 0, 1, 0, 0)]
    assert ok == [1, 1, 1, 0, 1, 1]  # a flipped count (0 → 1) is rejected in a constant stream
    rolling = p.FrameParser(confirm_frames=1)
    ok = [len(rolling.feed(stream(m, count=c))) for c in (5, 6, 7, 9, 10, 11, 12)]
    assert ok == [1, 1, 1, 0, 0, 1, 1]  # after a gap the counter re-locks on 3 consistent frames
    assert rolling.stats.count_mismatch == 2
    # the same count flip in two consecutive frames is still rejected
    twice = p.FrameParser(confirm_frames=1)
    assert [len(twice.feed(stream(m, count=c))) for c in (0, 0, 4, 4, 0)] == [1, 1, 0, 0, 1]


def test_parser_recovers_after_random_garbage():
    rng = random.Random(3)
    parser = p.FrameParser()
    good = [p.encode_message(p.MotionState(0.001 * i)) for i in range(200)]
    got = []
    for i, frame in enumerate(good):
        junk = bytes(rng.randrange(256) for _ in range(rng.randrange(30)))
        got += parser.feed(junk + frame, t_s=0.02 * i)
    received = {f.to_bytes() for f in got}
    assert received <= set(good)
    assert len(received) >= 150  # some frames are swallowed by a junk 0x55 followed by resync
    assert parser.stats.skipped_bytes > 0


@settings(max_examples=300, deadline=None)
@given(st.lists(st.binary(max_size=64), max_size=20))
def test_fuzz_parser_never_raises_and_only_returns_checksummed_frames(chunks):
    parser = p.FrameParser(confirm_frames=1, check_count=False, known_ids=None)
    everything = b"".join(chunks)
    for chunk in chunks:
        for frame in parser.feed(chunk):
            raw = frame.to_bytes()
            assert raw in everything
            assert p.decode_frame(raw) == p.Frame(frame.can_id, frame.data, frame.count)
    assert parser.stats.bytes_in == len(everything)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.binary(max_size=20).map(lambda b: b.replace(b"\x55", b"")),
                          st.integers(-32768, 32767), st.integers(-32768, 32767)), max_size=15))
def test_fuzz_every_frame_after_header_free_garbage_is_recovered(items):
    parser = plain_parser()
    expected, data = [], b""
    for junk, a, b in items:
        frame = p.encode_frame(p.ID_IMU_EULER, a.to_bytes(2, "big", signed=True) + b.to_bytes(2, "big", signed=True)
                               + bytes(4))
        expected.append(frame)
        data += junk + frame
    assert [f.to_bytes() for f in parser.feed(data)] == expected
