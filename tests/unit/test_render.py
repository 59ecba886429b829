"""The renderer's pictures: glyphs where the pairs are, per mode, in depth order, with health."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from slamlens.common.geometry import invert_T, make_T
from slamlens.common.messages import Health, SlamState, Violation
from slamlens.services.registration.synthetic import SyntheticCamera, overhead_pose
from slamlens.services.visualiser.camera_model import CameraModel
from slamlens.services.visualiser.render import Renderer, pick_feature, side_by_side
from slamlens.services.visualiser.settings import ViewSettings

# the paper world's 15 features (ids 1-5, 6-10, 11-15: three clusters)
PAPER_XY = np.array([
    [1.35, -0.45], [1.60, -0.35], [1.85, -0.50], [1.50, -0.70], [1.75, -0.80],
    [1.45, 1.60], [1.70, 1.45], [1.85, 1.75], [1.55, 1.85], [1.25, 1.85],
    [-0.45, 1.20], [-0.70, 1.05], [-0.85, 1.35], [-0.60, 1.55], [-0.35, 1.50]])
IDS = np.arange(1, 16)
CLUSTER = (IDS - 1) // 5
BOUNDS = (-1.0, -1.0, 2.0, 2.0)
QUIET = {"features": False, "robot": False, "legend": False, "path": False}


def paper_state(*, seq: int = 10, pose=(0.5, 0.2, 0.8), seed: int = 0,
                sigma_m: float = 0.03) -> SlamState:
    """EKF-like P: a common (robot-induced) part plus an anisotropic block per feature.

    P_d = D_i + D_j, small against the inter-feature distances; semi-axes ~2σ ≈ 6-8 cm.
    """
    rng = np.random.default_rng(seed)
    n = len(IDS)
    P = np.zeros((3 + 2 * n, 3 + 2 * n))
    P[:3, :3] = np.diag([0.01, 0.01, 0.002])
    P[3:, 3:] = np.kron(np.ones((n, n)), 0.05 ** 2 * np.eye(2))
    for i in range(n):
        t = rng.uniform(0, np.pi)
        R = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
        D = R @ np.diag([sigma_m ** 2, (0.6 * sigma_m) ** 2]) @ R.T / 2
        P[3 + 2 * i:5 + 2 * i, 3 + 2 * i:5 + 2 * i] += D
    return SlamState(robot="r1", seq=seq, stamp=float(seq), step="update", pose=list(pose),
                     landmark_ids=IDS, landmarks=PAPER_XY, covariance=P)


def top_down() -> CameraModel:
    return CameraModel.top_down(bounds_xy=BOUNDS, width=1280, height=720)


def is_red(px: np.ndarray) -> np.ndarray:
    b, g, r = (px[..., k].astype(int) for k in range(3))
    return (r >= 100) & (r - np.maximum(g, b) >= 60)


def is_magenta(px: np.ndarray) -> np.ndarray:
    b, g, r = (px[..., k].astype(int) for k in range(3))
    return (r >= 180) & (b >= 180) & (g <= 90)


def pixel(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    return img[int(round(uv[1])), int(round(uv[0]))]


def midpoints_px(camera: CameraModel, pairs: list[tuple[int, int]]) -> np.ndarray:
    mid = np.array([(PAPER_XY[a - 1] + PAPER_XY[b - 1]) / 2 for a, b in pairs])
    return camera.project(np.column_stack([mid, np.zeros(len(mid))]))[0]


ALL_PAIRS = [(a, b) for a in range(1, 16) for b in range(a + 1, 16)]
INTRA = [(a, b) for a, b in ALL_PAIRS if CLUSTER[a - 1] == CLUSTER[b - 1]]
INTER = [(a, b) for a, b in ALL_PAIRS if CLUSTER[a - 1] != CLUSTER[b - 1]]


def test_red_ellipsoids_appear_at_every_pair_midpoint_over_the_synthetic_camera() -> None:
    K = np.array([[640.0, 0.0, 640.0], [0.0, 640.0, 360.0], [0.0, 0.0, 1.0]])
    T_world_from_camera = overhead_pose(centre_xy=(0.5, 0.5), height_m=3.0)
    synthetic = SyntheticCamera(K, 1280, 720, T_world_from_camera=T_world_from_camera)
    frame = synthetic.render(robot_pose=(0.5, 0.2, 0.8))
    camera = CameraModel(K=K, dist=np.zeros(5), width=1280, height=720,
                         T_camera_from_map=invert_T(T_world_from_camera))
    before = frame.copy()
    out = Renderer().render(frame, state=paper_state(), camera=camera,
                            settings=ViewSettings(**QUIET))
    np.testing.assert_array_equal(frame, before)  # the input picture is not drawn on
    assert out.shape == frame.shape and out.dtype == np.uint8
    assert not is_red(frame).any()
    uv = midpoints_px(camera, ALL_PAIRS)
    assert all(is_red(pixel(out, p)) for p in uv)
    # far from the map the camera picture shows through untouched
    np.testing.assert_array_equal(out[700:, :200], frame[700:, :200])


def test_inter_mode_hides_intra_cluster_pairs() -> None:
    camera = top_down()
    out = Renderer().render(None, state=paper_state(), camera=camera,
                            settings=ViewSettings(mode="inter", **QUIET))
    assert all(is_red(pixel(out, p)) for p in midpoints_px(camera, INTER))
    assert not any(is_red(pixel(out, p)) for p in midpoints_px(camera, INTRA))
    everything = Renderer().render(None, state=paper_state(), camera=camera,
                                   settings=ViewSettings(**QUIET))
    assert all(is_red(pixel(everything, p)) for p in midpoints_px(camera, INTRA))


def test_minmeanmax_draws_three_glyphs_per_cluster_pair_on_the_centroid_lines() -> None:
    camera = top_down()
    settings = ViewSettings(mode="minmeanmax", **QUIET)
    out = Renderer().render(None, state=paper_state(), camera=camera, settings=settings)
    centroids = np.array([PAPER_XY[CLUSTER == c].mean(axis=0) for c in range(3)])
    for a, b in [(0, 1), (0, 2), (1, 2)]:
        for t in (0.35, 0.5, 0.65):
            p = centroids[a] + t * (centroids[b] - centroids[a])
            uv, _ = camera.project(np.array([[*p, 0.0]]))
            assert is_red(pixel(out, uv[0])), (a, b, t)
    assert not any(is_red(pixel(out, p)) for p in midpoints_px(camera, INTRA))
    inter = Renderer().render(None, state=paper_state(), camera=camera,
                              settings=ViewSettings(mode="inter", **QUIET))
    assert is_red(out).sum() < 0.3 * is_red(inter).sum()  # 9 glyphs instead of 75


def test_selection_shows_only_pairs_containing_the_feature() -> None:
    camera = top_down()
    out = Renderer().render(None, state=paper_state(), camera=camera,
                            settings=ViewSettings(selected_feature=7, **QUIET))
    chosen = [p for p in ALL_PAIRS if 7 in p]
    chosen_px = midpoints_px(camera, chosen)
    assert all(is_red(pixel(out, p)) for p in chosen_px)
    others = midpoints_px(camera, [p for p in ALL_PAIRS if 7 not in p])
    far = [p for p in others if np.min(np.linalg.norm(chosen_px - p, axis=1)) > 40]
    assert len(far) > 40
    assert not any(is_red(pixel(out, p)) for p in far)


def oblique(eye: tuple[float, float, float], target=(0.0, 0.5, 0.0)) -> CameraModel:
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T_world_from_camera = make_T(np.column_stack([x, y, z]), np.asarray(eye, float))
    K = np.array([[900.0, 0.0, 640.0], [0.0, 900.0, 360.0], [0.0, 0.0, 1.0]])
    return CameraModel(K=K, dist=np.zeros(5), width=1280, height=720,
                       T_camera_from_map=invert_T(T_world_from_camera))


def test_depth_order_nearer_objects_cover_farther_ones() -> None:
    # one pair with a big glyph at (0, 0.5) (P_d = 0.04·I: 2σ semi-axes and height 0.4 m)
    # and the robot's cone 0.45 m from its centre on the −y side
    n = 2
    P = np.eye(3 + 2 * n) * 0.01
    P[3:, 3:] = np.kron(np.ones((2, 2)), 0.1 * np.eye(2)) + np.eye(4) * 0.02
    state = SlamState(robot="r", seq=1, stamp=0.0, step="update", pose=[0.0, 0.05, 0.0],
                      landmark_ids=[1, 2], landmarks=[[-0.8, 0.5], [0.8, 0.5]], covariance=P)
    settings = ViewSettings(features=False, lines=False, legend=False, path=False)
    cap = np.array([[0.0, 0.05, 1.4 * settings.cone_height_m]])  # the robot cone's cap centre
    front = oblique((0.0, -2.5, 1.5))
    behind = oblique((0.0, 3.5, 1.2))  # sees the cap through the glyph
    img_front = Renderer().render(None, state=state, camera=front, settings=settings)
    img_behind = Renderer().render(None, state=state, camera=behind, settings=settings)
    b, g, r = (int(v) for v in pixel(img_front, front.project(cap)[0][0]))
    assert g - max(r, b) > 80  # the robot cone is in front of the glyph: green
    assert is_red(pixel(img_behind, behind.project(cap)[0][0]))  # now the glyph covers it
    # and both objects are really there, overlapping in the picture
    centre = np.array([[0.0, 0.5, 0.0]])
    for img, cam in ((img_front, front), (img_behind, behind)):
        assert is_red(pixel(img, cam.project(centre)[0][0] + [60, 0]))


def test_health_outlines_violations_and_rings_suspects() -> None:
    camera = top_down()
    state = paper_state()
    health = Health(robot="r1", seq=10, stamp=10.0, ok=False, suspects=np.array([12]),
                    violations=(Violation(kind="pair", ids=(3, 12), step=10, value=0.01),))
    settings = ViewSettings(legend=False)
    out = Renderer().render(None, state=state, camera=camera, settings=settings, health=health)
    clean = Renderer().render(None, state=state, camera=camera, settings=settings)
    assert not is_magenta(clean).any()
    (mid,) = midpoints_px(camera, [(3, 12)])
    u, v = int(mid[0]), int(mid[1])
    assert is_magenta(out[v - 25:v + 25, u - 25:u + 25]).sum() > 20  # outlined glyph
    tip, _ = camera.project(np.array([[*PAPER_XY[11], 0.0]]))
    u, v = int(tip[0, 0]), int(tip[0, 1])
    assert is_magenta(out[v - 30:v + 30, u - 30:u + 30]).sum() > 40  # ring around 12
    far = camera.project(np.array([[*PAPER_XY[6], 0.0]]))[0][0]  # feature 7: not involved
    u, v = int(far[0]), int(far[1])
    assert not is_magenta(out[v - 10:v + 10, u - 10:u + 10]).any()
    off = Renderer().render(None, state=state, camera=camera, health=health,
                            settings=ViewSettings(legend=False, health=False))
    assert not is_magenta(off).any()


def test_image_of_another_size_is_drawn_with_a_rescaled_camera() -> None:
    camera = top_down()
    small = np.full((360, 640, 3), 90, np.uint8)
    out = Renderer().render(small, state=paper_state(), camera=camera,
                            settings=ViewSettings(**QUIET))
    assert out.shape == (360, 640, 3)
    uv = midpoints_px(camera, INTER) / 2
    assert np.mean([bool(is_red(pixel(out, p))) for p in uv]) > 0.95
    grey = Renderer().render(np.full((720, 1280), 90, np.uint8), state=paper_state(),
                             camera=camera, settings=ViewSettings())
    assert grey.shape == (720, 1280, 3)


def test_path_grows_and_resets_when_seq_goes_back_or_the_robot_changes() -> None:
    renderer = Renderer()
    camera = top_down()
    settings = ViewSettings()
    for k in range(5):
        renderer.render(None, state=paper_state(seq=k, pose=(0.1 * k, 0.0, 0.0)),
                        camera=camera, settings=settings)
    renderer.render(None, state=paper_state(seq=4, pose=(0.4, 0.0, 0.0)), camera=camera,
                    settings=settings.replace(mode="inter"))  # same state again: no new point
    np.testing.assert_allclose(renderer.path_xy[:, 0], [0.0, 0.1, 0.2, 0.3, 0.4])
    renderer.render(None, state=paper_state(seq=0, pose=(1.0, 1.0, 0.0)), camera=camera,
                    settings=settings)
    np.testing.assert_allclose(renderer.path_xy, [[1.0, 1.0]])
    renderer.reset_path()
    assert len(renderer.path_xy) == 0


def test_path_is_drawn_in_the_path_colour() -> None:
    renderer = Renderer()
    camera = top_down()
    settings = ViewSettings(features=False, lines=False, ellipsoids=False, legend=False,
                            robot=False)
    for k in range(30):
        angle = 2 * math.pi * k / 30
        img = renderer.render(None, camera=camera, settings=settings, state=paper_state(
            seq=k, pose=(0.5 + 0.5 * math.cos(angle), 0.5 + 0.5 * math.sin(angle), 0.0)))
    on_path, _ = camera.project(np.array([[1.0, 0.5, 0.0], [0.5, 1.0, 0.0]]))
    for p in on_path:
        b, g, r = (int(v) for v in pixel(img, p))
        assert g > 150 and g - max(r, b) > 80


def test_legend_and_cluster_identities() -> None:
    camera = top_down()
    renderer = Renderer()
    with_legend = renderer.render(None, state=paper_state(), camera=camera,
                                  settings=ViewSettings(mode="inter"))
    without = renderer.render(None, state=paper_state(), camera=camera,
                              settings=ViewSettings(mode="inter", legend=False))
    box = (slice(12, 60), slice(12, 200))
    assert with_legend[box].mean() < without[box].mean() - 20  # the dark legend box
    ids = renderer.cluster_ids(paper_state(), ViewSettings(mode="inter"))
    assert len(set(ids.tolist())) == 3
    np.testing.assert_array_equal(ids, renderer.cluster_ids(paper_state(seed=3),
                                                            ViewSettings(mode="inter")))


@pytest.mark.parametrize("mode", ["all", "inter", "minmeanmax"])
def test_degenerate_states_render(mode: str) -> None:
    camera = top_down()
    empty = SlamState(robot="r", seq=0, stamp=0.0, step="init", pose=[0, 0, 0],
                      landmark_ids=np.zeros(0, np.int64), landmarks=np.zeros((0, 2)),
                      covariance=np.zeros((3, 3)))
    out = Renderer().render(None, state=empty, camera=camera, settings=ViewSettings(mode=mode))
    robot_px, _ = camera.project(np.array([[0.0, 0.0, 0.21]]))
    b, g, r = (int(v) for v in pixel(out, robot_px[0]))
    assert g - max(r, b) > 60  # the robot is drawn
    # a camera that sees nothing of the map (looking up) still returns a picture
    up = CameraModel(K=camera.K, dist=np.zeros(0), width=1280, height=720,
                     T_camera_from_map=make_T(np.eye(3), np.array([0.0, 0.0, -1.0])))
    assert Renderer().render(None, state=paper_state(), camera=up,
                             settings=ViewSettings(mode=mode)).shape == (720, 1280, 3)


def test_pick_feature_and_side_by_side() -> None:
    camera = top_down()
    state = paper_state()
    tip, _ = camera.project(np.array([[*PAPER_XY[8], 0.0]]))
    assert pick_feature(tip[0, 0] + 3, tip[0, 1] - 2, state=state, camera=camera) == 9
    assert pick_feature(5, 5, state=state, camera=camera) is None
    left, right = np.zeros((720, 1280, 3), np.uint8), np.full((360, 640, 3), 7, np.uint8)
    both = side_by_side(left, right)
    assert both.shape == (720, 2560, 3) and both[0, 2000, 0] == 7


def test_reference_pose_is_a_white_ring_joined_to_the_estimate() -> None:
    camera = top_down()
    state = paper_state(pose=(0.5, 0.2, 0.8))
    settings = ViewSettings(ellipsoids=False, lines=False, features=False, legend=False)
    plain = Renderer().render(None, state=state, camera=camera, settings=settings)
    reference = np.array([0.9, 0.2, 0.8])  # 40 cm from the estimate
    img = Renderer().render(None, state=state, camera=camera, settings=settings,
                            reference_pose=reference)
    (u, v), (ue, ve) = (camera.project(np.array([[0.9, 0.2, 0.0], [0.5, 0.2, 0.0]]))[0]
                        .round().astype(int))
    white = (img.min(axis=2) > 180) & (plain.min(axis=2) <= 180)  # anti-aliased: not 255
    ring = white[v - 14:v + 15, u - 14:u + 15]
    assert ring.sum() > 20  # a ring around the reference
    assert not white[v - 3:v + 4, u - 3:u + 4].all()  # hollow, the floor shows inside
    mid_u, mid_v = (u + ue) // 2, (v + ve) // 2
    assert white[mid_v - 2:mid_v + 3, mid_u - 2:mid_u + 3].any()  # the line to the estimate
    hidden = Renderer().render(None, state=state, camera=camera,
                               settings=settings.replace(robot=False), reference_pose=reference)
    assert not ((hidden.min(axis=2) > 180) & (plain.min(axis=2) <= 180)).any()


def test_legend_shows_the_standing_verdict_on_a_state_without_violations() -> None:
    """Health.ok is per state: a predict step may break nothing while a fault stands; the
    legend shows the robot's verdict (Health.verdict, kept up by Health.standing)."""
    camera = top_down()
    state = paper_state()
    settings = ViewSettings(ellipsoids=False, lines=False)
    ok = Health(robot="robot1", seq=state.seq, stamp=state.stamp, ok=True,
                suspects=np.zeros(0, np.int64))
    standing = Violation(kind="feature", ids=(3,), step=8, value=2e-3, first_step=5, count=4)
    fault = Health(robot="robot1", seq=state.seq, stamp=state.stamp, ok=True,
                   suspects=np.array([3]), verdict="fault", verdict_since=5,
                   standing=(standing,))
    tuning = dataclasses.replace(ok, verdict="tuning", verdict_since=2, standing=(
        Violation(kind="nees", ids=(), step=9, value=40.0, first_step=2, count=7),))
    clean = Renderer().render(None, state=state, camera=camera, settings=settings, health=ok)
    flagged = Renderer().render(None, state=state, camera=camera, settings=settings,
                                health=fault)
    tuned = Renderer().render(None, state=state, camera=camera, settings=settings,
                              health=tuning)
    legend = (slice(0, 160), slice(0, 640))
    assert is_magenta(flagged[legend]).sum() > is_magenta(clean[legend]).sum() + 20
    orange = (tuned[legend][..., 2] > 200) & (tuned[legend][..., 1] > 120) & (
        tuned[legend][..., 1] < 200) & (tuned[legend][..., 0] < 60)
    assert orange.sum() > 20 and is_magenta(tuned[legend]).sum() == is_magenta(
        clean[legend]).sum()


def with_gated(state: SlamState, ids: list[int], observations: np.ndarray,
               total: int) -> SlamState:
    """``state`` carrying rejected (gated) observations, as the estimator's gate publishes
    them (SlamState.gated_ids / gated_observations / diagnostics; set directly if this
    SlamState does not declare them yet)."""
    fields = {"gated_ids": np.asarray(ids, np.int64),
              "gated_observations": np.asarray(observations, float),
              "diagnostics": {"gated": float(total)}}
    names = {f.name for f in dataclasses.fields(SlamState)}
    if set(fields) <= names:
        return dataclasses.replace(state, **fields)
    for name, value in fields.items():
        object.__setattr__(state, name, value)
    return state


def test_rejected_observations_are_grey_crosses_where_they_were_seen() -> None:
    camera = top_down()
    state = paper_state(pose=(0.5, 0.2, 0.0))
    quiet = ViewSettings(**QUIET, ellipsoids=False, lines=False)
    # two observations the gate refused: 1 m ahead, and 0.8 m at 90° to the left
    gated = with_gated(paper_state(pose=(0.5, 0.2, 0.0)), [3, 12],
                       np.array([[1.0, 0.0], [0.8, math.pi / 2]]), total=17)
    plain = Renderer().render(None, state=state, camera=camera, settings=quiet)
    crossed = Renderer().render(None, state=gated, camera=camera, settings=quiet)
    uv = camera.project(np.array([[1.5, 0.2, 0.0], [0.5, 1.0, 0.0]]))[0]
    for u, v in uv:
        patch = (slice(int(v) - 6, int(v) + 7), slice(int(u) - 6, int(u) + 7))
        grey = (np.abs(crossed[patch].astype(int) - 170).max(axis=2) <= 25)
        assert grey.sum() >= 8 and not np.array_equal(crossed[patch], plain[patch])
    changed = np.any(crossed != plain, axis=2)
    assert changed.sum() < 400  # two small crosses, nothing else
    # the legend counts them; without the layer nothing is drawn
    legend = (slice(0, 200), slice(0, 700))
    with_legend = Renderer().render(None, state=gated, camera=camera, settings=ViewSettings())
    without = Renderer().render(None, state=state, camera=camera, settings=ViewSettings())
    assert not np.array_equal(with_legend[legend], without[legend])
    off = Renderer().render(None, state=gated, camera=camera,
                            settings=quiet.replace(rejected=False))
    assert np.array_equal(off, plain)
    from slamlens.services.visualiser.legend import rejected_legend
    assert rejected_legend(gated, ViewSettings()) == [[(
        "rejected observations (gate): 2 in this update, 17 in all", (170, 170, 170))]]
    assert rejected_legend(state, ViewSettings()) == []  # a state without the gate


def test_cluster_outlines_are_the_hull_of_every_member_grown_by_the_ring() -> None:
    """Each cluster's outline against an oracle: scipy's convex hull of every member's
    ring (the members ⊕ a 16-gon of 2.5 cone radii), projected and drawn the same way;
    clusters of one, two and five features, and a feature that is not outlined (-1)."""
    import cv2
    from scipy.spatial import ConvexHull

    from slamlens.common.clusters import cluster_colour
    from slamlens.services.visualiser import draw
    from slamlens.services.visualiser.render_steps import Canvas, draw_cluster_outlines

    state = paper_state()
    ids = np.array([4, 4, 4, 4, 4, 9, 9, -1, 2, 2, 2, 2, 2, 7, -1])  # 5, 2, 5, 1, unoutlined
    camera, settings = top_down(), ViewSettings()
    scene = Renderer().scene(state, settings, frozenset())
    img = np.zeros((camera.height, camera.width, 3), np.uint8)
    draw_cluster_outlines(Canvas(img, camera, state, scene, settings, px=1), ids)

    pad = 2.5 * settings.cone_radius_m
    t = 2 * np.pi * np.arange(16) / 16
    ring = pad * np.column_stack([np.cos(t), np.sin(t)])
    want = np.zeros_like(img)
    for cid in (2, 4, 7, 9):
        pts = (state.landmarks[ids == cid][:, None, :] + ring[None]).reshape(-1, 2)
        hull = pts[ConvexHull(pts).vertices]
        uv, _ = camera.project(np.column_stack([hull, np.zeros(len(hull))]))
        closed = np.concatenate([draw.fixed(uv), draw.fixed(uv)[:1]])
        cv2.polylines(want, [closed], False, cluster_colour(cid), 1, cv2.LINE_AA, draw.SHIFT)
    mine, theirs = img.any(axis=2), want.any(axis=2)
    assert theirs.sum() > 400
    overlap = (mine & theirs).sum() / (mine | theirs).sum()
    assert overlap > 0.9, f"the outlines overlap the oracle's by {overlap:.2f}"
    # in its colour: where both drew, the colours agree (anti-aliasing aside)
    both = mine & theirs
    differ = np.abs(img[both].astype(int) - want[both].astype(int)).max(axis=1)
    assert np.mean(differ <= 24) > 0.95
    for k in (7, 14):  # not outlined: its ring, where no other outline is, stays dark
        uv, _ = camera.project(np.column_stack([state.landmarks[k] + ring, np.zeros(16)]))
        its = np.zeros(img.shape[:2], np.uint8)
        cv2.polylines(its, [np.concatenate([draw.fixed(uv), draw.fixed(uv)[:1]])], False,
                      255, 1, cv2.LINE_AA, draw.SHIFT)
        alone = (its > 0) & ~theirs
        assert alone.sum() > 20 and not mine[alone].any()
