"""Malformed payloads for every message type: each one must be refused, none may crash.

Every payload :func:`bad_payloads` yields is invalid by construction — random bytes,
truncated msgpack, a non-map, a wrong schema, or a valid message with one field broken
(a wrong type, NaN or infinity, an integer out of range, a dtype given as a list or an
unknown string, a shape with 70 dimensions or a huge product, data of the wrong length,
a deeply nested or ragged list) — so a service must count exactly as many rejections as
it was sent. Used by the suite (a fast sample) and benchmarks/bench_fuzz.py (≥ 100 000
per key).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from typing import Any

import msgpack
import numpy as np

from slamlens.common.messages import (
    CameraControl,
    CameraFrame,
    CameraPose,
    Health,
    Message,
    Observations,
    Odometry,
    Registration,
    ServiceStatus,
    SlamState,
    StateSummary,
    Truth,
    Violation,
)


def valid(kind: type[Message], *, robot: str = "robot1", camera: str = "cam1",
          seq: int = 1) -> Message:
    """A small valid message of ``kind``."""
    n = 2
    if kind is Odometry:
        return Odometry(robot=robot, stamp=1.0, dt=0.1, v=0.1, w=0.0)
    if kind is Observations:
        return Observations(robot=robot, stamp=1.0, ids=np.array([1, 2]),
                            ranges=np.array([1.0, 1.5]), bearings=np.array([0.1, -0.2]))
    if kind is Truth:
        return Truth(robot=robot, stamp=1.0, pose=np.zeros(3), landmark_ids=np.array([1, 2]),
                     landmarks=np.ones((2, 2)))
    if kind is SlamState:
        N = 3 + 2 * n
        return SlamState(robot=robot, seq=seq, stamp=0.1 * seq, step="predict",
                         pose=np.zeros(3), landmark_ids=np.array([1, 2]),
                         landmarks=np.ones((2, 2)), covariance=np.eye(N) * 0.01, epoch=7)
    if kind is Health:
        return Health(robot=robot, seq=seq, stamp=1.0, ok=True, suspects=np.zeros(0, np.int64),
                      violations=(Violation(kind="pair", ids=(1, 2), step=1, value=1.0),))
    if kind is CameraFrame:
        return CameraFrame(camera=camera, seq=seq, stamp=1.0, encoding="jpeg", width=4,
                           height=4, data=b"\xff\xd8\xff\xd9")
    if kind is Registration:
        return Registration(camera=camera, robot=robot, stamp=1.0, K=np.eye(3),
                            dist=np.zeros(5), width=640, height=480,
                            T_camera_from_map=np.eye(4), reprojection_error_px=0.1)
    if kind is CameraControl:
        return CameraControl(command="reregister", robot=robot)
    if kind is CameraPose:
        return CameraPose(camera=camera, stamp=1.0, T_world_from_camera=np.eye(4))
    if kind is CameraControl:
        return CameraControl(command="reregister", robot=robot)
    if kind is ServiceStatus:
        return ServiceStatus(service="estimator", name=f"robot-{robot}", host="h", pid=1,
                             version="0", started=1.0, uptime_s=2.0, state="running",
                             robot=robot, epoch=7, counts={"states": 3.0},
                             rates={"states": 1.5})
    if kind is StateSummary:
        return StateSummary(robot=robot, seq=seq, stamp=1.0, step="update", pose=np.zeros(3),
                            pose_covariance=np.eye(3) * 0.01, landmark_ids=np.array([1, 2]),
                            landmarks=np.ones((2, 2)),
                            landmark_covariances=np.stack([np.eye(2) * 0.01] * 2), epoch=7,
                            what="clusters", cluster_threshold_m=0.6, cluster_count=0,
                            groups=np.array([0, 1]), group_pairs=np.array([[0, 1]]),
                            pair_count=np.array([1]), min_pair=np.array([[0, 1]]),
                            max_pair=np.array([[0, 1]]), min_Pd=np.eye(2)[None] * 0.02,
                            mean_Pd=np.eye(2)[None] * 0.02, max_Pd=np.eye(2)[None] * 0.02)
    raise TypeError(kind)


def _arrays_broken(field: str, dtype: str, shape: tuple[Any, ...]) -> list[Any]:
    ndim = len(shape)
    good_shape = [2 if s is None else s for s in shape] or [1]
    count = math.prod(good_shape)
    data = bytes(8 * count)
    broken: list[Any] = [
        {"dtype": [dtype], "shape": good_shape, "data": data},  # dtype as a list
        {"dtype": "<c16", "shape": good_shape, "data": bytes(16 * count)},
        {"dtype": "float128", "shape": good_shape, "data": data},
        {"dtype": 5, "shape": good_shape, "data": data},
        {"dtype": dtype, "shape": [1] * 70, "data": bytes(8)},  # 70 dimensions
        {"dtype": dtype, "shape": [2 ** 40] * max(ndim, 1), "data": data},  # huge product
        {"dtype": dtype, "shape": "3", "data": data},
        {"dtype": dtype, "shape": [-1] * max(ndim, 1), "data": data},
        {"dtype": dtype, "shape": good_shape, "data": "not bytes"},
        {"dtype": dtype, "shape": good_shape, "data": data[:-1] + b""},  # one byte short
        {"dtype": dtype, "shape": good_shape},  # no data
        _nested(40),  # deeper than any field
        [[1.0, 2.0], [3.0]],  # ragged
        ["a", "b"],
        "an array?",
        {"dtype": dtype, "shape": good_shape, "data": data[:-8]} if count > 1 else 7,
    ]
    if dtype == "<f8":
        nan = np.full(good_shape, np.nan).tobytes()
        inf = np.full(good_shape, np.inf).tobytes()
        broken += [{"dtype": dtype, "shape": good_shape, "data": nan},
                   {"dtype": dtype, "shape": good_shape, "data": inf}]
    else:
        broken += [[1.5] * good_shape[0], [2.0 ** 70] * good_shape[0]]
    return broken


def _nested(depth: int) -> Any:
    out: Any = 1.0
    for _ in range(depth):
        out = [out]
    return out


_WRONG: dict[str, list[Any]] = {
    "float": ["x", [1.0], {"a": 1}, True, math.nan, math.inf, -math.inf],
    "int": [1.5, "3", True, [1]],
    "str": [5, b"bytes", [], {"a": "b"}, 1.0],
    "bool": [1, "true", None, []],
    "bytes": ["str", 5, [1, 2]],
    "records": ["x", [1, 2], [{"kind": "nope", "ids": [], "step": 1, "growth": 1.0}],
                   [{"kind": "pair", "ids": "12", "step": 1, "growth": 1.0}]],
    "stats": ["x", [1.0], {"a": "b"}, {"a": math.nan}],
}


def field_breakers(kind: type[Message]) -> list[tuple[str, Any]]:
    """(field, broken value) pairs that make a valid ``kind`` message invalid."""
    out: list[tuple[str, Any]] = []
    for f in dataclasses.fields(kind):  # type: ignore[arg-type]
        meta = f.metadata
        k = meta.get("kind")
        required = f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
        if k == "array":
            if not required and f.name not in ("observed_ids", "new_ids"):
                continue  # optional arrays: a mismatch with its partner is not guaranteed
            out += [(f.name, v) for v in _arrays_broken(f.name, meta["dtype"], meta["shape"])]
        elif k in _WRONG:
            values = list(_WRONG[k])
            if k == "int":  # just outside the field's range, and still packable
                low, high = meta.get("range", (-(2 ** 63), 2 ** 63 - 1))
                values.append(high + 1 if high + 1 < 2 ** 64 else low - 1)
            if k == "str" and meta.get("choices"):
                values.append("not-a-choice")
            if k == "str" and not required:
                values = [v for v in values if v is not None]
            out += [(f.name, v) for v in values]
        if required and k != "array":
            out.append((f.name, None))  # missing
    return out


def bad_payloads(kind: type[Message], rng: np.random.Generator, count: int,
                 **valid_args: Any) -> Iterator[bytes]:
    """``count`` invalid payloads for ``kind`` (module docstring), varied by ``rng``."""
    template = valid(kind, **valid_args).to_dict()
    good = msgpack.packb(template, use_bin_type=True)
    breakers = field_breakers(kind)
    for i in range(count):
        choice = i % 6
        if choice == 0:
            yield bytes(rng.integers(0, 256, size=int(rng.integers(0, 200)), dtype=np.uint8))
        elif choice == 1:
            yield good[:int(rng.integers(0, len(good)))]  # truncated
        elif choice == 2:
            root = [template, 5, "x", None, [], 3.5][int(rng.integers(0, 6))]
            if isinstance(root, dict):
                root = dict(root, schema=int(rng.choice([0, 2, 99])))
            yield msgpack.packb(root, use_bin_type=True)
        else:
            name, value = breakers[int(rng.integers(0, len(breakers)))]
            broken = dict(template)
            if value is None:
                broken.pop(name, None)
            else:
                broken[name] = value
            yield msgpack.packb(broken, use_bin_type=True)
