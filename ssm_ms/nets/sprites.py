"""An image ``g`` for scenes of moving objects: each object a sprite drawn from its own code and moved, not redrawn.

A :class:`~ssm_ms.nets.ConvDecoder` maps a flat state to a whole frame, so a digit that moves 36 pixels has to be drawn
anew, by other weights, at every position it passes: on Moving MNIST at a CPU budget that ends in grey blobs
(``results/mnist_cpu.notes.md``). :class:`SpriteDecoder` separates *what* from *where*: the state holds, for each of
``n_sprites`` objects, two position components and ``what_dim`` content components; one shared ConvDecoder draws each
object's content as a ``sprite_size`` sprite, which is translated to its position (bilinear resampling) and composed
with the others and a uniform background (one learned intensity, so that a pixel no sprite covers is not drawn as
exactly 0) by the pixel-wise maximum, as Moving MNIST's frames are composed.

State layout (``state_dim >= n_sprites * (2 + what_dim)``): sprite ``s`` reads ``x[..., s * (2 + what_dim):]``, first
its position ``(row, column)`` then its content; the components after the sprites' (e.g. velocities) are free for
``f`` and not drawn. A position ``w`` in ``[-1, 1]`` puts the sprite's top-left corner at ``(w + 1) (H - S) / 2``
pixels from the canvas' (``H``: image size, ``S``: sprite size): ``-1`` at the top or left border, ``1`` at the bottom
or right; outside that range the sprite leaves the canvas in part. Positions add to a fixed per-sprite offset (on a
circle of radius ``offset_radius``, 0.5 by default; none for a single sprite), so that states that start equal, as
the shooting nodes do (zeros), do not draw every sprite at one place, where no gradient would tell them apart.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from ssm_ms.nets.decoder import ConvDecoder


class SpriteDecoder(nn.Module):
    """``[N, state_dim]`` -> ``[N, channels, image_size, image_size]``: ``n_sprites`` sprites, each drawn from its
    content code by one shared :class:`~ssm_ms.nets.ConvDecoder` and translated to its position, composed by the
    maximum.

    Args:
        state_dim: the state's size, at least ``n_sprites * (2 + what_dim)`` (the module doc: the layout).
        n_sprites: objects in a frame (Moving MNIST: its ``n_digits``).
        what_dim: content components per sprite.
        sprite_size: side of a sprite in pixels (Moving MNIST: its ``digit_size``, 28).
        image_size: side of the square frames (``None``: taken from the data; the model hands the data's shape).
        stem_channels, layers: the sprite ConvDecoder's stem and transposed convolutions (``[out_channels, kernel,
            stride]`` each; the last one's channels are the image's), drawn at ``sprite_size``
            (:class:`~ssm_ms.nets.ConvDecoder`'s ``image_size``).
        offset_radius: radius of the circle the sprites' fixed offsets lie on (0: no offsets).
        background: the background's initial intensity, in (0, 1) (learned, as a logit).
        backend: the sprite ConvDecoder's ``backend``.
    """

    def __init__(
        self,
        state_dim: int,
        n_sprites: int = 2,
        what_dim: int = 12,
        sprite_size: int = 28,
        image_size: int | None = None,
        stem_channels: int = 64,
        layers: Sequence[Sequence[int]] = ((64, 3, 2), (32, 3, 2), (1, 4, 2)),
        offset_radius: float = 0.5,
        background: float = 0.01,
        backend: str = "auto",
    ):
        super().__init__()
        need = n_sprites * (2 + what_dim)
        if n_sprites < 1 or what_dim < 1:
            raise ValueError(f"SpriteDecoder needs n_sprites >= 1 and what_dim >= 1, got {n_sprites} and {what_dim}")
        if state_dim < need:
            raise ValueError(
                f"SpriteDecoder: {n_sprites} sprites of 2 position + {what_dim} content components need a state of at "
                f"least {need} components, got state_dim={state_dim}: raise state_dim or lower what_dim"
            )
        self.state_dim, self.n_sprites, self.what_dim = int(state_dim), int(n_sprites), int(what_dim)
        self.sprite_size = int(sprite_size)
        self.sprite = ConvDecoder(
            self.what_dim,
            preset=None,
            stem_channels=stem_channels,
            layers=[list(layer) for layer in layers],
            image_size=self.sprite_size,
            backend=backend,
        )
        angles = torch.arange(self.n_sprites, dtype=torch.float32) * (2 * math.pi / self.n_sprites) + math.pi / 4
        offsets = offset_radius * torch.stack([torch.sin(angles), torch.cos(angles)], dim=-1)
        self.register_buffer("offsets", offsets if self.n_sprites > 1 else torch.zeros(1, 2), persistent=False)
        if not 0.0 < background < 1.0:
            raise ValueError(f"SpriteDecoder background must lie in (0, 1), got {background}")
        self.background = nn.Parameter(torch.logit(torch.tensor(float(background))))
        self.image_size: int | None = None
        if image_size is not None:
            self._set_image_size(int(image_size))

    def _set_image_size(self, image_size: int) -> None:
        if image_size < self.sprite_size:
            raise ValueError(
                f"SpriteDecoder: sprites of {self.sprite_size} px do not fit in {image_size} px frames: lower "
                "sprite_size to at most the image size"
            )
        self.image_size = image_size

    def adopt_measurement_shape(self, obs_shape: Sequence[int]) -> dict[str, int]:
        """Draw the data's frame size (called by the model's ``setup``); returns what it fixed, for the config."""
        if len(obs_shape) != 3 or obs_shape[-1] != obs_shape[-2] or obs_shape[0] != self.sprite.out_shape[0]:
            raise ValueError(
                f"SpriteDecoder draws square {self.sprite.out_shape[0]}-channel frames, but the measurements have "
                f"shape {list(obs_shape)}: use it on image data, with the layers' last channels the images'"
            )
        if self.image_size is not None:
            return {}  # a given size stays; a mismatch is the model's shape check to report
        self._set_image_size(int(obs_shape[-1]))
        return {"image_size": self.image_size}

    def placement(self, where: torch.Tensor) -> torch.Tensor:
        """``[M, 2]`` positions (with the offsets added) -> ``[M, 2, 3]`` the affine maps from frame coordinates to
        sprite coordinates (``F.affine_grid``'s ``theta``; normalised coordinates, ``x`` the column first)."""
        h, s = float(self.image_size), float(self.sprite_size)
        scale = h / s
        centre = where * ((h - s) / h)  # [-1, 1] -> the centre's normalised frame coordinates, sprite inside
        theta = where.new_zeros(where.shape[0], 2, 3)
        theta[:, 0, 0] = scale
        theta[:, 1, 1] = scale
        theta[:, 0, 2] = -centre[:, 1] * scale  # x: the column
        theta[:, 1, 2] = -centre[:, 0] * scale  # y: the row
        return theta

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.image_size is None:
            raise RuntimeError("SpriteDecoder has no image_size yet: give image_size, or let the model set it")
        lead = x.shape[:-1]
        slots = x.reshape(-1, self.state_dim)[:, : self.n_sprites * (2 + self.what_dim)]
        slots = slots.reshape(-1, self.n_sprites, 2 + self.what_dim)
        n = slots.shape[0]
        where = (slots[..., :2] + self.offsets.to(slots.dtype)).reshape(n * self.n_sprites, 2)
        sprites = self.sprite(slots[..., 2:].reshape(n * self.n_sprites, self.what_dim))  # [n S, C, s, s]
        c = sprites.shape[1]
        grid = F.affine_grid(self.placement(where), [n * self.n_sprites, c, self.image_size, self.image_size], False)
        placed = F.grid_sample(sprites, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        frames = placed.view(n, self.n_sprites, c, self.image_size, self.image_size).amax(dim=1)
        frames = torch.maximum(frames, torch.sigmoid(self.background).to(frames.dtype))
        return frames.reshape(*lead, c, self.image_size, self.image_size)
