"""SpriteDecoder: sprites pasted where the state says, composed by the maximum, checked against a naive paste."""

import numpy as np
import pytest
import torch

from ssm_ms.nets import SpriteDecoder


def _decoder(**kw) -> SpriteDecoder:
    torch.manual_seed(0)
    args = dict(state_dim=20, n_sprites=2, what_dim=6, sprite_size=12, image_size=30, stem_channels=8,
                layers=[[8, 3, 2], [1, 4, 2]], backend="plain")  # fmt: skip
    args.update(kw)
    return SpriteDecoder(**args)


def _naive(sprites: np.ndarray, corners: list[tuple[int, int]], size: int, background: float) -> np.ndarray:
    """Paste each sprite at its integer top-left corner into a uniform frame, composed by max (as moving_mnist.render)."""
    frame = np.full((size, size), background, dtype=np.float64)
    s = sprites.shape[-1]
    for sprite, (r, c) in zip(sprites, corners):
        r0, c0 = max(r, 0), max(c, 0)
        r1, c1 = min(r + s, size), min(c + s, size)
        window = frame[r0:r1, c0:c1]
        np.maximum(window, sprite[r0 - r : r1 - r, c0 - c : c1 - c], out=window)
    return frame


@pytest.mark.parametrize("corners", [[(0, 0), (18, 18)], [(3, 11), (7, 2)], [(18, 0), (5, 5)], [(-4, 9), (20, 25)]])
def test_sprites_land_at_integer_corners_as_a_naive_paste(corners):
    dec = _decoder()
    h, s = 30, 12
    x = torch.randn(1, 20, dtype=torch.float64)
    dec = dec.double()
    for k, (r, c) in enumerate(corners):
        # corner r <- position w: r = (w + offset + 1) (H - S) / 2
        target = torch.tensor([2.0 * r / (h - s) - 1.0, 2.0 * c / (h - s) - 1.0], dtype=torch.float64)
        x[0, k * 8 : k * 8 + 2] = target - dec.offsets[k].double()
    with torch.no_grad():
        frame = dec(x)[0, 0].numpy()
        sprites = dec.sprite(x[0, :16].view(2, 8)[:, 2:])[:, 0].numpy()
    np.testing.assert_allclose(frame, _naive(sprites, corners, h, 0.01), atol=1e-9)


def test_free_components_are_not_drawn_and_lead_dimensions_are_kept():
    dec = _decoder()
    x = torch.randn(3, 5, 20)
    y = x.clone()
    y[..., 16:] = torch.randn(3, 5, 4)  # components after the two sprites' 16
    with torch.no_grad():
        a, b = dec(x), dec(y)
    assert a.shape == (3, 5, 1, 30, 30)
    torch.testing.assert_close(a, b)


def test_a_half_pixel_move_is_the_mean_of_the_two_neighbouring_pastes():
    dec = _decoder(n_sprites=1, state_dim=8, offset_radius=0.0, background=1e-12).double()
    x = torch.zeros(3, 8, dtype=torch.float64)
    x[:, 2:] = torch.randn(6, dtype=torch.float64)
    step = 2.0 / (30 - 12)  # one pixel in w
    x[1, 1] = 0.5 * step
    x[2, 1] = step
    with torch.no_grad():
        f = dec(x)[:, 0]
    torch.testing.assert_close(f[1], 0.5 * (f[0] + f[2]))


def test_position_gradients_move_a_sprite_towards_its_target():
    """One gradient step on the positions alone lowers the squared error to a frame with the sprite moved by 2 px."""
    dec = _decoder(n_sprites=1, state_dim=8, offset_radius=0.0)
    code = torch.randn(1, 6)
    step = 2.0 / (30 - 12)
    with torch.no_grad():
        target = dec(torch.cat([torch.tensor([[2 * step, -2 * step]]), code], dim=1))
    where = torch.zeros(1, 2, requires_grad=True)
    loss = ((dec(torch.cat([where, code], dim=1)) - target) ** 2).sum()
    loss.backward()
    assert where.grad[0, 0] < 0 and where.grad[0, 1] > 0  # down the rows, left along the columns


def test_a_state_too_small_or_data_of_another_shape_is_refused_with_the_fix():
    with pytest.raises(ValueError, match="raise state_dim or lower what_dim"):
        SpriteDecoder(state_dim=10, n_sprites=2, what_dim=6)
    dec = _decoder(image_size=None)
    with pytest.raises(ValueError, match="square 1-channel frames"):
        dec.adopt_measurement_shape((3,))
    assert dec.adopt_measurement_shape((1, 40, 40)) == {"image_size": 40}
    assert dec(torch.zeros(2, 20)).shape == (2, 1, 40, 40)
    with pytest.raises(ValueError, match=r"background must lie in \(0, 1\)"):
        _decoder(background=0.0)
    with pytest.raises(ValueError, match="lower sprite_size"):
        _decoder(image_size=None).adopt_measurement_shape((1, 10, 10))


def test_results_tables_name_the_sprite_decoder_beside_f():
    from types import SimpleNamespace

    from ssm_ms.inference.ssm_forecaster import SSMForecaster
    from ssm_ms.nets import ConvDecoder, LocallyLinearTransition

    def label(g, name="encoder"):
        ssm = SimpleNamespace(f=LocallyLinearTransition(20, 2, 8), g=g)
        forecaster = SimpleNamespace(ssm=ssm, method_name=name, method_kind="encoder", ssm_checkpoint="x.ckpt")
        return SSMForecaster.describe(forecaster)["label"]

    assert label(_decoder()) == "SSM-LL with a sprite decoder + CNN-LSTM encoder"
    assert label(ConvDecoder(20)) == "SSM-LL + CNN-LSTM encoder"  # the paper's g is not named
    # a row of its own beside the default one (another SSM of the experiment) is told apart by its name
    assert label(ConvDecoder(20), "encoder_ssm1000") == "SSM-LL + CNN-LSTM encoder (encoder_ssm1000)"
