"""Hypothesis strategies for every message type and a few ready messages, shared by the codec's
tests (tests/msgs/)."""

from __future__ import annotations

import msgpack
import numpy as np
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from mogs_node import msgs

INT64 = st.integers(min_value=-(1 << 63), max_value=(1 << 63) - 1)
FINITE = st.floats(allow_nan=False, allow_infinity=False, width=64)
TEXT = st.text(max_size=40)


def array_values(spec: msgs.ArraySpec, dims: dict[str, int], pattern: tuple) -> st.SearchStrategy:
    shape = tuple(p if isinstance(p, int) else dims[p] for p in pattern)
    return st.sampled_from(spec.dtypes).flatmap(
        lambda dt: hnp.arrays(
            np.dtype(dt),
            shape,
            elements=(
                {"allow_nan": False, "allow_infinity": False}
                if spec.finite and np.dtype(dt).kind == "f"
                else None
            ),
        )
    )


def scalar_values(kind: str) -> st.SearchStrategy:
    return {
        "int": INT64,
        "float": FINITE,
        "float_or_nan": st.one_of(FINITE, st.just(float("nan"))),
        "str": TEXT,
        "bool": st.booleans(),
        "vec3": st.tuples(FINITE, FINITE, FINITE),
        "dict_num": st.dictionaries(
            TEXT, st.one_of(st.integers(-(2**31), 2**31), FINITE), max_size=5
        ),
        "dict_any": st.dictionaries(
            TEXT,
            st.one_of(
                st.integers(-1000, 1000),
                FINITE,
                TEXT,
                st.dictionaries(TEXT, st.integers(0, 10**9), max_size=3),
            ),
            max_size=4,
        ),
    }[kind]


@st.composite
def messages(draw: st.DrawFn, cls: type[msgs.Message]) -> msgs.Message:
    dims = {s: draw(st.integers(0, 6)) for s in ("N", "M", "D")}
    dims["H"] = draw(st.integers(1, 8))
    dims["W"] = draw(st.integers(1, 8))
    values = {name: draw(scalar_values(kind)) for name, kind in cls.SCALARS.items()}
    for name, spec in cls.ARRAYS.items():
        if spec.optional and draw(st.booleans()):
            values[name] = None
            continue
        pattern = draw(st.sampled_from(spec.shapes))
        values[name] = draw(array_values(spec, dims, pattern))
    if cls is msgs.Image:
        values["encoding"] = (
            "mono8" if values["data"].ndim == 2 else draw(st.sampled_from(["rgb8", "bgr8"]))
        )
    if cls is msgs.DepthMap:
        values["kind"] = draw(st.sampled_from(msgs.DepthMap.KINDS))
    if cls is msgs.CameraInfo:  # a valid calibration: its fields are checked against each other
        model = draw(st.sampled_from(sorted(msgs.CameraInfo.MODELS)))
        n = draw(st.sampled_from(msgs.CameraInfo.MODELS[model]))
        fx, fy = draw(st.floats(1.0, 5e3)), draw(st.floats(1.0, 5e3))
        values.update(
            distortion_model=model,
            distortion_coeffs=draw(hnp.arrays(np.float64, n, elements=st.floats(-1.0, 1.0))),
            K=np.array([[fx, 0.0, 10.0], [0.0, fy, 5.0], [0.0, 0.0, 1.0]]),
            width=draw(st.integers(1, 4096)),
            height=draw(st.integers(1, 4096)),
            camera_height_m=draw(st.one_of(st.floats(0.0, 10.0), st.just(float("nan")))),
        )
    return cls(**values)


def keyframe_msg(n: int = 3) -> msgs.Keyframe:
    return msgs.Keyframe(
        stamp_ns=5,
        frame_id="cam",
        keyframe_id=1,
        image=np.zeros((4, 6, 3), np.uint8),
        K=np.eye(3),
        T_world_cam=np.eye(4),
        feature_ids=np.arange(n, dtype=np.int64),
        feature_uv_px=np.zeros((n, 2), np.float32),
        feature_xyz_cam_m=np.ones((n, 3), np.float32),
        feature_weight=np.ones(n, np.float32),
    )


def header_of(frames: list) -> dict:
    return msgpack.unpackb(bytes(frames[1]), raw=False)


def with_header(frames: list, header: dict) -> list:
    return [frames[0], msgpack.packb(header, use_bin_type=True), *frames[2:]]
