import numpy as np
import pytest

from shared.codec import CodecError, decode, decode_any, encode, peek
from shared.schemas import (
    CameraIntrinsics, Candidate, CandidateKind, Decision, ErrorReply, MapChunk, JobEvent, JobEventKind,
    JobState, MissionStep, Panorama, Pose,
)


def panorama(v=12, h=32, w=32, semantic=True):
    rng = np.random.default_rng(0)
    return Panorama(
        pose=Pose(position_m=(1.0, -2.0, 0.0), heading_rad=0.3),
        camera=CameraIntrinsics(width_px=w, height_px=h),
        headings_rad=np.linspace(0, 6, v),
        rgb=rng.integers(0, 255, (v, h, w, 3), dtype=np.uint8),
        depth_m=rng.random((v, h, w), dtype=np.float32),
        semantic=rng.integers(-1, 20, (v, h, w)).astype(np.int32) if semantic else None,
    )


def test_round_trip_keeps_every_array_and_field():
    p = panorama()
    q = decode(encode(p), Panorama)
    assert q.pose == p.pose and q.camera == p.camera
    for name in ("headings_rad", "rgb", "depth_m", "semantic"):
        a, b = getattr(p, name), getattr(q, name)
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b)


def test_decode_is_zero_copy_over_the_received_buffer():
    payload = bytes(encode(panorama()))
    q = decode(payload, Panorama)
    # The arrays are views over the payload: no copy, and read-only because bytes are immutable.
    assert not q.rgb.flags.owndata and not q.rgb.flags.writeable
    assert np.shares_memory(q.rgb, np.frombuffer(payload, np.uint8))


def test_arrays_are_aligned_for_their_dtype():
    q = decode(bytes(encode(panorama())), Panorama)
    for arr in (q.rgb, q.depth_m, q.semantic, q.headings_rad):
        assert arr.ctypes.data % arr.dtype.itemsize == 0


def test_nested_models_enums_and_optional_none():
    ev = JobEvent(job_id="m1", seq=3, kind=JobEventKind.STEP, state=JobState.RUNNING,
                      data=MissionStep(pose=Pose(position_m=(1.0, 2.0, 0.0)),
                                       candidates=[Candidate(index=0, kind=CandidateKind.STOP)],
                                       decision=Decision(candidate_index=0, kind=CandidateKind.STOP)))
    back = decode(encode(ev), JobEvent)
    assert back == ev and isinstance(back.data, MissionStep) and back.data.candidates[0].kind == CandidateKind.STOP
    p = panorama(semantic=False)
    assert decode(encode(p), Panorama).semantic is None


def test_empty_and_large_arrays():
    chunk = MapChunk(map_id="m", version=1, index=0, count=1, xyz_m=np.zeros((0, 3), np.float32),
                     rgb=np.zeros((0, 3), np.uint8))
    assert decode(encode(chunk), MapChunk).xyz_m.shape == (0, 3)


@pytest.mark.parametrize(
    "mutate, reason",
    [
        (lambda b: b[:3], "truncated"),
        (lambda b: b"XXXX" + b[4:], "not_ours"),
        (lambda b: b[: len(b) // 2], "truncated"),
        (lambda b: b[:8] + b"\xc1" * 40 + b[48:], "malformed"),
        (lambda b: b"", "truncated"),
    ],
)
def test_bad_payloads_raise_one_typed_error(mutate, reason):
    payload = bytes(encode(panorama()))
    with pytest.raises(CodecError) as err:
        decode(mutate(payload), Panorama)
    assert err.value.reason == reason


def test_wrong_schema_version_and_invalid_fields():
    payload = bytes(encode(Pose(position_m=(0, 0, 0))))
    with pytest.raises(CodecError, match="wrong_schema"):
        decode(payload, Panorama)

    class PoseV2(Pose):
        SCHEMA = "Pose"
        VERSION = 2

    with pytest.raises(CodecError, match="wrong_version"):
        decode(payload, PoseV2)
    # A payload that is ours but whose fields do not validate (shape mismatch) is refused too.
    p = panorama()
    bad = bytes(encode(p)).replace(b"\xa8width_px\x20", b"\xa8width_px\x21")
    with pytest.raises(CodecError, match="invalid"):
        decode(bad, Panorama)


def test_oversized_payload_is_refused_before_parsing():
    with pytest.raises(CodecError, match="oversized"):
        decode(bytes(encode(panorama())), Panorama, max_bytes=1000)


def test_non_finite_pose_is_invalid():
    from shared.codec import _HEADER  # noqa: F401  (the envelope format is private)

    good = bytes(encode(Pose(position_m=(0.0, 0.0, 0.0))))
    schema, version, data = peek(good)
    assert schema == "Pose" and version == 1
    import msgpack

    from shared import codec

    header = msgpack.packb({"s": "Pose", "v": 1, "d": {"position_m": [float("nan"), 0, 0]}, "a": []})
    payload = codec._HEADER.pack(codec.MAGIC, len(header)) + header
    with pytest.raises(CodecError, match="finite"):
        decode(payload, Pose)


def test_decode_any_picks_the_schema():
    err = ErrorReply(code="not_found", message="no map x")
    out = decode_any(encode(err), {"Pose": Pose, "ErrorReply": ErrorReply})
    assert isinstance(out, ErrorReply) and out.message == "no map x"


def test_object_arrays_are_refused():
    with pytest.raises(Exception):
        MapChunk(map_id="m", version=1, index=0, count=1, xyz_m=np.array([[None, 1, 2]], dtype=object),
                 rgb=np.zeros((1, 3), np.uint8))
