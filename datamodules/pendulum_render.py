"""What the pendulum's sensors report: its camera's frames, in two renderings, with their noise and 8-bit
quantisation, and the joint encoders' reading.

Images, two renderings (``rendering``):

- ``"paper"`` (the default; the paper's public generator, ``ssm_ms/data/n_link.py`` of
  machines-in-motion/ssm_multiple_shooting): drawn with the generator's own calls, PIL's
  ``ImageDraw.line(width=8)`` on a ``128 x 128`` float canvas, pivot at canvas point ``(64, 64)``, the whole
  chain ``64`` canvas pixels long (a straight chain reaches the edge of the frame), then
  ``Image.resize(..., Image.LANCZOS)`` to ``image_size`` (which rings: clean values reach about -0.1 and 1.2).
  PIL's conventions are kept with it: a coordinate names a pixel index (pixel ``64`` is lit at the pivot,
  whose centre is 64.5 canvas pixels from the edge), end points are truncated to whole pixels, and an
  8-pixel line covers 3 pixels on one side of its axis and 4 on the other, so a hanging chain lights
  columns 61-68. Equal to the reference's ``create_image`` (without its noise) to the last bit on 2000
  random states per system (``tests/test_pendulum.py`` pins the pivot pixel against a closed form).
  ``line_width`` is in output pixels (default ``image_size / 16``, the paper's 8 of 128), drawn as the
  nearest whole number of canvas pixels.
- ``"analytic"`` (this project's first rendering, kept for the CPU twins' committed results):
  anti-aliased thick lines with round caps; a pixel's intensity is
  ``clip(line_width / 2 + 0.5 - distance, 0, 1)`` where ``distance`` is from the pixel centre to the
  nearest link segment (an analytic coverage estimate, max over segments). The whole chain spans
  ``image_size / 2 - line_width / 2 - 1`` pixels, so that the tip, its cap and its anti-aliasing ramp
  stay inside the image. Default ``line_width`` 2.

In both, every link has the same length in pixels, image right is the direction of positive angles
(``theta = pi / 2`` with one link points right), image down is gravity. Noise, as the paper's generator:
``y = clip(clean + N(0, noise_std^2), 0, 1)``, drawn on the float clean image (before any clipping);
then ``y`` and ``y_clean = clip(clean, 0, 1)`` are quantised to ``uint8`` (step ``1/255``; its error
std ``1/(255 sqrt 12) ~ 1.1e-3`` is negligible next to ``noise_std = 0.2``).
"""

from __future__ import annotations

import math

import numpy as np

RENDERINGS = ("paper", "analytic")
PAPER_CANVAS = 128  # the paper's generator draws on a 128 x 128 canvas, 8 pixels wide, then resizes


def default_line_width(rendering: str, image_size: int) -> float:
    """Line thickness in output pixels when none is given: the paper's 8 of 128, or 2 (analytic)."""
    return 8.0 * image_size / PAPER_CANVAS if rendering == "paper" else 2.0


def paper_canvas_width(line_width: float, image_size: int) -> int:
    """The line width in canvas pixels that PIL draws (a whole number): ``line_width`` output pixels scaled to the
    128-pixel canvas (the paper's 8 for ``image_size / 16``)."""
    return max(1, int(round(line_width * PAPER_CANVAS / image_size)))


def render_paper(angles: np.ndarray, image_size: int, line_width: float | None = None) -> np.ndarray:
    """Render chains as the paper's generator does, with its own drawing calls (see the module doc): PIL's
    ``ImageDraw.line`` on a 128 x 128 float canvas, pivot at canvas point ``(64, 64)``, the chain half the canvas
    long, then ``Image.resize(..., Image.LANCZOS)`` to ``image_size``.

    Args:
        angles: joint angles ``[T, n]`` (relative, as in :func:`~datamodules.pendulum_sim.pendulum_model`).
        image_size: output height and width in pixels.
        line_width: thickness in output pixels (default ``image_size / 16``, the paper's 8 canvas pixels); drawn
            as :func:`paper_canvas_width` whole canvas pixels.

    Returns:
        float32 ``[T, 1, H, W]``, not clipped (the filter rings slightly outside [0, 1]).
    """
    from PIL import Image, ImageDraw  # Pillow: a dependency of matplotlib, listed in pyproject.toml

    angles = np.asarray(angles, dtype=np.float64)
    if angles.ndim != 2:
        raise ValueError(f"angles must be [T, n_links], got shape {angles.shape}")
    if line_width is None:
        line_width = default_line_width("paper", image_size)
    width = paper_canvas_width(line_width, image_size)
    frames, n = angles.shape
    phi = np.cumsum(angles, axis=-1)
    # joint positions in canvas coordinates (x right, y down: image down is gravity); PIL lights the pixel whose
    # index is the (truncated) coordinate, so the pivot (64, 64) is pixel 64, as in the reference generator
    steps = np.stack([np.sin(phi), np.cos(phi)], axis=-1) * (PAPER_CANVAS / 2 / n)
    pts = np.concatenate([np.zeros((frames, 1, 2)), np.cumsum(steps, axis=-2)], axis=-2) + PAPER_CANVAS / 2
    out = np.empty((frames, 1, image_size, image_size), np.float32)
    for t in range(frames):
        canvas = Image.new("F", (PAPER_CANVAS, PAPER_CANVAS), 0.0)
        draw = ImageDraw.Draw(canvas)
        for s in range(n):
            draw.line([tuple(pts[t, s]), tuple(pts[t, s + 1])], fill=1.0, width=width)
        out[t, 0] = np.asarray(canvas.resize((image_size, image_size), resample=Image.LANCZOS))
    return out


def chain_length_pixels(image_size: int, line_width: float) -> float:
    """Length of the whole chain in pixels in the analytic rendering: half the image minus room for the tip's
    cap and ramp (the paper's rendering: half the image)."""
    return image_size / 2.0 - line_width / 2.0 - 1.0


def joint_positions(angles: np.ndarray, image_size: int, line_width: float) -> np.ndarray:
    """Pixel coordinates ``[..., n + 1, 2]`` (x right, y down; pixel ``(i, j)`` spans
    ``[j, j + 1] x [i, i + 1]``) of the pivot (the image centre) and the end of every link."""
    n = angles.shape[-1]
    link = chain_length_pixels(image_size, line_width) / n
    phi = np.cumsum(angles, axis=-1)
    steps = np.stack([np.sin(phi), np.cos(phi)], axis=-1) * link  # down is +y in the image
    pts = np.concatenate([np.zeros((*angles.shape[:-1], 1, 2)), np.cumsum(steps, axis=-2)], axis=-2)
    return pts + image_size / 2.0


def render_analytic(angles: np.ndarray, image_size: int, line_width: float | None = None) -> np.ndarray:
    """Render chains to anti-aliased images with round caps (the ``"analytic"`` rendering).

    Args:
        angles: joint angles ``[T, n]`` (relative, as in :func:`~datamodules.pendulum_sim.pendulum_model`).
        image_size: image height and width in pixels.
        line_width: line thickness in pixels.

    Returns:
        float32 ``[T, 1, H, W]`` in [0, 1]: ``clip(line_width / 2 + 0.5 - distance, 0, 1)``, with
        ``distance`` from the pixel centre to the nearest link segment.

    Each segment is evaluated only on a ``K x K`` window around it (``K`` = link length + line
    width + 3 pixels), which holds every pixel it can light; the windows are merged with ``max``.
    """
    angles = np.asarray(angles, dtype=np.float64)
    if angles.ndim != 2:
        raise ValueError(f"angles must be [T, n_links], got shape {angles.shape}")
    if line_width is None:
        line_width = default_line_width("analytic", image_size)
    frames, n = angles.shape
    reach = line_width / 2.0 + 0.5  # farthest a lit pixel centre can be from a segment
    link = chain_length_pixels(image_size, line_width) / n
    k = min(int(math.ceil(link + 2.0 * reach)) + 2, image_size)
    pts = joint_positions(angles, image_size, line_width).astype(np.float32)
    a, b = pts[:, :-1], pts[:, 1:]  # segment ends [T, n, 2]
    # window origins: the first pixel whose centre may lie within `reach` of the segment
    origin = np.floor(np.minimum(a, b) - np.float32(reach + 0.5)).astype(np.int64)
    np.clip(origin, 0, image_size - k, out=origin)
    idx = origin[..., None] + np.arange(k)  # pixel indices [T, n, 2, K]
    centres = idx.astype(np.float32) + np.float32(0.5)
    d = b - a
    inv_len2 = (1.0 / (d**2).sum(-1))[..., None, None]
    rx = centres[:, :, 0, None, :] - a[..., 0, None, None]  # [T, n, 1, K]
    ry = centres[:, :, 1, :, None] - a[..., 1, None, None]  # [T, n, K, 1]
    dx, dy = d[..., 0, None, None], d[..., 1, None, None]
    t = rx * (dx * inv_len2) + ry * (dy * inv_len2)  # projection on the segment [T, n, K, K]
    np.clip(t, 0.0, 1.0, out=t)
    ex = rx - t * dx
    ey = ry - t * dy
    val = np.float32(reach) - np.sqrt(ex * ex + ey * ey)
    np.clip(val, 0.0, 1.0, out=val)
    img = np.zeros((frames, image_size, image_size), np.float32)
    rows = np.arange(frames)[:, None, None]
    for s in range(n):  # windows of one segment lie in different frames: no clash within an assignment
        where = (rows, idx[:, s, 1, :, None], idx[:, s, 0, None, :])
        img[where] = np.maximum(img[where], val[:, s])
    return img[:, None]


RENDERERS = {"paper": render_paper, "analytic": render_analytic}


def render(
    angles: np.ndarray, image_size: int, line_width: float | None = None, rendering: str = "paper"
) -> np.ndarray:
    """Clean frames ``[T, 1, H, W]`` (float32) of chains with joint angles ``[T, n]``, in either rendering."""
    if rendering not in RENDERERS:
        raise ValueError(f"unknown rendering {rendering!r}: choose among {list(RENDERERS)}")
    return RENDERERS[rendering](angles, image_size, line_width)


def quantize(img: np.ndarray) -> np.ndarray:
    """Floats -> uint8 0..255 (clipped to [0, 1], rounded)."""
    return np.rint(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)


def angle_reading(q: np.ndarray) -> np.ndarray:
    """What the joint encoders report for angles ``[..., n]``: ``[sin q_1 .. sin q_n, cos q_1 .. cos q_n]``
    (float32, ``[..., 2 n]``). The sine and cosine, not the angle: a driven joint turns over and over (the
    torque-driven data reach 137 rad), and an angle without bound is one no network extrapolates; this reading is
    bounded, continuous through upright (a wrapped angle jumps there) and the observation of gym's Pendulum."""
    return np.concatenate([np.sin(q), np.cos(q)], axis=-1).astype(np.float32)
