"""``slamlens figures`` (a composition-level tool) writes the paper's twelve panels."""

from __future__ import annotations

import subprocess

import cv2
import numpy as np

from slamlens.services.harness.procs import REPO, slamlens_cmd


def test_figures_writes_twelve_panels_and_only_the_faulty_end_differs(tmp_path) -> None:
    out = subprocess.run(slamlens_cmd("figures", "--output-dir", str(tmp_path), "--width",
                                      "320", "--height", "180", "-q"),
                         cwd=REPO, capture_output=True, text=True, timeout=240)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == f"wrote 12 images to {tmp_path}"
    names = sorted(p.name for p in tmp_path.glob("*.png"))
    assert names == sorted(f"fig{n}{x}.png" for n in range(3, 9) for x in "ab")
    image = {p.stem: cv2.imread(str(p)) for p in tmp_path.glob("*.png")}
    assert all(im.shape == (180, 320, 3) for im in image.values())
    above_caption = slice(0, 180 - 30)
    # (a) is before the fault acts: the same picture in both runs (captions differ)
    np.testing.assert_array_equal(image["fig3a"][above_caption], image["fig6a"][above_caption])
    # (b) is after it: the faulty features' glyphs grew
    assert np.any(image["fig3b"][above_caption] != image["fig6b"][above_caption])
