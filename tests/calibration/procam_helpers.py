"""The procam Gray-code calibration captures in ../shared/data (5 poses of a 9x7 chessboard, 75 mm squares):
where they are, the board detected in their white frames, and one manifest per pose."""

from __future__ import annotations

import functools
import os
from pathlib import Path

import cv2

from appliance.calibration.boards import BoardSpec, Detection, detect
from appliance.patterns import BlackFrame, Sequence, WhiteFrame, gray_code_frames, write_manifest

PROCAM = Path(__file__).resolve().parents[3] / "shared" / "data" / "procam_graycode_calib"
PROCAM_BOARD = BoardSpec(type="chessboard", cols=9, rows=7, square_mm=75)


@functools.cache
def procam_white_detections() -> tuple[Detection | None, ...]:
    """The board in the 5 procam white frames (detected once per test session; other tests reuse it)."""
    return tuple(
        detect(cv2.imread(str(PROCAM / f"capture_{pose}" / "graycode_40.png"), cv2.IMREAD_GRAYSCALE), PROCAM_BOARD)
        for pose in range(5)
    )


def procam_manifests(folder: Path) -> list[Path]:
    """One manifest per procam pose, pointing at the shared images (frame order of the README)."""
    seq = Sequence(1024, 768, gray_code_frames(1024, "x", bits=10) + gray_code_frames(768, "y", bits=10)
                   + (WhiteFrame(), BlackFrame()))  # fmt: skip
    out = []
    for pose in range(5):
        imgs = [
            os.path.relpath(PROCAM / f"capture_{pose}" / f"graycode_{i:02d}.png", folder) for i in range(42)
        ]
        out.append(write_manifest(folder / f"pose{pose}.yaml", seq, ["cam0"], images={"cam0": imgs}))
    return out
