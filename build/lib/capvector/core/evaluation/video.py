"""Rollout videos as mp4 files, written by imageio's ffmpeg plugin (imageio-ffmpeg bundles the binary).

The encoder is imageio-ffmpeg's choice for .mp4: the first H.264 encoder the ffmpeg in use has
(libx264 in the bundled one), MPEG-4 part 2 where it has none (an ffmpeg named by IMAGEIO_FFMPEG_EXE
may lack them); pixels as yuv420p, so that browsers and common players open them. One encoder thread:
videos are written next to other work (a study's evaluations), never worth a core more.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

VIDEO_FPS = 80
"""Meta-World's `render_fps` (one env step is 12.5 ms of simulated time): videos play in real time."""
VIDEO_SUFFIX = ".mp4"


class Mp4Writer:
    """One mp4 written frame by frame, through a pipe into an ffmpeg process: a recorded episode's
    frames (up to 500 of 256 x 256 x 3 bytes) are never all in memory. Frames are uint8 (H, W, 3), H
    and W multiples of 16 (no rescaling); `close` (also after an error) ends the file."""

    def __init__(self, path: str | Path, fps: int = VIDEO_FPS):
        self.path, self.fps, self.frames = Path(path), fps, 0
        self._writer = None

    def append(self, frame: np.ndarray) -> None:
        if self._writer is None:
            self._writer = self._open(frame.shape)
        self._writer.append_data(frame)
        self.frames += 1

    def _open(self, shape: tuple[int, ...]) -> Any:  # imageio's writer
        import imageio.v2 as imageio

        height, width = shape[:2]
        if height % 16 or width % 16:
            raise ValueError(f"video frames must be multiples of 16 pixels a side, got {width}x{height}")
        return imageio.get_writer(
            self.path,
            format="FFMPEG",
            mode="I",
            fps=self.fps,
            pixelformat="yuv420p",
            macro_block_size=16,
            ffmpeg_log_level="error",
            output_params=["-threads", "1"],
        )

    def close(self) -> Path:
        if self._writer is None:
            raise ValueError(f"no frames were written to {self.path}")
        self._writer.close()
        return self.path


def write_mp4(frames: list[np.ndarray], path: str | Path, fps: int = VIDEO_FPS) -> Path:
    """Write frames (as `Mp4Writer` takes them) as an mp4 at `fps`."""
    writer = Mp4Writer(path, fps)
    try:
        for frame in frames:
            writer.append(frame)
    finally:
        if writer.frames:
            writer.close()
    if not writer.frames:
        raise ValueError(f"no frames to write to {path}")
    return writer.path
