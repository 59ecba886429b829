"""MRCLAM replay: parsing against the files themselves, the stream, the map frame, real facts."""

from __future__ import annotations

import logging
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from slamlens.common.errors import SourceError
from slamlens.common.messages import Observations, Odometry, Truth
from slamlens.services.slam.mrclam import MrclamRun, load_mrclam

ROOT = Path(__file__).parents[2]
SMALL = ROOT / "tests" / "fixtures" / "mrclam_small"
FULL = ROOT / "../shared/data/mrclam6"
Small = tuple[MrclamRun, list[Any]]


def data_rows(path: Path) -> list[list[str]]:
    """The file's data lines split into fields, read here independently of the parser."""
    return [line.split() for line in path.read_text().splitlines()
            if line.strip() and not line.lstrip().startswith("#")]


def wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def split(events: list) -> tuple[list[Odometry], list[Truth], list[Observations]]:
    return ([e for e in events if isinstance(e, Odometry)],
            [e for e in events if isinstance(e, Truth)],
            [e for e in events if isinstance(e, Observations)])


@pytest.fixture(scope="module")
def small() -> Small:
    run = load_mrclam(SMALL, robot=1)
    return run, list(run.events())


def test_counts_match_the_files(small: Small) -> None:
    run, _ = small
    barcodes = {int(b): int(s) for s, b in data_rows(SMALL / "Barcodes.dat")}
    landmark_subjects = {int(r[0]) for r in data_rows(SMALL / "Landmark_Groundtruth.dat")}
    meas = data_rows(SMALL / "Robot1_Measurement.dat")
    kept = [r for r in meas if barcodes.get(int(r[1])) in landmark_subjects]
    robots = [r for r in meas if int(r[1]) in barcodes and barcodes[int(r[1])] <= 5]
    assert run.stats.odometry == len(data_rows(SMALL / "Robot1_Odometry.dat")) == 3952
    assert run.stats.groundtruth == len(data_rows(SMALL / "Robot1_Groundtruth.dat"))
    assert run.stats.measurements == len(kept) == 171
    assert run.stats.skipped_robot == len(robots) == 31
    assert run.stats.skipped_unknown_barcode == 0
    assert run.stats.batches == len({r[0] for r in kept})
    assert run.stats.total_bad_lines == 0
    assert list(run.landmark_ids) == list(range(6, 21))


def test_odometry_is_held_until_the_next_sample(small: Small) -> None:
    run, events = small
    odo, _, _ = split(events)
    rows = np.array(data_rows(SMALL / "Robot1_Odometry.dat"), dtype=float)
    assert len(odo) == rows.shape[0] - 1  # the last sample has no end
    for i in (0, 1, 500, len(odo) - 1):
        assert odo[i].stamp == rows[i + 1, 0]
        assert odo[i].dt == pytest.approx(rows[i + 1, 0] - rows[i, 0], abs=1e-9)
        assert (odo[i].v, odo[i].w) == (rows[i, 1], rows[i, 2])
    assert all(o.robot == "robot1" for o in odo)


def test_measurements_grouped_by_time_with_subject_ids(small: Small) -> None:
    run, events = small
    _, _, obs = split(events)
    barcodes = {int(b): int(s) for s, b in data_rows(SMALL / "Barcodes.dat")}
    kept = [(float(r[0]), barcodes[int(r[1])], float(r[2]), float(r[3]))
            for r in data_rows(SMALL / "Robot1_Measurement.dat")
            if barcodes.get(int(r[1]), 0) >= 6]
    flat = [(o.stamp, int(i), float(r), float(b))
            for o in obs for i, r, b in zip(o.ids, o.ranges, o.bearings, strict=True)]
    assert flat == kept  # every landmark line, in file order, nothing else
    stamps = [o.stamp for o in obs]
    assert len(stamps) == len(set(stamps))  # one batch per timestamp
    assert max(len(o.ids) for o in obs) >= 2


def test_stream_is_time_ordered_and_starts_at_the_map_origin(small: Small) -> None:
    run, events = small
    stamps = [e.stamp for e in events]
    assert all(b >= a for a, b in zip(stamps, stamps[1:], strict=False))
    first = events[0]
    assert isinstance(first, Truth) and first.stamp == run.t0
    assert np.array_equal(first.pose, [0.0, 0.0, 0.0])
    rank = {Odometry: 0, Truth: 1, Observations: 2}
    for a, b in zip(events, events[1:], strict=False):
        if a.stamp == b.stamp:
            assert rank[type(a)] <= rank[type(b)]


def test_truth_is_the_ground_truth_in_the_frame_of_the_start_pose(small: Small) -> None:
    run, events = small
    _, truths, _ = split(events)
    gt = np.array(data_rows(SMALL / "Robot1_Groundtruth.dat"), dtype=float)
    lm = np.array(data_rows(SMALL / "Landmark_Groundtruth.dat"), dtype=float)
    # origin: ground truth interpolated at the first odometry time
    t0 = run.t0
    x0, y0 = np.interp(t0, gt[:, 0], gt[:, 1]), np.interp(t0, gt[:, 0], gt[:, 2])
    th0 = np.interp(t0, gt[:, 0], np.unwrap(gt[:, 3]))
    c, s = math.cos(th0), math.sin(th0)
    expected_lm = np.column_stack([c * (lm[:, 1] - x0) + s * (lm[:, 2] - y0),
                                   -s * (lm[:, 1] - x0) + c * (lm[:, 2] - y0)])
    for truth in truths[1::400]:
        assert np.allclose(truth.landmarks, expected_lm, atol=1e-9)
        row = gt[gt[:, 0] == truth.stamp][0]
        back = np.array([x0 + c * truth.pose[0] - s * truth.pose[1],
                         y0 + s * truth.pose[0] + c * truth.pose[1]])
        assert np.allclose(back, row[1:3], atol=1e-9)
        assert abs(wrap(np.array(truth.pose[2] + th0 - row[3]))) < 1e-9


def test_window_selects_by_seconds_after_the_first_odometry(small: Small) -> None:
    run, _ = small
    events = list(run.events(start=10.0, end=20.0))
    odo, truths, obs = split(events)
    assert truths[0].stamp >= run.t0 + 10.0 and np.array_equal(truths[0].pose, [0, 0, 0])
    assert all(run.t0 + 10.0 <= e.stamp <= run.t0 + 20.0 for e in events)
    assert all(o.stamp - o.dt >= run.t0 + 10.0 - 1e-9 for o in odo)
    rows = np.array(data_rows(SMALL / "Robot1_Odometry.dat"), dtype=float)
    inside = (rows[:-1, 0] >= run.t0 + 10.0) & (rows[1:, 0] <= run.t0 + 20.0)
    assert len(odo) == int(inside.sum()) > 100 and obs
    no_truth = list(run.events(start=10.0, end=20.0, truth=False))
    assert not any(isinstance(e, Truth) for e in no_truth)
    assert len(no_truth) == len(odo) + len(obs)


def test_malformed_lines_and_unknown_barcodes_are_skipped_and_counted(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    folder = tmp_path / "mrclam"
    shutil.copytree(SMALL, folder)
    meas = folder / "Robot1_Measurement.dat"
    lines = meas.read_text().splitlines(keepends=True)
    injected = ["garbage here\n", "1248444190.0 61 nan 0.1\n", "1248444190.0 61 -1.0 0.1\n",
                "1248444190.0 61.5 1.0 0.1\n", "1248444190.0 99 1.0 0.1\n",  # 99: no subject
                "1248444190.0 61 1.0\n"]
    meas.write_text("".join(lines[:10] + injected + lines[10:]))
    odo = folder / "Robot1_Odometry.dat"
    odo.write_text(odo.read_text() + "1248444300.0 0.1 x\n\n")
    with caplog.at_level(logging.INFO, logger="slamlens.mrclam"):
        run = load_mrclam(folder, robot=1)
    assert run.stats.bad_lines == {"Robot1_Measurement.dat": 5, "Robot1_Odometry.dat": 1}
    assert run.stats.skipped_unknown_barcode == 1 and run.stats.unknown_barcodes == (99,)
    assert run.stats.measurements == 171 and run.stats.odometry == 3952
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "6 malformed" in warnings[0].getMessage()
    assert sum(len(o.ids) for o in split(list(run.events()))[2]) == 171


def test_missing_folder_or_robot_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="does not exist"):
        load_mrclam(tmp_path / "nowhere")
    with pytest.raises(SourceError, match=r"robots present: \[1\]"):
        load_mrclam(SMALL, robot=4)


@pytest.mark.parametrize("robot", [1, 3])
def test_real_dataset_facts(robot: int) -> None:
    """data/README.md: range MAD 4–12 cm, bearing MAD 0.004–0.012 rad, 0.5–3.6 % > 0.5 m."""
    assert (FULL / "Barcodes.dat").is_file(), f"shared MRCLAM data missing at {FULL}"
    run = load_mrclam(FULL, robot=robot)
    assert run.stats.unknown_barcodes  # "a few barcodes ... map to no subject"
    known = {int(b) for _, b in data_rows(FULL / "Barcodes.dat")}
    assert not set(run.stats.unknown_barcodes) & known
    _, truths, obs = split(list(run.events()))
    t = np.array([tr.stamp for tr in truths])
    poses = np.array([tr.pose for tr in truths])
    theta = np.unwrap(poses[:, 2])
    lm = dict(zip(truths[0].landmark_ids.tolist(), truths[0].landmarks, strict=True))
    dr, db = [], []
    for o in obs:
        if not t[0] <= o.stamp <= t[-1]:
            continue  # ground truth ends before robot 1's odometry does
        x, y = np.interp(o.stamp, t, poses[:, 0]), np.interp(o.stamp, t, poses[:, 1])
        th = np.interp(o.stamp, t, theta)
        for i, r, b in zip(o.ids, o.ranges, o.bearings, strict=True):
            mx, my = lm[int(i)]
            dr.append(r - math.hypot(mx - x, my - y))
            db.append(wrap(np.array(b - (math.atan2(my - y, mx - x) - th))))
    dr_a, db_a = np.array(dr), np.array(db)
    assert dr_a.size > 1000

    def mad(a: np.ndarray) -> float:
        return float(np.median(np.abs(a - np.median(a))))

    assert 0.04 <= mad(dr_a) <= 0.12
    assert 0.004 <= mad(db_a) <= 0.012
    assert 0.5 <= 100 * np.mean(np.abs(dr_a) > 0.5) <= 3.6


def test_robot_name_is_configurable() -> None:
    run = load_mrclam(SMALL, robot=1, robot_name="pioneer")
    assert run.robot == "pioneer"
    assert {e.robot for e in run.events(end=2.0)} == {"pioneer"}
