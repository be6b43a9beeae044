"""The codec: random messages round-trip bit-exactly; bad payloads raise ContractError only."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from navi_contracts import (
    Action,
    CompileJob,
    CompileResult,
    ContractError,
    DistanceMatrix,
    FloorPlan,
    Message,
    ModelPromoted,
    RobotPose,
    StepRequest,
    StepResult,
    TelemetryEvent,
    decode,
    decode_any,
    encode,
)

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
f32 = st.floats(width=32, allow_nan=True, allow_infinity=True)
ident = st.text(alphabet="abcdefghijklmnopqrstuvwxyz0123456789-_", min_size=1, max_size=24)


@st.composite
def distance_matrices(draw: st.DrawFn) -> DistanceMatrix:
    n, az, el = draw(st.integers(0, 3)), draw(st.integers(1, 9)), draw(st.integers(1, 5))
    arr = hnp.arrays(np.float32, (n, az, el), elements=f32)  # (N, Az, El) float32, NaN/inf included
    return DistanceMatrix(
        env_ids=draw(hnp.arrays(np.int32, (n,))),  # (N,) int32
        azimuth_bins=az,
        elevation_bins=el,
        depth=draw(arr),
        semantic=draw(arr),
        delta_depth=draw(arr),
        step_id=draw(st.integers(0, 2**62)),
        timestamp=draw(finite),
        run_id=draw(st.text(max_size=20)),
    )


@st.composite
def step_results(draw: st.DrawFn) -> StepResult:
    obs = draw(st.none() | distance_matrices())
    n = obs.n_envs if obs is not None else draw(st.integers(0, 5))
    return StepResult(
        request_id=draw(ident),
        step_id=draw(st.integers(0, 10**9)),
        env_ids=draw(hnp.arrays(np.int32, (n,))),  # (N,) int32
        reward=draw(hnp.arrays(np.float32, (n,), elements=f32)),  # (N,) float32
        done=draw(hnp.arrays(np.bool_, (n,))),  # (N,) bool
        truncated=draw(hnp.arrays(np.bool_, (n,))),  # (N,) bool
        episode_return=draw(hnp.arrays(np.float32, (n,), elements=f32)),  # (N,) float32
        observation=obs,
    )


@st.composite
def actions(draw: st.DrawFn) -> Action:
    n = draw(st.integers(0, 6))
    return Action(
        env_ids=draw(hnp.arrays(np.int32, (n,))),  # (N,) int32
        command=draw(hnp.arrays(np.float32, (n, 4), elements=f32)),  # (N, 4) float32
        step_id=draw(st.integers(0, 10**9)),
        timestamp=draw(finite),
        policy_id=draw(st.text(max_size=10)),
    )


@st.composite
def step_requests(draw: st.DrawFn) -> StepRequest:
    n = draw(st.integers(0, 6))
    return StepRequest(
        request_id=draw(ident),
        env_ids=draw(hnp.arrays(np.int32, (n,))),  # (N,) int32
        actions=draw(hnp.arrays(np.float32, (n, 4), elements=f32)),  # (N, 4) float32
        reset=draw(st.booleans()),
    )


scalar_messages = st.one_of(
    st.builds(
        RobotPose,
        env_id=st.integers(0, 10**6),
        x=finite,
        y=finite,
        z=finite,
        roll=finite,
        pitch=finite,
        yaw=finite,
        timestamp=finite,
    ),
    st.builds(
        TelemetryEvent,
        key=st.from_regex(r"[a-z][a-z0-9_.]{0,30}", fullmatch=True),
        value=f32.map(float),
        step=st.integers(0, 2**62),
        run_id=ident,
        timestamp=finite,
    ),
    st.builds(
        CompileJob,
        job_id=ident,
        source=ident,
        output=ident,
        resolution=st.sampled_from([8, 64, 512]),
        scale=st.none() | finite,
        map_name=st.none() | ident,
        seeds=st.lists(st.tuples(finite, finite, finite), max_size=3).map(tuple),
        repair=st.booleans(),
    ),
    st.builds(
        CompileResult,
        job_id=ident,
        ok=st.just(True),
        output=ident,
        stats=st.dictionaries(ident, finite, max_size=4),
        duration_s=finite,
    ),
    st.builds(CompileResult, job_id=ident, ok=st.just(False), error_type=ident, error=st.text(min_size=1)),
    st.builds(
        ModelPromoted,
        alias=ident,
        version=ident,
        previous_version=st.none() | ident,
        checkpoint=ident,
        notes=st.text(max_size=30),
        tags=st.lists(ident, max_size=3).map(tuple),
        timestamp=finite,
    ),
)


@st.composite
def floor_plans(draw: st.DrawFn) -> FloorPlan:
    h, w = draw(st.integers(1, 6)), draw(st.integers(1, 6))
    return FloorPlan(
        scene=draw(ident),
        run_id=draw(ident),
        origin_x=draw(finite),
        origin_y=draw(finite),
        cell_size=draw(st.floats(0.01, 10.0)),
        z=draw(finite),
        clearance=draw(hnp.arrays(np.float32, (h, w), elements=f32)),  # (H, W) float32
        timestamp=draw(finite),
    )


any_message = st.one_of(
    distance_matrices(), step_results(), actions(), step_requests(), floor_plans(), scalar_messages
)


def _same(a: object, b: object) -> bool:
    """Bit-exact equality, arrays included (NaN payloads compared by bytes)."""
    if isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray)
        return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    if isinstance(a, Message):
        assert type(a) is type(b)
        return all(_same(getattr(a, f), getattr(b, f)) for f in type(a).model_fields)
    if isinstance(a, float) and isinstance(b, float) and np.isnan(a):
        return bool(np.isnan(b))
    return a == b


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(any_message)
def test_round_trip_is_bit_exact(msg: Message) -> None:
    payload = encode(msg)
    back = decode(payload, type(msg))
    assert _same(msg, back)
    assert _same(msg, decode_any(payload))


def test_arrays_decode_as_views_without_copy() -> None:
    depth = np.random.default_rng(0).random((2, 256, 48), dtype=np.float32)  # (N, Az, El)
    dm = DistanceMatrix(
        env_ids=np.arange(2, dtype=np.int32),
        azimuth_bins=256,
        elevation_bins=48,
        depth=depth,
        semantic=depth,
        delta_depth=depth,
        step_id=1,
        timestamp=0.0,
    )
    back = decode(encode(dm), DistanceMatrix)
    assert not back.depth.flags.owndata and not back.depth.flags.writeable
    np.testing.assert_array_equal(back.depth, depth)


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(any_message, st.data())
def test_truncated_payloads_raise_contract_error(msg: Message, data: st.DataObject) -> None:
    payload = encode(msg)
    cut = data.draw(st.integers(0, len(payload) - 1))
    with pytest.raises(ContractError):
        decode(payload[:cut], type(msg))


@settings(max_examples=500, suppress_health_check=[HealthCheck.too_slow])
@given(any_message, st.data())
def test_mutated_payloads_raise_contract_error_or_stay_valid(msg: Message, data: st.DataObject) -> None:
    payload = bytearray(encode(msg))
    for _ in range(data.draw(st.integers(1, 4))):
        i = data.draw(st.integers(0, len(payload) - 1))
        payload[i] = data.draw(st.integers(0, 255))
    try:
        back = decode(bytes(payload), type(msg))
    except ContractError:
        return
    # A flip inside a number can leave a valid message: it must then be whole and valid.
    assert type(back) is type(msg)
    type(msg).model_validate(back.model_dump())


@given(st.binary(max_size=200))
def test_garbage_raises_contract_error(blob: bytes) -> None:
    with pytest.raises(ContractError):
        decode(blob, TelemetryEvent)


def _telemetry() -> TelemetryEvent:
    return TelemetryEvent(key="actor.training.sps", value=1.0, step=1, run_id="r", timestamp=0.0)


def test_unknown_schema_version_is_rejected() -> None:
    envelope = msgpack.unpackb(encode(_telemetry()))
    envelope["v"] = 99
    with pytest.raises(ContractError, match="schema version 99"):
        decode(msgpack.packb(envelope), TelemetryEvent)


def test_wrong_type_and_unknown_type_are_rejected() -> None:
    payload = encode(_telemetry())
    with pytest.raises(ContractError, match="expected a RobotPose"):
        decode(payload, RobotPose)
    envelope = msgpack.unpackb(payload)
    envelope["type"] = "Nope"
    with pytest.raises(ContractError, match="unknown message type"):
        decode_any(msgpack.packb(envelope))


def _dm(depth: np.ndarray) -> bytes:
    """Encode a DistanceMatrix whose depth array is replaced after validation (a hostile sender)."""
    good = np.zeros((1, 4, 2), np.float32)  # (N, Az, El)
    dm = DistanceMatrix(
        env_ids=np.zeros(1, np.int32),
        azimuth_bins=4,
        elevation_bins=2,
        depth=good,
        semantic=good,
        delta_depth=good,
        step_id=0,
        timestamp=0.0,
    )
    object.__setattr__(dm, "depth", depth)
    return encode(dm)


def test_wrong_dtype_or_shape_is_rejected() -> None:
    with pytest.raises(ContractError, match="dtype"):
        decode(_dm(np.zeros((1, 4, 2), np.float64)), DistanceMatrix)
    with pytest.raises(ContractError, match="shape"):
        decode(_dm(np.zeros((1, 4, 3), np.float32)), DistanceMatrix)


def test_oversized_payload_is_rejected() -> None:
    payload = _dm(np.zeros((1, 4, 2), np.float32))
    with pytest.raises(ContractError, match="exceeds"):
        decode(payload, DistanceMatrix, max_bytes=len(payload) - 1)


def test_array_byte_count_must_match_shape() -> None:
    ext = msgpack.ExtType(1, b"\x0c\x00" + msgpack.packb(["<f4", [1, 4, 2]]) + b"\x00" * 31)
    envelope = msgpack.unpackb(
        _dm(np.zeros((1, 4, 2), np.float32)), ext_hook=lambda c, d: msgpack.ExtType(c, d)
    )
    envelope["data"]["depth"] = ext
    with pytest.raises(ContractError):
        decode(msgpack.packb(envelope), DistanceMatrix)


def test_object_arrays_cannot_be_sent() -> None:
    with pytest.raises(ContractError, match="cannot go on the wire"):
        _dm(np.array([[["x", "y"]] * 4], dtype=object))
