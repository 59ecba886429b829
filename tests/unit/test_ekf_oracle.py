"""The in-place EKF kernels against a dense textbook EKF written here from docs/estimator.md.

The oracle builds the full N×N F, the full 2×N H and the full augmentation Jacobian and
multiplies dense matrices; it shares no code with services/slam/ekf.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from slamlens.services.slam import ekf, ekf_storage

SIG_V, SIG_W, SIG_R, SIG_B = 0.05, 0.05, 0.05, 0.02
RTOL = 1e-10


def wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


# ----------------------------------------------------------------------------- the oracle


def dense_predict(x: np.ndarray, P: np.ndarray, v: float, w: float, dt: float):
    N = x.size
    th = x[2]
    x2 = x.copy()
    x2[0] += v * dt * math.cos(th)
    x2[1] += v * dt * math.sin(th)
    x2[2] = wrap(th + w * dt)
    F = np.eye(N)
    F[0, 2] = -v * dt * math.sin(th)
    F[1, 2] = v * dt * math.cos(th)
    G = np.zeros((N, 2))
    G[0, 0] = dt * math.cos(th)
    G[1, 0] = dt * math.sin(th)
    G[2, 1] = dt
    M = np.diag([SIG_V**2, SIG_W**2])
    return x2, F @ P @ F.T + G @ M @ G.T


def dense_update(x: np.ndarray, P: np.ndarray, j: int, z: np.ndarray):
    N = x.size
    a = 3 + 2 * j
    dx, dy = x[a] - x[0], x[a + 1] - x[1]
    q = dx * dx + dy * dy
    sq = math.sqrt(q)
    h = np.array([sq, math.atan2(dy, dx) - x[2]])
    H = np.zeros((2, N))
    H[:, 0:3] = [[-dx / sq, -dy / sq, 0], [dy / q, -dx / q, -1]]
    H[:, a:a + 2] = [[dx / sq, dy / sq], [-dy / q, dx / q]]
    R = np.diag([SIG_R**2, SIG_B**2])
    nu = z - h
    nu[1] = wrap(nu[1])
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    x2 = x + K @ nu
    x2[2] = wrap(x2[2])
    P2 = P - K @ S @ K.T
    return x2, 0.5 * (P2 + P2.T), nu, S


def dense_initialise(x: np.ndarray, P: np.ndarray, z: np.ndarray):
    N = x.size
    r, phi = z
    al = x[2] + phi
    m = np.array([x[0] + r * math.cos(al), x[1] + r * math.sin(al)])
    # full Jacobian of g(x, z) = [x; m(x, z)] with respect to [x; z]
    Y = np.zeros((N + 2, N + 2))
    Y[:N, :N] = np.eye(N)
    Y[N:, 0:3] = [[1, 0, -r * math.sin(al)], [0, 1, r * math.cos(al)]]
    Y[N:, N:] = [[math.cos(al), -r * math.sin(al)], [math.sin(al), r * math.cos(al)]]
    big = np.zeros((N + 2, N + 2))
    big[:N, :N] = P
    big[N:, N:] = np.diag([SIG_R**2, SIG_B**2])
    return np.concatenate([x, m]), Y @ big @ Y.T


# ----------------------------------------------------------------------------- helpers


def random_state(rng: np.random.Generator, n: int, spread: float = 0.1):
    N = 3 + 2 * n
    x = np.concatenate([rng.uniform(-2, 2, 2), [rng.uniform(-math.pi, math.pi)],
                        rng.uniform(-5, 5, 2 * n)])
    A = rng.normal(scale=spread, size=(N, N))
    P = A @ A.T + 1e-4 * np.eye(N)
    return x, P


def put(x: np.ndarray, P: np.ndarray, extra: int = 4):
    N = x.size
    xb = np.zeros(N + extra)
    xb[:N] = x
    # Poison the unused upper triangle: the kernels must never read it.
    L = np.triu(np.full((N + extra, N + extra), np.nan), 1)
    L[:N, :N] += np.tril(P)
    ws = ekf.Workspace.for_capacity(N + extra)
    return xb, L, ws


def assert_close(actual: np.ndarray, expected: np.ndarray, what: str) -> None:
    scale = max(1.0, float(np.max(np.abs(expected))))
    err = float(np.max(np.abs(actual - expected)))
    assert err <= RTOL * scale, f"{what}: max error {err:.3e} (scale {scale:.2e})"


def full(L: np.ndarray, N: int) -> np.ndarray:
    return ekf.symmetric(L, N)


# ----------------------------------------------------------------------------- tests


@pytest.mark.parametrize("seed", range(20))
def test_predict_equals_dense(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(0, 31))
    x, P = random_state(rng, n)
    v, w, dt = rng.normal(0, 1), rng.normal(0, 1), rng.uniform(0, 0.5)
    xe, Pe = dense_predict(x, P, v, w, dt)
    xb, L, _ = put(x, P)
    ekf.predict(xb, L, n, v=v, w=w, dt=dt, var_v=SIG_V**2, var_w=SIG_W**2)
    N = x.size
    assert_close(xb[:N], xe, "x")
    assert_close(full(L, N), Pe, "P")
    # Pmm must be untouched bit for bit (docs/estimator.md: a prediction touches only robot rows)
    assert np.array_equal(full(L, N)[3:, 3:], P[3:, 3:])


@pytest.mark.parametrize("seed", range(20))
def test_update_equals_dense(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    n = int(rng.integers(1, 31))
    x, P = random_state(rng, n)
    j = int(rng.integers(0, n))
    a = 3 + 2 * j
    h = np.array([math.hypot(x[a] - x[0], x[a + 1] - x[1]),
                  math.atan2(x[a + 1] - x[1], x[a] - x[0]) - x[2]])
    z = h + rng.normal(0, [0.1, 0.05])
    z[1] = wrap(z[1])
    xe, Pe, nue, Se = dense_update(x, P, j, z)
    xb, L, ws = put(x, P)
    out = ekf.update(xb, L, n, j, z_range=z[0], z_bearing=z[1], var_range=SIG_R**2,
                     var_bearing=SIG_B**2, ws=ws)
    N = x.size
    assert_close(xb[:N], xe, "x")
    assert_close(full(L, N), Pe, "P")
    assert_close(np.array(out[:2]), nue, "innovation")
    assert_close(np.array([[out[2], out[3]], [out[3], out[4]]]), Se, "S")


@pytest.mark.parametrize("seed", range(20))
def test_initialise_equals_dense_augmentation(seed: int) -> None:
    rng = np.random.default_rng(200 + seed)
    n = int(rng.integers(0, 31))
    x, P = random_state(rng, n)
    z = np.array([rng.uniform(0.1, 5), rng.uniform(-math.pi, math.pi)])
    xe, Pe = dense_initialise(x, P, z)
    xb, L, ws = put(x, P)
    ekf.initialise(xb, L, n, z_range=z[0], z_bearing=z[1], var_range=SIG_R**2,
                   var_bearing=SIG_B**2, ws=ws)
    N = x.size + 2
    assert_close(xb[:N], xe, "x")
    assert_close(full(L, N), Pe, "P")


@pytest.mark.parametrize("defer", [False, True])
@pytest.mark.parametrize("guarded", [False, True])
@pytest.mark.parametrize("seed", range(5))
def test_batch_of_updates_equals_dense_one_by_one(seed: int, defer: bool,
                                                  guarded: bool) -> None:
    """Sequential relinearisation: each update linearises at the previous posterior.

    With ``defer`` the downdates of P are held back and applied together (by ``flush``, and
    by the kernel itself once ``MAX_DEFERRED`` are held: the batch is longer than that); each
    update still sees the P its predecessors left, as its innovation covariance shows."""
    rng = np.random.default_rng(300 + seed)
    n = 12
    x, P = random_state(rng, n)
    order = rng.integers(0, n, size=ekf.MAX_DEFERRED + 3)  # repeats: a landmark twice
    zs = []
    for j in order:
        a = 3 + 2 * j
        zs.append(np.array([math.hypot(x[a] - x[0], x[a + 1] - x[1]) + rng.normal(0, 0.1),
                            wrap(math.atan2(x[a + 1] - x[1], x[a] - x[0]) - x[2]
                                 + rng.normal(0, 0.05))]))
    xe, Pe = x, P
    expected_s = []
    for j, z in zip(order, zs, strict=True):
        xe, Pe, _, Se = dense_update(xe, Pe, int(j), z)
        expected_s.append(Se)
    # the same with every update linearised at the prior would differ clearly
    xb, L, ws = put(x, P)
    guard = ekf.Guard(psd_rtol=1e-9) if guarded else None
    for j, z, Se in zip(order, zs, expected_s, strict=True):
        out = ekf.update(xb, L, n, int(j), z_range=z[0], z_bearing=z[1], var_range=SIG_R**2,
                         var_bearing=SIG_B**2, ws=ws, guard=guard, defer=defer)
        assert_close(np.array([[out[2], out[3]], [out[3], out[4]]]), Se, "S")
    assert ws.deferred == (2 * ((len(order)) % ekf.MAX_DEFERRED) if defer else 0)
    ekf.flush(L, x.size, ws)
    assert ws.deferred == 0
    assert_close(xb[:x.size], xe, "x")
    assert_close(full(L, x.size), Pe, "P")


def test_a_deferred_update_is_guarded_against_the_held_back_downdates() -> None:
    """The guard checks each variance of the P that the held-back downdates leave: a step
    that would drive one negative only together with them is refused, nothing written."""
    rng = np.random.default_rng(5)
    n = 3
    x, P = random_state(rng, n)
    a = 3
    z = np.array([math.hypot(x[a] - x[0], x[a + 1] - x[1]),
                  wrap(math.atan2(x[a + 1] - x[1], x[a] - x[0]) - x[2])])
    xb, L, ws = put(x, P)
    ekf.update(xb, L, n, 0, z_range=z[0], z_bearing=z[1], var_range=SIG_R**2,
               var_bearing=SIG_B**2, ws=ws, defer=True)
    # a held-back downdate that takes almost all that is left of P_77 (landmark 2's y
    # variance), not touching the five columns this update reads
    ws.pending[2:4, :] = 0.0
    left = P[7, 7] - ws.pending[0, 7] ** 2 - ws.pending[1, 7] ** 2
    ws.pending[2, 7] = math.sqrt(left) * (1 - 1e-9)
    ws.deferred = 4
    before_x, before_l, before_held = xb.copy(), L.copy(), ws.pending.copy()
    with pytest.raises(ekf.RefusedStepError, match="variance 7"):
        ekf.update(xb, L, n, 0, z_range=z[0], z_bearing=z[1], var_range=SIG_R**2,
                   var_bearing=SIG_B**2, ws=ws, guard=ekf.Guard(psd_rtol=1e-9), defer=True)
    assert np.array_equal(xb, before_x)
    assert np.array_equal(L, before_l, equal_nan=True)
    assert ws.deferred == 4 and np.array_equal(ws.pending, before_held)


def test_mixed_sequence_equals_dense() -> None:
    """predict / initialise / update interleaved over a growing map, against the oracle."""
    rng = np.random.default_rng(7)
    x = np.zeros(3)
    P = np.diag([1e-4, 1e-4, 1e-5])
    cap = 3 + 2 * 20
    xb = np.zeros(cap)
    L = np.zeros((cap, cap))
    L[:3, :3] = np.tril(P)
    ws = ekf.Workspace.for_capacity(cap)
    n = 0
    for step in range(60):
        v, w = rng.uniform(0, 1), rng.normal(0, 0.5)
        x, P = dense_predict(x, P, v, w, 0.1)
        ekf.predict(xb, L, n, v=v, w=w, dt=0.1, var_v=SIG_V**2, var_w=SIG_W**2)
        if step % 3 == 0 and n < 20:
            z = np.array([rng.uniform(0.5, 3), rng.uniform(-1.5, 1.5)])
            x, P = dense_initialise(x, P, z)
            ekf.initialise(xb, L, n, z_range=z[0], z_bearing=z[1], var_range=SIG_R**2,
                           var_bearing=SIG_B**2, ws=ws)
            n += 1
        elif n:
            j = int(rng.integers(0, n))
            a = 3 + 2 * j
            z = np.array([math.hypot(x[a] - x[0], x[a + 1] - x[1]) + rng.normal(0, SIG_R),
                          wrap(math.atan2(x[a + 1] - x[1], x[a] - x[0]) - x[2]
                               + rng.normal(0, SIG_B))])
            x, P, _, _ = dense_update(x, P, j, z)
            ekf.update(xb, L, n, j, z_range=z[0], z_bearing=z[1], var_range=SIG_R**2,
                       var_bearing=SIG_B**2, ws=ws)
        N = 3 + 2 * n
        assert_close(xb[:N], x, f"x at step {step}")
        assert_close(full(L, N), P, f"P at step {step}")


def test_bearing_innovation_is_wrapped_across_pi() -> None:
    """A landmark straight behind, seen at +π−ε, predicted at −π+ε: ν is small, not 2π."""
    x = np.array([0.0, 0.0, 0.0, -2.0, -1e-3])
    P = np.diag([1e-3, 1e-3, 1e-3, 1e-2, 1e-2])
    z = np.array([2.0, math.pi - 1e-3])
    xe, Pe, nue, _ = dense_update(x, P, 0, z)
    xb, L, ws = put(x, P)
    out = ekf.update(xb, L, 1, 0, z_range=z[0], z_bearing=z[1], var_range=SIG_R**2,
                     var_bearing=SIG_B**2, ws=ws)
    assert abs(out[1]) < 0.01
    assert_close(np.array(out[:2]), nue, "innovation")
    assert_close(xb[:5], xe, "x")


@pytest.mark.parametrize("use_blas", [True, False])
def test_downdate_paths_agree_on_a_strided_view(use_blas: bool) -> None:
    rng = np.random.default_rng(11)
    N, cap = 41, 64
    A = rng.normal(size=(N, N))
    P = A @ A.T
    L = np.zeros((cap, cap))
    L[:N, :N] = P
    vt = np.zeros((2, cap))
    vt[:, :N] = rng.normal(size=(2, N))
    ekf.downdate_lower(L, vt, N, use_blas=use_blas)
    expected = P - vt[:, :N].T @ vt[:, :N]
    assert_close(np.tril(L[:N, :N]), np.tril(expected), "lower triangle")
    assert np.all(L[N:, :] == 0) and np.all(L[:, N:] == 0), "wrote outside the N×N block"


def test_blas_downdate_is_available() -> None:
    """The fast path must really be in use here (else the benchmark targets cannot hold)."""
    assert ekf_storage._dsyrk() is not None


def test_singular_innovation_leaves_state_untouched() -> None:
    x = np.array([0.0, 0.0, 0.0, 0.0, 0.0])  # landmark exactly on the robot
    P = np.eye(5) * 0.01
    xb, L, ws = put(x, P)
    x0, L0 = xb.copy(), L.copy()
    with pytest.raises(ekf.SingularInnovationError):
        ekf.update(xb, L, 1, 0, z_range=1.0, z_bearing=0.0, var_range=SIG_R**2,
                   var_bearing=SIG_B**2, ws=ws)
    assert np.array_equal(xb, x0)
    assert np.array_equal(L, L0, equal_nan=True)
    # an indefinite P (e.g. corrupted by a fault) giving S ≤ 0 is refused as well
    x = np.array([0.0, 0.0, 0.0, 1.0, 0.0])
    P = -np.eye(5)
    xb, L, ws = put(x, P)
    x0, L0 = xb.copy(), L.copy()
    with pytest.raises(ekf.SingularInnovationError):
        ekf.update(xb, L, 1, 0, z_range=1.0, z_bearing=0.0, var_range=SIG_R**2,
                   var_bearing=SIG_B**2, ws=ws)
    assert np.array_equal(xb, x0)
    assert np.array_equal(L, L0, equal_nan=True)


@pytest.mark.parametrize("N", [1, 9, 127, 128, 129, 300])
def test_symmetric_materialises_lower_triangle(N: int) -> None:
    rng = np.random.default_rng(N)
    A = rng.normal(size=(N, N))
    P = A @ A.T
    L = np.triu(np.full((N + 3, N + 3), 99.0), 1)  # the upper triangle is never read
    L[:N, :N] += np.tril(P)
    out = ekf.symmetric(L, N)
    assert out.shape == (N, N)
    assert np.array_equal(out, out.T)
    assert np.array_equal(np.tril(out), np.tril(P))
    into = np.full((N, N), np.nan)  # into a given buffer: every entry written
    assert ekf.symmetric(L, N, out=into) is into
    assert np.array_equal(into, out)
