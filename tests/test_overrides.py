"""One command-line option changes the image size, one file the number of measured channels: the
decoder is drawn at the size the data option names (checked against the transposed-convolution output
formula), a size it cannot draw is one message, and a linear read-out takes its size from the data."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf

from ssm_ms.module import MultipleShootingModule
from ssm_ms.nets import ConvDecoder, LinearReadout
from ssm_ms.nets.decoder import PRESETS
from tests.test_cli import CPU, ROOT, fit_tiny, outputs, run


def conv_transpose_out(
    size: int, kernel: int, stride: int, padding: int = 0, dilation: int = 1, output_padding: int = 0
) -> int:
    """PyTorch's documented ConvTranspose2d output size."""
    return (size - 1) * stride - 2 * padding + dilation * (kernel - 1) + output_padding + 1


def expected_stem(image_size: int, layers) -> tuple[int, int]:
    """The smallest stem whose stack draws at least image_size, and what it draws (searched, not solved)."""
    for stem in range(1, 200):
        size = stem
        for _, kernel, stride in layers:
            size = conv_transpose_out(size, kernel, stride)
        if size >= image_size:
            return stem, size
    raise AssertionError("no stem found")


def reference_decode(g: ConvDecoder, x: torch.Tensor, image_size: int, drawn: int) -> torch.Tensor:
    """The decoder's layers applied one by one with torch.nn.functional, then the centre crop."""
    h = F.relu(F.linear(x, g.stem[0].weight, g.stem[0].bias)).view(len(x), *g.stem_shape)
    for layer in g.deconv:
        if isinstance(layer, torch.nn.ConvTranspose2d):
            h = F.conv_transpose2d(h, layer.weight, layer.bias, stride=layer.stride)
        elif isinstance(layer, torch.nn.LayerNorm):
            h = F.layer_norm(h, layer.normalized_shape, layer.weight, layer.bias, layer.eps)
        elif isinstance(layer, torch.nn.ReLU):
            h = F.relu(h)
        else:
            h = torch.sigmoid(h)
    assert h.shape[-1] == drawn
    start = (drawn - image_size) // 2
    return h[..., start : start + image_size, start : start + image_size]


@pytest.mark.parametrize(
    "preset, image_size",
    [("pendulum", 24), ("pendulum", 32), ("pendulum", 33), ("quad", 24), ("quad", 40), ("mnist", 32), ("mnist", 50)],
)
def test_decoder_at_a_new_size_against_the_output_formula(preset, image_size):
    torch.manual_seed(0)
    channels = {"mnist": 24}.get(preset)  # a narrower mnist stem keeps the test small
    g = ConvDecoder(3, preset, stem_channels=channels, image_size=image_size).double()
    stem, drawn = expected_stem(image_size, PRESETS[preset][2])
    assert g.stem_shape[1:] == (stem, stem)
    assert 0 <= drawn - image_size < int(np.prod([stride for _, _, stride in PRESETS[preset][2]]))  # a small margin
    with torch.no_grad():  # non-trivial LayerNorm parameters
        for p in g.parameters():
            p.add_(0.1 * torch.randn_like(p))
    x = torch.randn(4, 3, dtype=torch.float64)
    out = g(x)
    assert out.shape == (4, 1, image_size, image_size)
    torch.testing.assert_close(out, reference_decode(g, x, image_size, drawn))
    if (preset, image_size) in (("pendulum", 24), ("quad", 48), ("mnist", 64)):
        assert drawn == image_size  # the paper's sizes: nothing cropped


def test_decoder_refuses_a_size_it_cannot_draw():
    with pytest.raises(
        ValueError,
        match=r"'quad' preset cannot draw 16x16 .* smallest it draws is 24x24 "
        r"\(exactly 24, 36, 48, 60, .*at least 24",
    ):
        ConvDecoder(3, "quad", image_size=16)
    with pytest.raises(ValueError, match="give one"):
        ConvDecoder(3, None, stem_channels=4, stem_size=3, layers=[[1, 3, 2]], image_size=9)


def test_image_size_override_fits_one_batch_and_print_config_shows_it(tmp_path, capsys):
    config = CPU / "pendulum.yaml"
    override = [
        "--data.init_args.image_size",
        "32",
        "--data.init_args.n_train",
        "2",
        "--data.init_args.n_test",
        "2",
        "--data.init_args.batch_size",
        "2",
    ]
    with pytest.raises(SystemExit):
        run(tmp_path, "fit", config, *override, "--print_config")
    printed = OmegaConf.create(capsys.readouterr().out)
    assert printed.model.init_args.g.init_args.image_size == 32 and printed.data.init_args.image_size == 32
    cli = fit_tiny(tmp_path, config, *override)
    assert cli.trainer.fit_loop.epoch_loop.batch_progress.total.completed == 1  # one batch trained
    batch = next(iter(cli.datamodule.train_dataloader()))
    assert batch["y"].shape[-2:] == (32, 32)
    with torch.no_grad():
        assert cli.model.g(torch.zeros(2, 10)).shape == (2, 1, 32, 32)
    ssm_ckpt = outputs(tmp_path, config) / "checkpoints" / "last.ckpt"
    model = MultipleShootingModule.load_from_checkpoint(ssm_ckpt)
    assert model.obs_shape() == (1, 32, 32)
    # the encoder stage, given the same option, reads the 32x32 frames
    stage = run(
        tmp_path,
        "fit",
        CPU / "pendulum_encoder.yaml",
        *override,
        "--trainer.max_epochs",
        "1",
        "--trainer.limit_val_batches",
        "0",
        "--model.init_args.ssm_checkpoint",
        str(ssm_ckpt),
        "--model.init_args.results_dir",
        str(tmp_path / "results"),
    )
    assert stage.model.encoder.obs_shape == (1, 32, 32)
    assert stage.trainer.fit_loop.epoch_loop.batch_progress.total.completed == 1


def test_a_size_the_decoder_cannot_draw_is_one_message(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        run(tmp_path, "fit", CPU / "pendulum.yaml", "--data.init_args.image_size", "8")
    err = capsys.readouterr().err
    assert stop.value.code == 1 and "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 2 and lines[0].startswith("error: ConvDecoder") and "at least 12" in lines[0], err


def test_measured_channels_come_from_the_file(tmp_path, capsys):
    rng = np.random.default_rng(0)
    y = rng.standard_normal((10, 20, 3)).astype(np.float32)  # 3 channels; the example file has 2
    np.savez(tmp_path / "three.npz", y=y, y_clean=y)
    config = ROOT / "configs" / "oscillator.yaml"
    args = ["--data.init_args.train_path", str(tmp_path / "three.npz"), "--model.init_args.n_nodes", "2"]
    with pytest.raises(SystemExit):
        run(tmp_path, "fit", config, *args, "--print_config")
    printed = OmegaConf.create(capsys.readouterr().out).model.init_args.g.init_args
    assert printed.out_features is None  # the file's, known once it is read
    cli = run(
        tmp_path,
        "fit",
        config,
        *args,
        "--trainer.max_epochs",
        "1",
        "--trainer.limit_train_batches",
        "1",
        "--trainer.limit_val_batches",
        "0",
    )
    g = cli.model.g
    assert isinstance(g, torch.nn.Linear) and g.weight.shape == (3, 4) and g.bias.shape == (3,)
    assert cli.model.hparams["g"]["init_args"]["out_features"] == 3
    model = MultipleShootingModule.load_from_checkpoint(outputs(tmp_path, config) / "checkpoints" / "last.ckpt")
    torch.testing.assert_close(model.g.weight, g.weight.cpu())


def test_linear_readout_sizes_once_and_refuses_images():
    g = LinearReadout(4, out_features=None)
    assert sum(p.numel() for p in g.parameters()) == 0
    with pytest.raises(ValueError, match="has not seen the data yet"):
        g(torch.zeros(1, 4))
    assert g.adopt_measurement_shape((5,)) == {"out_features": 5}
    assert g(torch.zeros(2, 4)).shape == (2, 5)
    assert LinearReadout(4, 2).adopt_measurement_shape((5,)) == {}  # given sizes stay (the model then says they differ)
    with pytest.raises(ValueError, match="use a ConvDecoder for images"):
        LinearReadout(4).adopt_measurement_shape((1, 8, 8))
