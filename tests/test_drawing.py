"""Forecasting figures of ssm_ms.drawing and the callbacks of ssm_ms.viz, checked against layouts and loops recomputed here."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from lightning.pytorch.loggers import TensorBoardLogger
from PIL import Image
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from ssm_ms.drawing import (
    attractor_figure,
    lorenz_prediction_figure,
    loss_curves_figure,
    prediction_mosaic,
    save_figure,
    save_gif,
    save_png,
    shooting_figure,
)
from ssm_ms.module import MultipleShootingModule
from ssm_ms.nets import LocallyLinearTransition, Projection
from ssm_ms.viz import ShootingPictureLogger, shooting_predictions
from tests.conftest import RotationDataModule, fast_trainer, rotation_model


def lines_by_gid(ax, gid: str):
    return [line for line in ax.get_lines() if line.get_gid() == gid]


# ---------------------------------------------------------------------- prediction_mosaic
@pytest.mark.parametrize("every,n_filter", [(10, 50), (1, 37)])
def test_prediction_mosaic_blocks_and_separator(every, n_filter):
    gen = torch.Generator().manual_seed(0)
    t, c, h, w, pad, sep = 100, 1, 5, 4, 1, 3
    y_true, y_model = torch.rand(t, c, h, w, generator=gen), torch.rand(t, c, h, w, generator=gen)
    out = prediction_mosaic(y_true, y_model, n_filter, every=every, pad=pad, separator=sep, separator_value=0.5)

    expected_cols = [9, 19, 29, 39, 49, 59, 69, 79, 89, 99] if every == 10 else list(range(100))
    k = sum(1 for i in expected_cols if i < n_filter)  # filtering columns
    assert out.shape == (c, pad + 2 * (h + pad), pad + len(expected_cols) * (w + pad) + sep + pad)
    lefts = []
    for j, frame in enumerate(expected_cols):
        left = pad + j * (w + pad) + (sep + pad if j >= k else 0)
        lefts.append(left)
        assert torch.equal(out[:, pad : pad + h, left : left + w], y_true[frame])
        assert torch.equal(out[:, 2 * pad + h : 2 * pad + 2 * h, left : left + w], y_model[frame])
    # the bar lies after the last filtering column and before the first prediction column
    bar = (out[0] == 0.5).all(dim=0).nonzero().flatten().tolist()
    assert bar == list(range(pad + k * (w + pad), pad + k * (w + pad) + sep))
    assert lefts[k - 1] + w < bar[0] and bar[-1] < lefts[k]


def test_prediction_mosaic_batch_rows_and_no_bar_when_all_predicted():
    gen = torch.Generator().manual_seed(1)
    b, t, c, h, w, pad, sep = 3, 20, 3, 4, 6, 2, 5
    y_true, y_model = torch.rand(b, t, c, h, w, generator=gen), torch.rand(b, t, c, h, w, generator=gen)
    out = prediction_mosaic(y_true, y_model, n_filter=0, every=5, max_rows=2, pad=pad, separator=sep)
    cols = [4, 9, 14, 19]
    assert out.shape == (c, pad + 4 * (h + pad) + sep, pad + len(cols) * (w + pad))  # no bar: no shift
    for s in range(2):
        for r, ys in enumerate((y_true, y_model)):
            top = pad + (2 * s + r) * (h + pad) + s * sep
            for j, frame in enumerate(cols):
                left = pad + j * (w + pad)
                assert torch.equal(out[:, top : top + h, left : left + w], ys[s, frame])


def test_prediction_mosaic_bad_input():
    y = torch.rand(10, 1, 4, 4)
    with pytest.raises(ValueError, match="every"):
        prediction_mosaic(y, y, 5, every=11)
    with pytest.raises(ValueError, match="n_filter"):
        prediction_mosaic(y, y, 11)
    with pytest.raises(ValueError, match="same shape"):
        prediction_mosaic(y, y[:5], 3)


# ---------------------------------------------------------------------- files
def test_save_png_and_figure_create_folders(tmp_path):
    img = torch.rand(3, 5, 7)
    path = save_png(img, tmp_path / "a" / "b" / "img.png")
    back = np.asarray(Image.open(path)).astype(np.float64)
    assert back.shape == (5, 7, 3)
    np.testing.assert_allclose(back, np.round(img.permute(1, 2, 0).numpy() * 255), atol=0.51)
    fig = attractor_figure(torch.randn(50, 3))
    assert save_figure(fig, tmp_path / "c" / "fig.png").stat().st_size > 0


def test_save_gif_frames_size_duration_and_pixels(tmp_path):
    gen = torch.Generator().manual_seed(2)
    t, h, w, scale, margin, label = 5, 6, 7, 3, 4, 14
    y_true, y_model = torch.rand(t, 1, h, w, generator=gen), torch.rand(t, 1, h, w, generator=gen)
    path = save_gif(
        y_true, y_model, 3, tmp_path / "gif" / "seq.gif", fps=10, scale=scale, margin=margin, label_height=label
    )
    with Image.open(path) as im:
        assert im.n_frames == t
        assert im.size == (3 * margin + 2 * w * scale, 2 * label + h * scale)
        assert im.info["duration"] == 100
        first = np.asarray(im.convert("L")).astype(np.float64)
        im.seek(t - 1)
        last = np.asarray(im.convert("L")).astype(np.float64)
    truth = first[label : label + h * scale : scale, margin : margin + w * scale : scale]
    np.testing.assert_allclose(truth, np.round(y_true[0, 0].numpy() * 255), atol=1)
    x_model = 2 * margin + w * scale
    # nearest upscaling: every pixel of a block equals its corner
    block = last[label : label + h * scale, x_model : x_model + w * scale]
    np.testing.assert_allclose(block, np.kron(np.round(y_model[-1, 0].numpy() * 255), np.ones((scale, scale))), atol=1)


def test_save_gif_rgb_writes_every_frame(tmp_path):
    y = torch.rand(4, 3, 5, 5)
    with Image.open(save_gif(y, y.flip(0), 2, tmp_path / "rgb.gif", fps=20, scale=2)) as im:
        assert im.n_frames == 4 and im.info["duration"] == 50


# ---------------------------------------------------------------------- Lorenz figures
@pytest.mark.parametrize("window", [None, 30])
def test_lorenz_prediction_figure(window):
    gen = torch.Generator().manual_seed(3)
    t, n_filter, dt = 200, 120, 0.01
    states, true = torch.randn(t, 3, generator=gen), torch.randn(t, 3, generator=gen)
    y_clean = true[:, :1]
    y = y_clean + 0.1 * torch.randn(t, 1, generator=gen)
    fig = lorenz_prediction_figure(y, y_clean[:, 0], states, n_filter, true_state=true, dt=dt, window=window)
    lo, hi = (0, t) if window is None else (n_filter - window, n_filter + window)
    time = np.arange(lo, hi) * dt
    main = [ax for ax in fig.axes if ax.get_label() != "true-state axis"]
    twins = [ax for ax in fig.axes if ax not in main]
    assert len(main) == 3 and len(twins) == 2  # the true unmeasured components on their own right axes
    for i, twin in zip((1, 2), twins):
        (true_line,) = lines_by_gid(twin, "true")
        np.testing.assert_array_equal(true_line.get_ydata(), true[lo:hi, i].double().numpy())
    for i, ax in enumerate(main):
        (start,) = lines_by_gid(ax, "prediction_start")
        np.testing.assert_allclose(start.get_xdata(), [n_filter * dt] * 2)
        (model,) = lines_by_gid(ax, "model")
        np.testing.assert_allclose(model.get_xdata(), time)
        np.testing.assert_array_equal(model.get_ydata(), states[lo:hi, i].double().numpy())
        assert not lines_by_gid(ax, "true")
    (meas,) = lines_by_gid(main[0], "measurement")
    np.testing.assert_array_equal(meas.get_ydata(), y[lo:hi, 0].double().numpy())
    (clean,) = lines_by_gid(main[0], "noiseless")
    np.testing.assert_array_equal(clean.get_ydata(), y_clean[lo:hi, 0].double().numpy())


def test_attractor_figure():
    states = torch.randn(300, 3, dtype=torch.float64)
    fig = attractor_figure(states, title="f from a node")
    (ax,) = fig.axes
    assert ax.name == "3d"
    (line,) = ax.get_lines()
    xs, ys, zs = line.get_data_3d()
    np.testing.assert_array_equal(np.stack([xs, ys, zs], 1), states.numpy())
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        attractor_figure(torch.randn(10, 2))
    # the true system beside it: one line per run, drawn from the data given
    true = torch.randn(2, 40, 3, dtype=torch.float64)
    fig = attractor_figure(states, true_states=true)
    model_ax, true_ax = fig.axes
    assert [ln.get_gid() for ln in model_ax.get_lines()] == ["attractor"]
    lines = true_ax.get_lines()
    assert [ln.get_gid() for ln in lines] == ["true_attractor"] * 2
    for line, run in zip(lines, true):
        np.testing.assert_array_equal(np.stack(line.get_data_3d(), 1), run.numpy())


# ---------------------------------------------------------------------- loss curves
def test_loss_curves_figure_reads_back_scalars(tmp_path):
    from torch.utils.tensorboard import SummaryWriter

    written = {
        "train/fit": [1.0 / (s + 1) for s in range(12)],
        "train/gap": [0.5 * 0.8**s for s in range(12)],
        "alpha": [1.0 if s < 6 else 10.0 for s in range(12)],
        "lr": [1e-3 if s < 6 else 1e-4 for s in range(12)],
    }
    writer = SummaryWriter(str(tmp_path / "version_0"))
    for step in range(12):
        for tag, values in written.items():
            writer.add_scalar(tag, values[step], step)
    writer.close()
    fig = loss_curves_figure(tmp_path)
    lines = {line.get_gid(): line for ax in fig.axes for line in ax.get_lines()}
    assert set(lines) == set(written)
    for tag, values in written.items():
        np.testing.assert_array_equal(lines[tag].get_xdata(), np.arange(12))
        np.testing.assert_allclose(lines[tag].get_ydata(), values, rtol=1e-6)  # event files hold float32
    assert lines["train/fit"].axes.get_yscale() == "log"


def test_loss_curves_figure_errors(tmp_path):
    from torch.utils.tensorboard import SummaryWriter

    with pytest.raises(FileNotFoundError, match="no TensorBoard event file"):
        loss_curves_figure(tmp_path)
    writer = SummaryWriter(str(tmp_path))
    writer.add_scalar("something/else", 1.0, 0)
    writer.close()
    with pytest.raises(ValueError, match="something/else"):
        loss_curves_figure(tmp_path)


# ---------------------------------------------------------------------- multiple shooting
def test_shooting_predictions_against_loop_and_figure():
    torch.manual_seed(4)
    d, m, n, n_traj = 3, 4, 3, 5
    f = LocallyLinearTransition(d, n_matrices=4, hidden=8)
    model = MultipleShootingModule(f, Projection([0, 2]), state_dim=d, num_trajectories=n_traj, n_nodes=m).double()
    with torch.no_grad():
        model.nodes.weight.normal_()
    index = torch.tensor([3, 0])
    y = torch.zeros(2, m * n, 2)
    out = shooting_predictions(model, index, y=y)
    assert out.shape == (2, m, n + 1, 2)
    assert torch.equal(out, shooting_predictions(model, index, seq_len=m * n))
    with torch.no_grad():
        for b, j in enumerate(index.tolist()):
            table = model.nodes.weight[j]
            for i in range(m):
                x = table[i * d : (i + 1) * d]
                for k in range(n + 1):
                    torch.testing.assert_close(out[b, i, k], x[[0, 2]], rtol=1e-12, atol=1e-12)
                    x = f(x.unsqueeze(0)).squeeze(0)
    with pytest.raises(ValueError, match="multiple"):
        shooting_predictions(model, index, seq_len=13)

    fig = shooting_figure(y[0], out[0], n, title="t")
    assert len(fig.axes) == 2
    for c, ax in enumerate(fig.axes):
        for i in range(m):
            (line,) = lines_by_gid(ax, f"node{i}")
            np.testing.assert_array_equal(line.get_xdata(), list(range(i * n, (i + 1) * n + 1)))
            np.testing.assert_array_equal(line.get_ydata(), out[0, i, :, c].numpy())
            (dot,) = lines_by_gid(ax, f"node{i}-start")
            assert list(dot.get_xdata()) == [i * n] and list(dot.get_ydata()) == [out[0, i, 0, c].item()]
        assert len([line for line in ax.get_lines() if (line.get_gid() or "").endswith(tuple("0123456789"))]) == m
    with pytest.raises(ValueError, match="n=2"):
        shooting_figure(y[0], out[0], 2)


def test_shooting_picture_logger_writes_before_and_after(tmp_path):
    dm = RotationDataModule(data_dir=str(tmp_path / "data"), batch_size=4, val_trajectories=2)
    logger = TensorBoardLogger(str(tmp_path / "logs"))
    trainer = fast_trainer(tmp_path, 1, callbacks=[ShootingPictureLogger(n_trajectories=2)], logger=logger)
    trainer.fit(rotation_model(), datamodule=dm)
    acc = EventAccumulator(logger.log_dir)
    acc.Reload()
    assert {"shooting/before", "shooting/after"} <= set(acc.Tags()["images"])
    before, after = acc.Images("shooting/before")[0], acc.Images("shooting/after")[0]
    assert before.step == 0 and after.step == trainer.global_step > 0
    assert before.height == after.height and before.height > before.width / 2  # two figures stacked


def test_shooting_picture_logger_is_silent_without_tensorboard(tmp_path):
    dm = RotationDataModule(data_dir=str(tmp_path / "data"), batch_size=4, val_trajectories=2)
    trainer = fast_trainer(tmp_path, 1, callbacks=[ShootingPictureLogger()], limit_train_batches=1)
    trainer.fit(rotation_model(), datamodule=dm)  # logger=False: nothing to write, nothing fails


def test_loss_curves_merge_resumed_runs_later_write_wins(tmp_path):
    from torch.utils.tensorboard import SummaryWriter

    for run, (steps, value, t0) in enumerate([(range(0, 6), 1.0, 1000.0), (range(3, 9), 2.0, 2000.0)]):
        writer = SummaryWriter(str(tmp_path / f"version_{run}"))
        for s in steps:
            writer.add_scalar("train/fit", value, s, walltime=t0 + s)
        writer.close()
    (line,) = [ln for ax in loss_curves_figure(tmp_path).axes for ln in ax.get_lines() if ln.get_gid() == "train/fit"]
    np.testing.assert_array_equal(line.get_xdata(), np.arange(9))
    np.testing.assert_array_equal(line.get_ydata(), [1.0, 1.0, 1.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0])


def test_save_png_scales_by_pixel_repetition(tmp_path):
    img = torch.rand(1, 3, 5)
    path = save_png(img, tmp_path / "a.png", scale=3)
    arr = np.asarray(Image.open(path)).astype(np.float64) / 255
    assert arr.shape == (9, 15)
    expected = np.kron(img[0].numpy(), np.ones((3, 3)))  # every pixel a 3x3 block
    assert np.abs(arr - expected).max() <= 0.5 / 255 + 1e-9
