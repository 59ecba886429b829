"""The RViz MarkerArray of a state: read back by rosbags, held to scene3d's geometry.

Every array is read by ``rosbags`` and written again by ``rosbags``' own serialiser (the
same bytes); the ellipsoids' centres, sizes and turns are scene3d's glyphs (the picture
every 3D exporter shares), ids are stable from state to state, what disappears is deleted
and a new map starts with DELETEALL.
"""

from __future__ import annotations

import numpy as np
import pytest

from slamlens.common.messages import Health, SlamState, Violation
from slamlens.common.scene3d import FEATURE, VIOLATION, SceneSettings, pair_glyphs
from slamlens.services.ros2.markers import DELETE, DELETEALL, SPHERE, MarkerExport
from slamlens.services.ros2.rostypes import typestore

MA = "visualization_msgs/msg/MarkerArray"


def _state(xy: np.ndarray, *, seq: int = 5, epoch: int = 7, ids: np.ndarray | None = None,
           seed: int = 0) -> SlamState:
    n = len(xy)
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(3 + 2 * n, 3 + 2 * n))
    P = A @ A.T * 1e-3 + np.eye(3 + 2 * n) * 1e-3
    return SlamState(robot="robot1", seq=seq, stamp=100.0 + seq, step="update",
                     pose=np.array([0.5, -0.25, 1.0]),
                     landmark_ids=np.arange(10, 10 + n) if ids is None else ids,
                     landmarks=np.asarray(xy, float), covariance=P, epoch=epoch)


def _read(payload: bytes) -> list:
    store = typestore("jazzy")
    msg = store.deserialize_cdr(payload, MA)
    again = bytes(store.serialize_cdr(msg, MA))
    assert payload[:len(again)] == again and len(payload) - len(again) < 4
    return list(msg.markers)


def _by(markers: list, ns: str) -> list:
    return [m for m in markers if m.ns == ns]


@pytest.mark.parametrize("mode", ["all", "inter", "minmeanmax"])
def test_ellipsoids_are_scene3ds_glyphs(mode: str) -> None:
    rng = np.random.default_rng(3)
    xy = np.concatenate([rng.normal(0, 0.1, (4, 2)), rng.normal(2, 0.1, (5, 2))])
    state = _state(xy)
    settings = SceneSettings(mode=mode, cluster_threshold_m=0.8)
    markers = _read(MarkerExport(settings).update(state))
    glyphs = pair_glyphs(state, settings)
    ells = _by(markers, "ellipsoids")
    assert len(ells) == len(glyphs.centres) > 0
    assert len({m.id for m in ells}) == len(ells)
    for m, c, ax, yaw in zip(ells, glyphs.centres, glyphs.axes, glyphs.yaw, strict=True):
        assert m.type == SPHERE and m.action == 0 and m.header.frame_id == "map"
        p, q = m.pose.position, m.pose.orientation
        assert (p.x, p.y, p.z) == tuple(c)
        assert (m.scale.x, m.scale.y, m.scale.z) == tuple(2 * ax)
        assert (q.x, q.y) == (0, 0) and np.isclose(2 * np.arctan2(q.z, q.w), yaw)
    (lines,) = _by(markers, "pairs")
    pts = np.array([[p.x, p.y] for p in lines.points])
    assert np.array_equal(pts, glyphs.lines_xy.reshape(-1, 2))
    labels = _by(markers, "labels")
    assert sorted(m.text for m in labels) == sorted(str(i) for i in range(10, 19))
    assert (lines.header.stamp.sec, lines.header.stamp.nanosec) == (105, 0)


def test_ids_stay_and_what_disappears_is_deleted() -> None:
    xy = np.array([[0.0, 0.0], [0.1, 0.0], [3.0, 0.0], [3.1, 0.0]])
    export = MarkerExport(SceneSettings(mode="inter", cluster_threshold_m=0.5))
    first = _by(_read(export.update(_state(xy, seq=1))), "ellipsoids")
    pairs = pair_glyphs(_state(xy), SceneSettings(mode="inter", cluster_threshold_m=0.5)).pairs
    ids_first = {tuple(p): m.id for p, m in zip(pairs.tolist(), first, strict=True)}
    # a fifth feature near the first cluster: the old pairs keep their ids, new ones come
    xy5 = np.vstack([xy, [[0.2, 0.0]]])
    second = _read(export.update(_state(xy5, seq=2)))
    pairs5 = pair_glyphs(_state(xy5), SceneSettings(mode="inter", cluster_threshold_m=0.5)).pairs
    ells = [m for m in _by(second, "ellipsoids") if m.action == 0]
    ids_second = {tuple(p): m.id for p, m in zip(pairs5.tolist(), ells, strict=True)}
    for pair, marker_id in ids_first.items():
        assert ids_second[pair] == marker_id
    assert not [m for m in second if m.action == DELETE]
    # the clusters merge (one cluster: no inter pairs): every ellipsoid is deleted by id
    third = _read(export.update(_state(xy5 * [0.1, 1.0], seq=3)))
    deleted = sorted(m.id for m in third if m.action == DELETE and m.ns == "ellipsoids")
    assert deleted == sorted(ids_second.values())
    assert not [m for m in _by(third, "ellipsoids") if m.action == 0]
    assert [m.action for m in _by(third, "pairs")] == [DELETE]


def test_a_new_map_starts_with_deleteall_and_labels_of_forgotten_features_go() -> None:
    xy = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    export = MarkerExport(SceneSettings())
    export.update(_state(xy, seq=4))
    fewer = _read(export.update(_state(xy[:2], seq=5, ids=np.array([10, 11]))))
    assert [m.id for m in fewer if m.action == DELETE and m.ns == "labels"] == [2]
    restart = _read(export.update(_state(xy, seq=1, epoch=8)))
    assert restart[0].action == DELETEALL
    back = _read(export.update(_state(xy, seq=0, epoch=8)))  # seq going back: a new map too
    assert back[0].action == DELETEALL


def test_suspects_and_flagged_pairs_are_magenta() -> None:
    xy = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    health = Health(robot="robot1", seq=5, stamp=105.0, ok=False, suspects=np.array([11]),
                    violations=(Violation(kind="pair", ids=(11, 12), step=5, value=3.0),),
                    verdict="fault")
    markers = _read(MarkerExport(SceneSettings()).update(_state(xy), health=health))
    (features,) = _by(markers, "features")
    per_cone = len(features.colors) // 3
    colours = np.array([[c.r, c.g, c.b] for c in features.colors[::per_cone]])
    assert np.allclose(colours, np.array([FEATURE, VIOLATION, FEATURE]), atol=1e-6)
    flagged = [m for m in _by(markers, "ellipsoids")
               if np.allclose((m.color.r, m.color.g, m.color.b), VIOLATION, atol=1e-6)]
    assert len(flagged) == 1
    pts = [(p.x, p.y) for p in features.points]
    assert min(pts) >= (-0.1, -0.1)  # the cones stand on the features
