"""``slamlens rerun``'s pure parts, through a real Rerun recording read back with Rerun's
own reader: the ellipsoids against the textbook relative covariances (dense, one pair at a
time, numpy's ``eigh``), the plots and the text log, the timelines, bad input, and the
command without the Rerun SDK."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rerun as rr

from slamlens.common.errors import MessageError
from slamlens.common.messages import (
    CameraFrame,
    Health,
    Registration,
    SlamState,
    Truth,
    Violation,
)
from slamlens.services.harness.procs import REPO
from slamlens.services.rerun.settings import RerunSettings
from slamlens.services.rerun.translator import RerunTranslator, log_batches
from tests.rrd_check import read_rrd, stores

ROBOT = "r1"
JPEG = b"\xff\xd8\xff\xe0" + b"\x00" * 64


def _state(n: int = 7, seq: int = 5, stamp: float = 2.5, epoch: int = 7,
           seed: int = 0) -> SlamState:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-2.0, 3.0, (n, 2))
    A = rng.normal(0, 0.1, (3 + 2 * n, 3 + 2 * n))
    P = A @ A.T + 1e-3 * np.eye(3 + 2 * n)
    return SlamState(robot=ROBOT, seq=seq, stamp=stamp, step="update",
                     pose=np.array([0.3, -0.2, 0.4]), landmark_ids=np.arange(10, 10 + n),
                     landmarks=xy, covariance=P, epoch=epoch)


def _record(path: Path, translator: RerunTranslator,
            messages: list[tuple[str, bytes]]) -> dict:
    """The messages through the translator into a real .rrd; what Rerun reads back."""
    rec = rr.RecordingStream("slamlens-test")
    rec.set_sinks(rr.FileSink(str(path)))
    log_batches(rec, translator.start())
    for kind, payload in messages:
        log_batches(rec, translator.feed(kind, payload))
    log_batches(rec, translator.finish())
    rec.flush(timeout_sec=10)
    rec.disconnect()
    return read_rrd(path)


def _at(rows: list[dict], seq: int) -> dict:
    hits = [r for r in rows if r.get("seq") == seq]
    assert hits, f"no row at seq {seq}"
    return hits[-1]


def _rotate_x(q: np.ndarray) -> np.ndarray:
    """Where the quaternion (x, y, z, w) takes the x axis."""
    x, y, z, w = q
    return np.array([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)])


def test_the_ellipsoids_are_the_textbook_relative_covariances(tmp_path: Path) -> None:
    state = _state()
    n, P, xy = state.n, state.covariance, state.landmarks
    rows = _record(tmp_path / "a.rrd", RerunTranslator(RerunSettings(robot=ROBOT)),
                   [("state", state.to_bytes())])
    ell = _at(rows[f"/world/{ROBOT}/ellipsoids"], state.seq)
    centres = np.array(ell["Ellipsoids3D:centers"])
    halves = np.array(ell["Ellipsoids3D:half_sizes"])
    quats = np.array(ell["Ellipsoids3D:quaternions"])
    assert len(centres) == n * (n - 1) // 2
    sizes = []
    k = 0
    for i in range(n):
        for j in range(i + 1, n):
            a, b = 3 + 2 * i, 3 + 2 * j
            Pd = P[a:a + 2, a:a + 2] + P[b:b + 2, b:b + 2] - P[a:a + 2, b:b + 2] \
                - P[b:b + 2, a:a + 2]
            lam, vec = np.linalg.eigh(Pd)
            np.testing.assert_allclose(centres[k], [*(0.5 * (xy[i] + xy[j])), 0.0], atol=1e-6)
            np.testing.assert_allclose(halves[k], 2.0 * np.sqrt([lam[1], lam[0], lam[0]]),
                                       rtol=1e-6)
            along = _rotate_x(quats[k])
            assert abs(abs(along[:2] @ vec[:, 1]) - 1.0) < 1e-6 and abs(along[2]) < 1e-6
            sizes.append(np.sqrt(lam[1]))
            k += 1
    lines = _at(rows[f"/world/{ROBOT}/pairs"], state.seq)["LineStrips3D:strips"]
    assert len(lines) == n * (n - 1) // 2
    features = _at(rows[f"/world/{ROBOT}/features"], state.seq)
    np.testing.assert_allclose(np.array(features["Points3D:positions"])[:, :2], xy, atol=1e-6)
    assert features["Points3D:labels"] == [str(i) for i in range(10, 10 + n)]
    robot = _at(rows[f"/world/{ROBOT}/robot"], state.seq)
    np.testing.assert_allclose(robot["Points3D:positions"][0], [0.3, -0.2, 0.0], atol=1e-6)
    np.testing.assert_allclose(robot["Arrows3D:vectors"][0][:2],
                               0.25 * np.array([np.cos(0.4), np.sin(0.4)]), atol=1e-6)
    for name, value in (("min", min(sizes)), ("max", max(sizes)), ("mean", np.mean(sizes))):
        row = _at(rows[f"/plots/{ROBOT}/pd/{name}"], state.seq)
        assert row["Scalars:scalars"] == pytest.approx([value], rel=1e-9)
        assert row["stamp"] == pytest.approx(state.stamp)
    assert stores(tmp_path / "a.rrd") == (1, 0)


def test_health_plots_its_bands_and_says_the_verdict_once_per_change(tmp_path: Path) -> None:
    stats = {"nees_pose": 2.5, "nees_pose_lo": 0.2, "nees_pose_hi": 9.3, "nis": 1.1,
             "nis_lo": 0.05, "nis_hi": 7.4, "gap": 3.0}

    def health(seq: int, verdict: str, violations: tuple[Violation, ...] = ()) -> bytes:
        return Health(robot=ROBOT, seq=seq, stamp=0.1 * seq, ok=not violations,
                      suspects=np.array([3] if violations else [], np.int64),
                      violations=violations, statistics=stats, verdict=verdict).to_bytes()

    bad = tuple(Violation(kind="pair", ids=(3, k), step=3, value=0.1 * k, detail=f"grew {k}")
                for k in range(4, 16))
    rows = _record(tmp_path / "h.rrd", RerunTranslator(RerunSettings(robot=ROBOT)), [
        ("health", health(1, "ok")), ("health", health(2, "ok")),
        ("health", health(3, "fault", bad)), ("health", health(4, "fault"))])
    for series, key in (("nees/value", "nees_pose"), ("nees/lo", "nees_pose_lo"),
                        ("nees/hi", "nees_pose_hi"), ("nis/value", "nis"), ("nis/hi", "nis_hi")):
        timed = [r for r in rows[f"/plots/{ROBOT}/{series}"] if "seq" in r]
        assert [r["seq"] for r in timed] == [1, 2, 3, 4]
        assert timed[0]["Scalars:scalars"] == [stats[key]]
    assert f"/plots/{ROBOT}/gap" not in rows
    texts = [(r["seq"], r["TextLog:level"][0], r["TextLog:text"][0])
             for r in rows[f"/log/{ROBOT}"]]
    verdicts = [t for t in texts if "verdict" in t[2]]
    assert [(s, level) for s, level, _ in verdicts] == [(1, "INFO"), (3, "ERROR")]
    at3 = [t for t in texts if t[0] == 3 and "verdict" not in t[2]]
    assert len(at3) == 11 and "pair 3–4: grew 4" in at3[0][2]  # 10, then "… and 2 more"
    assert "2 more" in at3[-1][2]


def _registration(stamp: float, T: np.ndarray | None = None) -> bytes:
    if T is None:
        T = np.eye(4)
        T[:3, :3] = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]
        T[:3, 3] = [-1.0, 0.5, 4.0]
    return Registration(camera="cam", robot=ROBOT, stamp=stamp,
                        K=np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]),
                        dist=np.zeros(5), width=640, height=480, T_camera_from_map=T,
                        reprojection_error_px=0.3).to_bytes()


def _frame(stamp: float, data: bytes = JPEG) -> bytes:
    return CameraFrame(camera="cam", seq=1, stamp=stamp, encoding="jpeg", width=640,
                       height=480, data=data).to_bytes()


def test_camera_messages_go_on_the_robots_clock(tmp_path: Path) -> None:
    wall = 1.8e9
    truth = Truth(robot=ROBOT, stamp=3.0, pose=np.array([1.0, 2.0, 0.5]),
                  landmark_ids=np.array([1, 2]), landmarks=np.array([[0.0, 1.0], [2.0, 3.0]]))
    tr = RerunTranslator(RerunSettings(robot=ROBOT, camera=("cam",)))
    rows = _record(tmp_path / "c.rrd", tr, [
        ("frame", _frame(wall)),  # before any robot data: skipped
        ("registration", _registration(wall)),  # waits for the robot's clock
        ("truth", truth.to_bytes()),
        ("frame", _frame(wall + 1)),  # another clock: at the robot's newest stamp
        ("frame", _frame(2.0)),  # the robot's clock: its own stamp
        ("state", _state(seq=9, stamp=4.0).to_bytes())])
    assert tr.early == 1 and tr.images == 2 and tr.cameras == 1
    images = [r for r in rows["/world/camera/cam/image"] if "EncodedImage:blob" in r]
    assert [(r["stamp"], r["seq"]) for r in images] == [(3.0, 0), (2.0, 0)]
    assert images[0]["EncodedImage:media_type"] == ["image/jpeg"]
    pose = rows["/world/camera/cam"][-1]
    assert pose["stamp"] == 3.0
    np.testing.assert_allclose(pose["Transform3D:translation"][0], [-1.0, 0.5, 4.0])
    assert pose["Transform3D:relation"] == [2]  # ChildFromParent: T_camera_from_map
    pinhole = [r for r in rows["/world/camera/cam/image"] if "Pinhole:image_from_camera" in r]
    assert pinhole[0]["Pinhole:resolution"] == [[640.0, 480.0]]
    np.testing.assert_allclose(np.array(pinhole[0]["Pinhole:image_from_camera"][0]
                                        ).reshape(3, 3).T,
                               [[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    true_robot = rows[f"/world/{ROBOT}/truth/robot"][-1]
    np.testing.assert_allclose(true_robot["Points3D:positions"][0], [1.0, 2.0, 0.0])
    assert rows[f"/world/{ROBOT}/truth/features"][-1]["Points3D:labels"] == ["1", "2"]


def test_scene_hz_thins_the_states_and_a_new_map_starts_the_path_again() -> None:
    tr = RerunTranslator(RerunSettings(robot=ROBOT, scene_hz=2.0))
    drawn = []
    for seq in range(12):
        out = tr.feed("state", _state(n=3, seq=seq, stamp=1.0 + 0.1 * seq).to_bytes())
        drawn += [seq] if out else []
    assert drawn == [0, 5, 10] and tr.skipped == 9
    out = tr.feed("state", _state(n=3, seq=0, stamp=0.0, epoch=8).to_bytes())
    paths = [log for batch in out for log in batch.logs if log.path.endswith("/path")]
    assert tr.maps == 2 and len(paths) == 1  # the new map's path, from its first pose


@pytest.mark.parametrize("kind, payload, field", [
    ("state", b"\xc1 not msgpack", ""),
    ("state", Health(robot=ROBOT, seq=1, stamp=0.0, ok=True, suspects=np.zeros(0, np.int64)
                     ).to_bytes(), ""),
    ("frame", _frame(1.0, b"GIF89a"), "data"),
    ("registration", _registration(1.0, np.diag([2.0, 1.0, 1.0, 1.0])), "T_camera_from_map"),
    ("truth", b"", ""),
    ("summary", _state().to_bytes(), ""),
])
def test_what_cannot_be_converted_is_a_message_error(kind: str, payload: bytes,
                                                     field: str) -> None:
    tr = RerunTranslator(RerunSettings(robot=ROBOT, camera=("cam",)))
    tr.feed("truth", Truth(robot=ROBOT, stamp=1.0, pose=np.zeros(3),
                           landmark_ids=np.zeros(0, np.int64),
                           landmarks=np.zeros((0, 2))).to_bytes())
    with pytest.raises(MessageError, match=field or None):
        tr.feed(kind, payload)
    assert tr.feed("state", _state().to_bytes())  # and the next good one is drawn


def test_without_the_rerun_sdk_the_command_says_how_to_install_it() -> None:
    code = ("import sys; sys.modules['rerun'] = None; "
            "from slamlens.services.commands.cli import main; sys.exit(main(sys.argv[1:]))")
    proc = subprocess.run([sys.executable, "-c", code, "rerun", "--save", "x.rrd",
                           "--connect", "tcp/127.0.0.1:9"], cwd=REPO, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 1
    assert proc.stderr.strip().splitlines() == [
        "slamlens: error: slamlens rerun needs the Rerun SDK, which the base install leaves "
        "out: pip install 'slamlens[rerun]' (or pip install rerun-sdk)"]
