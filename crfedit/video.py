"""Writing a sequence of rendered frames as a video: MP4 (H.264) or animated GIF.

MP4 needs the ``imageio-ffmpeg`` package (the ``[video]`` extra), whose wheel bundles an ffmpeg
binary.  Without it, or when the file name ends in ``.gif``, frames go to an animated GIF written
by Pillow.  Writes are atomic: the target appears only once the whole file is written.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from .errors import CrfError
from .io import atomic_path

DEFAULT_FPS = 12.0


def mp4_available() -> bool:
    """True when ``imageio_ffmpeg`` can be imported (MP4 can be written)."""
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        return False
    return True


def video_path(path: str | os.PathLike) -> Path:
    """The file :func:`write_video` writes for ``path`` (``.mp4`` or ``.gif``): ``path`` itself,
    or ``.gif`` in place of ``.mp4`` when MP4 cannot be written."""
    path = Path(path)
    if path.suffix.lower() not in (".mp4", ".gif"):
        raise CrfError(f"--video {path}: the file name must end in .mp4 or .gif")
    if path.suffix.lower() == ".gif" or mp4_available():
        return path
    return path.with_suffix(".gif")


MIN_FPS = 0.01
"""The slowest frame rate a video takes: 100 s a frame.  A GIF stores a frame's delay in 16 bits
of hundredths of a second (at most 655 s), and --fps 0.001 ended in an OverflowError."""


def check_fps(fps: float) -> float:
    """``fps`` when a video can play at it (:data:`MIN_FPS` to 240 frames a second), else a one-line error."""
    if not MIN_FPS <= fps <= 240:  # False for NaN too
        raise CrfError(f"--fps {fps:g}: must be from {MIN_FPS:g} (100 s a frame) to 240")
    return fps


def to_uint8(frame: np.ndarray) -> np.ndarray:
    """A float [H, W, 3] image in [0, 1] (or uint8) as contiguous uint8 [H, W, 3]."""
    arr = np.asarray(frame)
    if arr.dtype != np.uint8:
        arr = np.clip(np.round(np.nan_to_num(arr.astype(np.float64)) * 255.0), 0, 255).astype(np.uint8)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"expected an RGB frame [H, W, 3], got shape {arr.shape}")
    return np.ascontiguousarray(arr)


def write_video(path: str | os.PathLike, frames: Sequence[np.ndarray], fps: float = DEFAULT_FPS) -> Path:
    """Write ``frames`` (RGB [H, W, 3], float in [0, 1] or uint8, one size) and return the path
    written: MP4 when possible and ``path`` does not end in ``.gif``, else a GIF (see
    :func:`video_path`)."""
    if not frames:
        raise CrfError(f"{path}: no frames to write")
    check_fps(fps)
    target = video_path(path)
    images = [to_uint8(f) for f in frames]
    if any(im.shape != images[0].shape for im in images):
        raise CrfError(f"{path}: frames differ in size; a video needs one size")
    if target.suffix.lower() == ".gif":
        _write_gif(target, images, fps)
    else:
        _write_mp4(target, images, fps)
    return target


def gif_frame_rate(fps: float) -> float:
    """The rate a GIF asked for ``fps`` plays at: a GIF's frame time is a whole number of
    hundredths of a second, at least 2 (browsers clamp shorter ones), so 12 fps plays at 12.5."""
    return 100.0 / max(2, round(100.0 / fps))


def _write_gif(path: Path, images: list[np.ndarray], fps: float) -> None:
    from PIL import Image

    pil = [Image.fromarray(im) for im in images]
    duration = round(1000.0 / gif_frame_rate(fps))  # ms per frame, a multiple of 10 that Pillow stores exactly
    with atomic_path(path) as tmp:
        pil[0].save(tmp, format="GIF", save_all=True, append_images=pil[1:], duration=duration, loop=0)


def _write_mp4(path: Path, images: list[np.ndarray], fps: float) -> None:
    """H.264 in yuv420p, which needs even sides: odd sides get one white row/column."""
    import imageio_ffmpeg

    h, w = images[0].shape[:2]
    ph, pw = h % 2, w % 2
    if ph or pw:
        images = [np.pad(im, ((0, ph), (0, pw), (0, 0)), constant_values=255) for im in images]
    with atomic_path(path) as tmp:
        writer = imageio_ffmpeg.write_frames(
            str(tmp), (w + pw, h + ph), fps=fps, codec="libx264", macro_block_size=2,
            output_params=["-f", "mp4"], ffmpeg_log_level="error",
        )
        writer.send(None)  # start ffmpeg
        try:
            for im in images:
                writer.send(im)
        finally:
            writer.close()
