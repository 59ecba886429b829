"""Glyphs: closed-form eigen vs numpy, axis rules, and exact ellipsoid projections."""

from __future__ import annotations

import numpy as np
import pytest

from slamlens.common.errors import ConfigError
from slamlens.common.geometry import make_T, rot_z
from slamlens.services.visualiser.camera_model import CameraModel
from slamlens.services.visualiser.glyphs import (
    Ellipsoids,
    eig_sym2,
    ellipse_polygons,
    ellipsoids_from_pd,
    project_ellipsoids,
    semi_axes,
)

F = 900.0
K = np.array([[F, 0.0, 640.0], [0.0, F, 360.0], [0.0, 0.0, 1.0]])


def random_psd(rng: np.random.Generator, count: int) -> np.ndarray:
    A = rng.normal(size=(count, 2, 2)) * rng.uniform(1e-3, 1.0, (count, 1, 1))
    M = A @ A.transpose(0, 2, 1)
    # some awkward ones: isotropic, diagonal, rank one, nearly singular
    M[0] = np.eye(2) * 0.01
    M[1] = np.diag([0.04, 0.0009])
    M[2] = np.outer([0.3, 0.4], [0.3, 0.4])
    M[3] = np.array([[1.0, 0.999999], [0.999999, 1.0]])
    return M


def down_camera(height_m: float) -> CameraModel:
    R = np.diag([1.0, -1.0, -1.0])
    centre = np.array([0.0, 0.0, height_m])
    return CameraModel(K=K, dist=np.zeros(0), width=1280, height=720,
                       T_camera_from_map=make_T(R, -R @ centre))


def oblique_camera(dist: tuple[float, ...] = ()) -> CameraModel:
    tilt = -0.7
    Rx = np.array([[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)], [0, np.sin(tilt), np.cos(tilt)]])
    R = Rx @ np.diag([1.0, -1.0, -1.0]) @ rot_z(0.4).T
    eye = np.array([0.6, -2.2, 2.0])
    return CameraModel(K=K, dist=np.array(dist), width=1280, height=720,
                       T_camera_from_map=make_T(R, -R @ eye))


def test_closed_form_eigen_matches_numpy_eigh() -> None:
    rng = np.random.default_rng(7)
    M = random_psd(rng, 2000)
    lam1, lam2, angle = eig_sym2(M)
    expected = np.linalg.eigh(M)[0]  # ascending
    scale = expected[:, 1]
    np.testing.assert_allclose(lam1, expected[:, 1], rtol=1e-12, atol=0)
    assert np.all(np.abs(lam2 - expected[:, 0]) <= 1e-12 * scale)
    # the angle is the major eigenvector's direction: M·v = λ1·v
    v = np.stack([np.cos(angle), np.sin(angle)], axis=-1)
    residual = np.einsum("kij,kj->ki", M, v) - lam1[:, None] * v
    assert np.all(np.linalg.norm(residual, axis=1) <= 1e-12 * scale)
    assert np.all((angle > -np.pi / 2 - 1e-15) & (angle <= np.pi / 2 + 1e-15))


def test_eigen_of_a_rotated_diagonal_recovers_its_axes() -> None:
    R = rot_z(0.6)[:2, :2]
    M = R @ np.diag([0.09, 0.01]) @ R.T
    lam1, lam2, angle = eig_sym2(M[None])
    assert lam1[0] == pytest.approx(0.09) and lam2[0] == pytest.approx(0.01)
    assert angle[0] == pytest.approx(0.6)


def test_semi_axes_per_glyph_mode() -> None:
    lam1, lam2 = np.array([0.04, 0.01]), np.array([0.01, -1e-18])
    a, b = semi_axes(lam1, lam2, glyph="sigma", sigma_k=2.0, scale=1.5)
    np.testing.assert_allclose(a, 1.5 * 2.0 * np.sqrt(lam1))
    np.testing.assert_allclose(b, [1.5 * 2.0 * 0.1, 0.0])  # a rounding-negative λ → 0
    a, b = semi_axes(lam1, lam2, glyph="linear", sigma_k=2.0, scale=3.0)
    np.testing.assert_allclose(a, 3.0 * lam1)  # the paper: axis length = eigenvalue
    np.testing.assert_allclose(b, [0.03, 0.0])
    with pytest.raises(ConfigError, match="unknown glyph mode"):
        semi_axes(lam1, lam2, glyph="area", sigma_k=2.0, scale=1.0)


def test_ellipsoid_takes_the_minor_axis_as_height_and_sits_at_the_midpoint() -> None:
    Pd = np.array([rot_z(0.3)[:2, :2] @ np.diag([0.0025, 0.0004]) @ rot_z(0.3)[:2, :2].T])
    ell = ellipsoids_from_pd(Pd, np.array([[1.0, 2.0]]), glyph="sigma", sigma_k=2.0, scale=1.0)
    assert ell.a[0] == pytest.approx(0.1) and ell.b[0] == pytest.approx(0.04)
    assert ell.h[0] == ell.b[0]
    assert ell.yaw[0] == pytest.approx(0.3)
    np.testing.assert_allclose(ell.centres[0], [1.0, 2.0, 0.0])


def test_flat_glyph_seen_straight_down_projects_to_f_a_over_z() -> None:
    Z = 3.0
    cam = down_camera(Z)
    ell = Ellipsoids(centres=np.zeros((1, 3)), a=np.array([0.2]), b=np.array([0.08]),
                     h=np.array([0.0]), yaw=np.array([0.0]))
    ie = project_ellipsoids(ell, cam)
    assert ie.valid[0]
    np.testing.assert_allclose(ie.axes[0], [F * 0.2 / Z, F * 0.08 / Z], rtol=1e-12)
    np.testing.assert_allclose(ie.centre[0], [640.0, 360.0], atol=1e-9)
    # map +x is image right; a yaw of 90° turns the major axis to image vertical
    assert abs(np.sin(ie.angle[0])) < 1e-12
    ell90 = Ellipsoids(centres=np.zeros((1, 3)), a=np.array([0.2]), b=np.array([0.08]),
                       h=np.array([0.0]), yaw=np.array([np.pi / 2]))
    assert abs(np.cos(project_ellipsoids(ell90, cam).angle[0])) < 1e-12


def test_solid_glyph_seen_straight_down_matches_the_exact_silhouette() -> None:
    # the silhouette of an on-axis ellipsoid with height h at distance Z: f·a / sqrt(Z² − h²)
    Z, a, b = 3.0, 0.3, 0.12
    ell = ellipsoids_from_pd(np.array([np.diag([(a / 2) ** 2, (b / 2) ** 2])]),
                             np.zeros((1, 2)), glyph="sigma", sigma_k=2.0, scale=1.0)
    ie = project_ellipsoids(ell, down_camera(Z))
    np.testing.assert_allclose(ie.axes[0], [F * a / np.sqrt(Z**2 - b**2),
                                            F * b / np.sqrt(Z**2 - b**2)], rtol=1e-12)


def test_a_flat_glyph_from_a_rank_one_pd_is_still_drawn_as_a_line() -> None:
    Z = 3.0
    Pd = np.array([np.outer([0.6, 0.8], [0.6, 0.8]) * 0.01])  # λ = 0.01 and 0
    ell = ellipsoids_from_pd(Pd, np.zeros((1, 2)), glyph="sigma", sigma_k=2.0, scale=1.0)
    assert ell.b[0] < 1e-6 and ell.h[0] < 1e-6  # zero up to rounding
    ie = project_ellipsoids(ell, down_camera(Z))
    assert ie.valid[0]
    assert ie.axes[0, 0] == pytest.approx(F * 0.2 / Z) and ie.axes[0, 1] == 0.5
    zero = ellipsoids_from_pd(np.zeros((1, 2, 2)), np.zeros((1, 2)), glyph="sigma",
                              sigma_k=2.0, scale=1.0)
    assert not project_ellipsoids(zero, down_camera(Z)).valid[0]  # nothing to draw


def surface_points(ell: Ellipsoids, k: int, count: int, rng: np.random.Generator) -> np.ndarray:
    u = rng.normal(size=(count, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    return (u * [ell.a[k], ell.b[k], ell.h[k]]) @ rot_z(ell.yaw[k]).T + ell.centres[k]


def normalised_radius(ie, k: int, uv: np.ndarray) -> np.ndarray:
    d = uv - ie.centre[k]
    c, s = np.cos(ie.angle[k]), np.sin(ie.angle[k])
    x, y = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
    return np.hypot(x / ie.axes[k, 0], y / ie.axes[k, 1])


def test_projected_outline_is_the_silhouette_of_the_ellipsoid_oblique_view() -> None:
    rng = np.random.default_rng(3)
    g = 12
    ell = Ellipsoids(centres=np.column_stack([rng.uniform(-0.8, 1.2, (g, 2)),
                                              rng.uniform(-0.2, 0.3, g)]),
                     a=rng.uniform(0.05, 0.4, g), b=rng.uniform(0.02, 0.05, g),
                     h=rng.uniform(0.02, 0.2, g), yaw=rng.uniform(-np.pi, np.pi, g))
    cam = oblique_camera()
    ie = project_ellipsoids(ell, cam)
    assert ie.valid.all()
    for k in range(g):
        uv, _ = cam.project(surface_points(ell, k, 20000, rng))
        r = normalised_radius(ie, k, uv)
        assert r.max() <= 1 + 1e-9  # every surface point projects inside the outline …
        assert r.max() >= 1 - 1e-3  # … and the outline is touched (it is the silhouette)


def test_distorted_outline_is_close_to_the_distorted_silhouette() -> None:
    rng = np.random.default_rng(4)
    g = 8
    ell = Ellipsoids(centres=np.column_stack([rng.uniform(-0.8, 1.2, (g, 2)), np.zeros(g)]),
                     a=rng.uniform(0.05, 0.12, g), b=rng.uniform(0.02, 0.05, g),
                     h=rng.uniform(0.02, 0.05, g), yaw=rng.uniform(-np.pi, np.pi, g))
    cam = oblique_camera(dist=(-0.25, 0.08, 0.001, -0.001, -0.01))
    ie = project_ellipsoids(ell, cam)
    for k in range(g):
        uv, _ = cam.project(surface_points(ell, k, 20000, rng))  # exact, through the lens
        r = normalised_radius(ie, k, uv)
        assert 0.97 < r.max() < 1.03  # first-order: within 3 % of the glyph's size


def test_glyph_centre_projects_at_the_pair_midpoint_from_overhead() -> None:
    cam = CameraModel.top_down(bounds_xy=(-1.0, -1.0, 2.0, 2.0))
    rng = np.random.default_rng(5)
    first, second = rng.uniform(-1, 2, (30, 2)), rng.uniform(-1, 2, (30, 2))
    mid = 0.5 * (first + second)
    Pd = random_psd(rng, 30) * 0.01
    ell = ellipsoids_from_pd(Pd, mid, glyph="sigma", sigma_k=2.0, scale=1.0)
    ie = project_ellipsoids(ell, cam)
    uv, _ = cam.project(np.column_stack([mid, np.zeros(30)]))
    # the silhouette's centre is the projected 3D centre up to a tiny perspective shift
    assert np.all(np.linalg.norm(ie.centre - uv, axis=1) < 0.5)


def test_glyphs_behind_or_around_the_camera_are_invalid() -> None:
    cam = down_camera(1.0)
    ell = Ellipsoids(centres=np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 0.5], [0.0, 0.0, 0.9]]),
                     a=np.array([0.1, 0.1, 0.1]), b=np.array([0.1, 0.1, 0.1]),
                     h=np.array([0.1, 0.1, 0.3]), yaw=np.zeros(3))
    ie = project_ellipsoids(ell, cam)
    # above the camera (behind it), in front, straddling the camera's plane
    assert ie.valid.tolist() == [False, True, False]


def test_ellipse_polygons_lie_on_the_ellipse() -> None:
    centre = np.array([[100.0, 50.0], [10.0, 20.0]])
    axes = np.array([[30.0, 10.0], [5.0, 4.0]])
    angle = np.array([0.4, -1.2])
    polys = ellipse_polygons(centre, axes, angle, vertices=24)
    assert polys.shape == (2, 24, 2)
    for k in range(2):
        d = polys[k] - centre[k]
        c, s = np.cos(angle[k]), np.sin(angle[k])
        x, y = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
        np.testing.assert_allclose((x / axes[k, 0]) ** 2 + (y / axes[k, 1]) ** 2, 1.0)
