"""The recorder's pure parts: layout, the player's clock, the Foxglove scene (against the
viewer's own scene as an oracle), and reading bad recordings."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import msgpack
import numpy as np
import pytest
from mcap.writer import CompressionType, Writer

from slamlens.common.errors import SourceError
from slamlens.common.messages import Health, SlamState, Violation
from slamlens.common.scene3d import VIOLATION, SceneSettings, pair_glyphs
from slamlens.services.harness.procs import REPO
from slamlens.services.recorder.channels import FoxgloveTranslator, covariance_summary
from slamlens.services.recorder.layout import message_of_key, ntp64_to_ns, record_expressions
from slamlens.services.recorder.reading import Recording
from slamlens.services.recorder.scene import scene_update
from slamlens.services.recorder.timeline import PlayClock
from slamlens.services.visualiser.scene import build_scene
from slamlens.services.visualiser.settings import ViewSettings
from tests.mcap_check import protobuf_class

SCENE = None


def _state(n: int = 9, seed: int = 0, seq: int = 5) -> SlamState:
    rng = np.random.default_rng(seed)
    centres = np.array([[0.0, 0.0], [2.5, 0.3], [1.0, 2.6]])
    xy = centres[rng.integers(0, 3, n)] + rng.normal(0, 0.2, (n, 2))
    A = rng.normal(0, 0.1, (3 + 2 * n, 3 + 2 * n))
    P = A @ A.T + 1e-3 * np.eye(3 + 2 * n)
    return SlamState(robot="r1", seq=seq, stamp=1.0 + seq, step="update",
                     pose=np.array([0.3, -0.2, 0.4]), landmark_ids=np.arange(10, 10 + n),
                     landmarks=xy, covariance=P, epoch=7)


def test_ntp64_is_unix_nanoseconds() -> None:
    assert ntp64_to_ns((5 << 32) | (1 << 31)) == 5_500_000_000
    assert ntp64_to_ns(1 << 32) == 1_000_000_000


def test_keys_to_message_types_and_record_expressions() -> None:
    assert message_of_key("slamlens/robot/r1/state", "slamlens") == "SlamState"
    assert message_of_key("slamlens/camera/c/registration/r1", "slamlens") == "Registration"
    assert message_of_key("slamlens/camera/c/frame", "slamlens") == "CameraFrame"
    assert message_of_key("other/robot/r1/state", "slamlens") == ""
    assert message_of_key("a/b/robot/r1/odometry", "a/b") == "Odometry"
    assert record_expressions("slamlens") == ["slamlens/**"]
    assert record_expressions("slamlens", robots=("r1",), cameras=("c",)) == [
        "slamlens/robot/r1/**", "slamlens/camera/c/**"]


def test_the_play_clock_times_pauses_seeks_and_changes_rate() -> None:
    clock = PlayClock(rate=2.0, anchor_pos_ns=10_000_000_000, anchor_wall=100.0)
    assert clock.due(12_000_000_000) == pytest.approx(101.0)  # 2 s of recording at 2×
    assert clock.position_ns(100.5) == 11_000_000_000
    clock.pause(100.5)
    assert clock.position_ns(200.0) == 11_000_000_000
    clock.resume(300.0)
    assert clock.due(12_000_000_000) == pytest.approx(300.5)
    clock.seek(20_000_000_000, 301.0)
    assert clock.position_ns(302.0) == 22_000_000_000
    clock.set_rate(1.0, 302.0)
    assert clock.due(23_000_000_000) == pytest.approx(303.0)
    fast = PlayClock(rate=0.0, anchor_pos_ns=0, anchor_wall=0.0)
    assert fast.due(10**18) == float("-inf")
    fast.played(5)
    assert fast.position_ns(1e9) == 5


@pytest.mark.parametrize("mode", ["all", "inter", "minmeanmax"])
@pytest.mark.parametrize("glyph", ["sigma", "linear"])
def test_the_foxglove_glyphs_are_the_viewers_glyphs(mode: str, glyph: str) -> None:
    state = _state()
    mine = pair_glyphs(state, SceneSettings(mode=mode, glyph=glyph, cluster_threshold_m=0.8))
    view = ViewSettings(mode=mode, glyph=glyph, cluster_threshold_m=0.8)
    from slamlens.common.clusters import cluster_labels

    labels = cluster_labels(state.landmarks, threshold_m=0.8) if mode != "all" else None
    theirs = build_scene(state, view, cluster_ids=labels)
    assert len(mine.centres) > 0
    np.testing.assert_allclose(mine.lines_xy, theirs.lines_xy)
    np.testing.assert_allclose(mine.centres, theirs.glyphs.centres)
    np.testing.assert_allclose(mine.axes[:, 0], theirs.glyphs.a)
    np.testing.assert_allclose(mine.axes[:, 1], theirs.glyphs.b)
    np.testing.assert_allclose(mine.axes[:, 2], theirs.glyphs.h)
    np.testing.assert_allclose(mine.yaw, theirs.glyphs.yaw)
    np.testing.assert_array_equal(mine.role, theirs.glyph_role)
    np.testing.assert_allclose(mine.sizes_m, theirs.glyph_size)


def _decode_scene(data: bytes):
    from foxglove.messages import SceneUpdate

    global SCENE
    if SCENE is None:
        s = SceneUpdate.get_schema()
        SCENE = protobuf_class(s.name, bytes(s.data))
    return {e.id: e for e in SCENE.FromString(data).entities}


def test_suspects_and_flagged_pairs_are_magenta() -> None:
    state = _state(n=4)
    health = Health(robot="r1", seq=5, stamp=6.0, ok=False, suspects=np.array([11]),
                    violations=(Violation(kind="pair", ids=(12, 10), step=5, value=0.1),))
    data, glyphs = scene_update(state, SceneSettings(), log_time_ns=10**9,
                                path_xy=np.zeros((0, 2)), health=health)
    entities = _decode_scene(data)
    colours = [(c.color.r, c.color.g, c.color.b)
               for c in entities["r1/features"].cylinders]
    assert colours[1] == pytest.approx(VIOLATION) and colours[0] != pytest.approx(VIOLATION)
    spheres = entities["r1/ellipsoids"].spheres
    pair_index = [(10, 11), (10, 12), (10, 13), (11, 12), (11, 13), (12, 13)].index((10, 12))
    assert glyphs.flagged.tolist() == [i == pair_index for i in range(6)]
    assert (spheres[pair_index].color.r, spheres[pair_index].color.b) == (1.0, 1.0)
    assert spheres[0].color.b < 0.2


def test_the_translator_draws_at_most_scene_hz_and_always_the_newest() -> None:
    tr = FoxgloveTranslator(SceneSettings(), prefix="slamlens", scene_hz=2.0)
    drawn = []
    for seq in range(10):  # stamps 1.0 … 10.0 s, at 2 Hz every state is due; 0.1 s apart
        state = _state(seq=seq)
        state = SlamState(**{**{f: getattr(state, f) for f in (
            "robot", "step", "pose", "landmark_ids", "landmarks", "covariance", "epoch")},
            "seq": seq, "stamp": 1.0 + 0.1 * seq})
        out = tr.feed("slamlens/robot/r1/state", state.to_bytes(), 10**9 + seq)
        drawn += [seq for m in out if m.topic.endswith("/scene")]
    drawn += [9 for m in tr.finish() if m.topic.endswith("/scene")]
    assert drawn == [0, 5, 9]
    summary = covariance_summary(_state(n=3))
    assert summary["pairs_n"] == 3 and len(summary["pairs"]) == 3
    assert summary["pd_min_m"] <= summary["pd_mean_m"] <= summary["pd_max_m"]


# ------------------------------------------------------------------ bad recordings


def _write(path: Path, channels: dict[str, tuple[str, list[bytes]]]) -> None:
    with path.open("wb") as f:
        w = Writer(f, chunk_size=2048, compression=CompressionType.LZ4)
        w.start()
        ids = {topic: w.register_channel(topic, enc, 0) for topic, (enc, _) in channels.items()}
        t = 1_000_000_000
        for topic, (_, payloads) in channels.items():
            for data in payloads:
                t += 1_000_000
                w.add_message(ids[topic], log_time=t, data=data, publish_time=t)
        w.finish()


def _payload(seq: int) -> bytes:
    return msgpack.packb({"schema": 1, "seq": seq, "pad": b"x" * 300}, use_bin_type=True)


def test_not_mcap_and_missing_files_are_one_clear_error(tmp_path: Path) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_text("not a recording\n")
    with pytest.raises(SourceError, match="is not an MCAP file"):
        Recording(junk)
    with pytest.raises(SourceError, match="does not exist"):
        Recording(tmp_path / "nothing.mcap")
    proc = subprocess.run([sys.executable, "-m", "slamlens.services", "play", str(junk)], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    assert proc.stderr.strip().splitlines() == [
        f"slamlens: error: {junk} is not an MCAP file (it starts with b'not a re', not the "
        "MCAP magic)"]


def test_unknown_encodings_and_malformed_payloads_are_counted_skips(tmp_path: Path) -> None:
    path = tmp_path / "mixed.mcap"
    _write(path, {
        "slamlens/robot/r1/state": ("msgpack", [_payload(0), b"\xc1garbage", _payload(1),
                                                msgpack.packb([1, 2]), _payload(2)]),
        "slamlens/robot/r1/odometry": ("cdr", [b"\x00\x01"]),
        "bad key/*": ("msgpack", [_payload(9)]),
        "/foxglove/robot/r1/scene": ("protobuf", [b""]),
    })
    rec = Recording(path)
    assert rec.playable_topics() == ["slamlens/robot/r1/state"]
    assert "unknown message encoding 'cdr'" in rec.skipped_channels["slamlens/robot/r1/odometry"]
    assert "derived" in rec.skipped_channels["/foxglove/robot/r1/scene"]
    assert "is not a Zenoh key" in rec.skipped_channels["bad key/*"]
    played = list(rec.messages())
    assert [msgpack.unpackb(m.data)["seq"] for m in played] == [0, 1, 2]
    assert rec.bad.total == 2


def test_a_truncated_file_reads_up_to_its_last_complete_chunk(tmp_path: Path) -> None:
    path = tmp_path / "whole.mcap"
    _write(path, {"slamlens/robot/r1/state": ("msgpack", [_payload(i) for i in range(200)])})
    cut = tmp_path / "cut.mcap"
    data = path.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    rec = Recording(cut)
    assert rec.truncated and rec.playable_topics() == ["slamlens/robot/r1/state"]
    seqs = [msgpack.unpackb(m.data)["seq"] for m in rec.messages()]
    assert 20 < len(seqs) < 200 and seqs == list(range(len(seqs)))
    assert json.dumps(seqs)  # plain ints
