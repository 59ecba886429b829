"""Correlation glyphs: P_d → 3D ellipsoid → image ellipse, vectorised over all glyphs.

Paper §3.2: the tensor P_d (2x2) is eigen-decomposed; the glyph's axes lie along the
eigenvectors with lengths from the eigenvalues, and the 2D glyph is extended into 3D with
the minor axis as its height. Here the ellipsoid is centred on the floor (z = 0) at the
pair's midpoint, so its floor cross-section is exactly the paper's 2D glyph and the pair's
line passes through its centre.

The image of an ellipsoid under a pinhole camera is a conic, computed exactly from the
dual quadric: Q* = H·diag(a², b², h², −1)·Hᵀ, C* = P·Q*·Pᵀ. Lens distortion is applied to
the resulting ellipse to first order (its centre is distorted exactly, its shape matrix
by the distortion map's Jacobian at that centre): exact for the centre, accurate while a
glyph is small compared with the scale over which the distortion changes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slamlens.common.geometry import eig_sym2, semi_axes
from slamlens.services.visualiser.camera_model import NEAR_M, CameraModel

MIN_MINOR_PX = 0.5  #: thinnest drawn glyph, pixels


@dataclass(frozen=True)
class Ellipsoids:
    """A set of upright ellipsoids in the map frame (one row per glyph)."""

    centres: np.ndarray  #: (g, 3) map frame, m
    a: np.ndarray  #: (g,) major horizontal semi-axis, m
    b: np.ndarray  #: (g,) minor horizontal semi-axis, m
    h: np.ndarray  #: (g,) vertical semi-axis, m (= b: the minor axis as height)
    yaw: np.ndarray  #: (g,) direction of the major axis in the map frame, rad

    def __len__(self) -> int:
        return int(self.centres.shape[0])


def ellipsoids_from_pd(Pd: np.ndarray, centres: np.ndarray, *, glyph: str, sigma_k: float,
                       scale: float) -> Ellipsoids:
    """The paper's correlation ellipsoids for relative covariances ``Pd`` (g, 2, 2).

    ``centres`` is (g, 2) (placed on the floor, z = 0) or (g, 3).
    """
    Pd = np.asarray(Pd, dtype=float).reshape(-1, 2, 2)
    centres = np.asarray(centres, dtype=float)
    if centres.ndim == 2 and centres.shape[1] == 2:
        centres = np.column_stack([centres, np.zeros(len(centres))])
    lam1, lam2, yaw = eig_sym2(Pd)
    a, b = semi_axes(lam1, lam2, glyph=glyph, sigma_k=sigma_k, scale=scale)
    return Ellipsoids(centres=centres.reshape(-1, 3), a=a, b=b, h=b.copy(), yaw=yaw)


@dataclass(frozen=True)
class ImageEllipses:
    """Projected outlines of ellipsoids (one row per input ellipsoid)."""

    centre: np.ndarray  #: (g, 2) pixels (centre of the image ellipse, not of the 3D centre)
    axes: np.ndarray  #: (g, 2) semi-axes (major, minor), pixels
    angle: np.ndarray  #: (g,) image angle of the major axis, rad (from +u towards +v)
    depth: np.ndarray  #: (g,) camera depth of the 3D centre, m (for painter's ordering)
    valid: np.ndarray  #: (g,) bool: entirely in front of the camera and non-degenerate


def project_ellipsoids(ell: Ellipsoids, camera: CameraModel) -> ImageEllipses:
    """Exact image conics of ``ell`` through the pinhole, then the distortion to first order."""
    g = len(ell)
    P = camera.P
    P3 = P[:, :3]
    cos, sin = np.cos(ell.yaw), np.sin(ell.yaw)
    # Columns of P·H with H = [[R·diag(a, b, h), c], [0, 1]] and R = rot_z(yaw).
    m1 = ell.a[:, None] * (cos[:, None] * P3[:, 0] + sin[:, None] * P3[:, 1])
    m2 = ell.b[:, None] * (-sin[:, None] * P3[:, 0] + cos[:, None] * P3[:, 1])
    m3 = ell.h[:, None] * P3[:, 2]
    m4 = ell.centres @ P3.T + P[:, 3]
    # Dual conic C* = m1m1ᵀ + m2m2ᵀ + m3m3ᵀ − m4m4ᵀ (the dual quadric's diag(.., −1)).
    C = (np.einsum("gi,gj->gij", m1, m1) + np.einsum("gi,gj->gij", m2, m2)
         + np.einsum("gi,gj->gij", m3, m3) - np.einsum("gi,gj->gij", m4, m4))
    s = -C[:, 2, 2]  # = depth² − (depth extent)²: > 0 iff the glyph is wholly in front
    depth = m4[:, 2]
    valid = (s > 0) & (depth > NEAR_M)
    s_safe = np.where(valid, s, 1.0)
    centre = -C[:, :2, 2] / s_safe[:, None]
    A = C[:, :2, :2] / s_safe[:, None, None] + np.einsum("gi,gj->gij", centre, centre)
    if camera.has_distortion and g:
        centre, A = _distort_ellipses(camera, centre, A)
    lam1, lam2, angle = eig_sym2(A)
    valid &= (lam1 > 0) & np.isfinite(lam1) & np.isfinite(centre).all(axis=1)
    axes = np.sqrt(np.maximum(np.column_stack([lam1, lam2]), 0.0))
    # A flat glyph (rank-one P_d, e.g. from a broken estimator) still shows, as a thin line.
    axes[:, 1] = np.maximum(axes[:, 1], MIN_MINOR_PX)
    return ImageEllipses(centre=centre, axes=axes, angle=angle, depth=depth, valid=valid)


def _distort_ellipses(camera: CameraModel, centre: np.ndarray,
                      A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distorted centre, and A ← J·A·Jᵀ with J the distortion map's Jacobian (pixels)."""
    step = 0.5  # px: central differences, far below any glyph size that matters
    g = len(centre)
    probes = np.concatenate([centre, centre + [step, 0], centre - [step, 0],
                             centre + [0, step], centre - [0, step]])
    d = camera.distort_pixels(probes).reshape(5, g, 2)
    J = np.stack([(d[1] - d[2]) / (2 * step), (d[3] - d[4]) / (2 * step)], axis=-1)
    return d[0], J @ A @ J.transpose(0, 2, 1)


def unit_circle(vertices: int) -> np.ndarray:
    """(V, 2) points on the unit circle, counter-clockwise from +x."""
    t = np.linspace(0.0, 2 * np.pi, vertices, endpoint=False)
    return np.column_stack([np.cos(t), np.sin(t)])


def ellipse_polygons(centre: np.ndarray, axes: np.ndarray, angle: np.ndarray, *,
                     vertices: int) -> np.ndarray:
    """(g, V, 2) polygon vertices of image ellipses (float pixels)."""
    circle = unit_circle(vertices)
    x = axes[:, 0:1] * circle[:, 0]
    y = axes[:, 1:2] * circle[:, 1]
    cos, sin = np.cos(angle)[:, None], np.sin(angle)[:, None]
    return np.stack([centre[:, 0:1] + cos * x - sin * y,
                     centre[:, 1:2] + sin * x + cos * y], axis=-1)
