"""Writing run artifacts: PNG images and plots, MP4/GIF videos, rerun recordings."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Iterable

import numpy as np


def _tmp(path: Path) -> Path:
    return path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")


def save_image(path: Path, image: np.ndarray) -> Path:
    """Save a uint8 HxW(x3) image as PNG, atomically."""
    import imageio.v3 as iio

    path = Path(path)
    tmp = _tmp(path)
    iio.imwrite(tmp, np.asarray(image, dtype=np.uint8), extension=".png")
    os.replace(tmp, path)
    return path


def save_video(path: Path, frames: Iterable[np.ndarray], fps: float = 25.0) -> Path:
    """Save frames as MP4 (H.264 through imageio-ffmpeg) or GIF, by the file's suffix."""
    import imageio.v3 as iio

    path = Path(path)
    frames = [np.asarray(f, dtype=np.uint8) for f in frames]
    if not frames:
        raise ValueError("save_video: no frames")
    tmp = _tmp(path)
    if path.suffix == ".gif":
        iio.imwrite(tmp, np.stack(frames), extension=".gif", duration=1000.0 / fps, loop=0)
    else:
        # H.264 needs even sizes; pad by one pixel where needed
        h, w = frames[0].shape[:2]
        pad = ((0, h % 2), (0, w % 2), (0, 0))
        frames = [np.pad(f, pad[: f.ndim], mode="edge") for f in frames]
        iio.imwrite(tmp, np.stack(frames), extension=".mp4", fps=fps, codec="libx264", macro_block_size=1)
    os.replace(tmp, path)
    return path


def save_movie(stem: Path, frames: list[np.ndarray], fps: float = 25.0) -> Path:
    """Save frames as ``stem``.mp4, or, where no H.264 encoder is at hand, as ``stem``.gif at half
    the frame rate (a GIF of every frame is large); returns the file written."""
    stem = Path(stem)
    try:
        return save_video(stem.with_suffix(".mp4"), frames, fps=fps)
    except Exception:  # imageio-ffmpeg without libx264, or no ffmpeg binary
        return save_video(stem.with_suffix(".gif"), list(frames)[::2], fps=fps / 2)


def read_rgb_image(path: Path, size: int, what: str = "--target", who: str = "the model sees") -> np.ndarray:
    """An RGB image file of ``size`` x ``size`` pixels as uint8 (H, W, 3); anything else exits 2
    with one line naming ``what`` (the option) and what ``who`` expects."""
    import imageio.v3 as iio

    from .errors import BadInput

    try:
        image = np.asarray(iio.imread(path, plugin="pillow"))
    except Exception as exc:  # imageio raises many kinds for a file that is not an image
        raise BadInput(f"{what} {path}: not an image ({type(exc).__name__})") from None
    if image.ndim == 3 and image.shape[2] == 4:
        image = image[..., :3]
    if image.ndim != 3 or image.shape[2] != 3:
        raise BadInput(f"{what} {path}: expected an RGB image, got an array of shape {image.shape}")
    if image.shape[:2] != (size, size):
        raise BadInput(f"{what} {path}: {who} {size}x{size} images, got {image.shape[1]}x{image.shape[0]}")
    return image.astype(np.uint8)


def save_training_curves(path: Path, history: list[dict[str, Any]], loss: str, metric: str,
                         chance: float | None = None) -> Path:
    """The training curves of ``fit``'s history (``epoch``, ``train_loss``, ``val_metric`` a point)
    as a PNG: ``loss`` and ``metric`` label the two curves, ``chance`` draws a dotted line."""

    def draw(ax):
        epochs = [h["epoch"] for h in history]
        ax.plot(epochs, [h["train_loss"] for h in history], marker="o", label=loss)
        ax.plot(epochs, [h["val_metric"] for h in history], marker="o", label=metric)
        if chance is not None:
            ax.axhline(chance, color="grey", ls=":", lw=1, label="chance")
        ax.set_xlabel("epoch")
        ax.legend()

    return save_plot(path, draw)


def save_plot(path: Path, draw, figsize=(5, 3.5)) -> Path:
    """``draw(ax)`` on a matplotlib axis, saved as PNG (headless Agg backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    fig, ax = plt.subplots(figsize=figsize, dpi=100)
    try:
        draw(ax)
        fig.tight_layout()
        tmp = _tmp(path)
        fig.savefig(tmp, format="png")
        os.replace(tmp, path)
    finally:
        plt.close(fig)
    return path


class Recording:
    """A rerun recording written to an .rrd file (``physint view`` opens it)."""

    def __init__(self, path: Path, name: str):
        import rerun as rr

        self.rr = rr
        self.path = Path(path)
        self.stream = rr.RecordingStream(f"physint-{name}")
        self.stream.save(str(self.path))

    def time(self, step: int | None = None, seconds: float | None = None) -> None:
        if step is not None:
            self.stream.set_time("step", sequence=int(step))
        if seconds is not None:
            self.stream.set_time("sim_time", duration=float(seconds))

    def image(self, entity: str, image: np.ndarray) -> None:
        self.stream.log(entity, self.rr.Image(np.asarray(image)))

    def scalar(self, entity: str, value: float) -> None:
        self.stream.log(entity, self.rr.Scalars([float(value)]))

    def points(self, entity: str, points: np.ndarray, **kw: Any) -> None:
        self.stream.log(entity, self.rr.Points3D(np.asarray(points), **kw))

    def text(self, entity: str, text: str) -> None:
        self.stream.log(entity, self.rr.TextDocument(text), static=True)

    def close(self) -> None:
        self.stream.flush()
        self.stream.disconnect()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
