"""Amortised shooting nodes (``node_encoder``): each node is the encoder's reading of the ``history`` samples before it.
Checked against loops written here: the nodes, the loss, the validation rollout, the state of a new recording; the
settings of free nodes refused beside it, in one message each; a model built in Python saved and loaded whole."""

from __future__ import annotations

import pytest
import torch

from ssm_ms.checkpointing import holds_ssm
from ssm_ms.inference.simulation import initial_state, simulate_recording
from ssm_ms.module import MultipleShootingModule
from ssm_ms.nets import ConvDecoder, HistoryEncoder, LinearReadout, LocallyLinearTransition
from ssm_ms.training.checks import check_data
from ssm_ms.training.shooting import gap_term, multiple_shooting_loss

H, M, N, D = 5, 3, 4, 3  # history, nodes, piece length, state


def model(input_dim: int = 1, **kwargs) -> MultipleShootingModule:
    torch.manual_seed(0)
    f = LocallyLinearTransition(D, n_matrices=2, hidden=8, input_dim=input_dim)
    enc = HistoryEncoder(D, obs_dim=2, input_dim=input_dim, history=H, hidden=[6])
    return MultipleShootingModule(f, LinearReadout(D, 2), n_nodes=M, node_encoder=enc, **kwargs)


def batch(b: int = 2, inputs: bool = True) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(1)
    out = {"y": torch.randn(b, H + M * N, 2, generator=g), "index": torch.arange(b)}
    if inputs:
        out["u"] = torch.randn(b, H + M * N, 1, generator=g)
    return out


def test_history_encoder_is_a_linear_map_plus_an_mlp_of_the_flat_history():
    enc = HistoryEncoder(D, obs_dim=2, input_dim=1, history=H, hidden=[6])
    y, u = torch.randn(4, H, 2), torch.randn(4, H, 1)
    flat = torch.cat([y.reshape(4, -1), u.reshape(4, -1)], 1)
    lin, mlp = enc.linear, enc.mlp
    expected = flat @ lin.weight.T + lin.bias + mlp[2](torch.tanh(mlp[0](flat)))
    torch.testing.assert_close(enc(y, u), expected)


def test_images_are_read_frame_by_frame_by_the_cnn_then_as_a_flat_history():
    torch.manual_seed(0)
    enc = HistoryEncoder(D, obs_dim=[1, 24, 24], input_dim=1, history=H, hidden=[6], frames="pendulum")
    y, u = torch.rand(4, H, 1, 24, 24), torch.randn(4, H, 1)
    features = torch.stack([enc.frames.cnn(y[:, k]).flatten(1) for k in range(H)], 1)  # each frame on its own
    flat = torch.cat([features.reshape(4, -1), u.reshape(4, -1)], 1)
    lin, mlp = enc.linear, enc.mlp
    expected = flat @ lin.weight.T + lin.bias + mlp[2](torch.tanh(mlp[0](flat)))
    torch.testing.assert_close(enc(y, u), expected)
    f = LocallyLinearTransition(D, n_matrices=2, hidden=8, input_dim=1)
    m = MultipleShootingModule(f, ConvDecoder(D, preset="pendulum", image_size=24), n_nodes=M, node_encoder=enc)
    check_data(m, H + M * N, (1, 24, 24))  # accepted
    m = MultipleShootingModule(f, ConvDecoder(D, preset="pendulum", image_size=28), n_nodes=M, node_encoder=enc)
    with pytest.raises(ValueError, match=r"reads measurements of shape \(1, 24, 24\), the data have \(1, 28, 28\)"):
        check_data(m, H + M * N, (1, 28, 28))
    with pytest.raises(ValueError, match="need the per-frame CNN: set frames"):
        HistoryEncoder(D, obs_dim=[1, 24, 24], history=H)
    with pytest.raises(ValueError, match=r"an int \(vector components\) or \[C, H, W\] \(images\), got \[4, 5\]"):
        HistoryEncoder(D, obs_dim=[4, 5], history=H)
    with pytest.raises(ValueError, match="take no per-frame CNN: remove frames"):
        HistoryEncoder(D, obs_dim=2, history=H, frames="pendulum")


def test_nodes_read_the_history_before_each_node_and_the_loss_is_the_naive_loop():
    m, b = model(), batch()
    nodes, y, u = m.batch_nodes(b)
    assert y.shape[1] == u.shape[1] == M * N
    fit_terms, gaps = [], []
    for k in range(2):
        states = []
        for i in range(M):  # node i at window time H + i N reads samples i N .. i N + H - 1
            s = m.node_encoder(b["y"][k : k + 1, i * N : i * N + H], b["u"][k : k + 1, i * N : i * N + H])
            torch.testing.assert_close(nodes[k, i], s[0])
            states.append(s)
        for i in range(M):
            x = states[i]
            for j in range(N):
                t = H + i * N + j
                fit_terms.append((m.g(x) - b["y"][k : k + 1, t]).pow(2))
                x = m.f(x, b["u"][k : k + 1, t])
            if i + 1 < M:
                gaps.append((states[i + 1] - x).pow(2))
    fit, gap = m.shooting_loss(b)
    torch.testing.assert_close(fit, torch.cat(fit_terms).mean())
    torch.testing.assert_close(gap, torch.cat(gaps).mean())


@pytest.mark.filterwarnings("ignore:You are trying to `self.log\\(\\)`")
def test_training_records_its_states_and_validation_rolls_out_from_the_first_node():
    m = model()
    b = batch(b=4)
    m._record_states(m.batch_nodes(b)[0])
    assert int(m.states_seen) == 4 * M and m.training_states().shape == (4 * M, D)
    with torch.no_grad():
        x0 = m.node_encoder(b["y"][:, :H], b["u"][:, :H])
        x, expected = x0, []
        for t in range(H, H + M * N):
            expected.append(m.g(x))
            x = m.f(x, b["u"][:, t])
        out = m.validation_step(b, 0)
    torch.testing.assert_close(out["y_hat"], torch.stack(expected, 1))
    torch.testing.assert_close(out["y"], b["y"][:, H:])


def test_a_new_recording_s_state_is_the_encoder_s_reading_of_its_last_history_samples():
    m = model().eval()
    y, u = torch.randn(1, 30, 2), torch.randn(1, 30, 1)
    with torch.no_grad():
        x, estimates = initial_state(m, y[:, :12], u)
        torch.testing.assert_close(x, m.node_encoder(y[:, 12 - H : 12], u[:, 12 - H : 12]))
        assert torch.isnan(estimates).all() and estimates.shape == (1, 12, 2)
        out, where = simulate_recording(m, y, u, n_init=12)
        xs, sim = x, []
        for t in range(12, 30):
            sim.append(m.g(xs))
            xs = m.f(xs, u[:, t])
    torch.testing.assert_close(out[:, 12:], torch.stack(sim, 1))
    assert int(where[0]) == -1
    with pytest.raises(ValueError, match="only 3 are given to estimate it from: give at least 5"):
        initial_state(m, y[:, :3], u)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"node_optimizer": "sparse"}, "node_optimizer: sparse set the free shooting nodes"),
        ({"constraint": "augmented_lagrangian"}, "constraint: augmented_lagrangian set the free"),
        ({"node_init_map": {0: 0}}, "node_init_map set the free shooting nodes"),
    ],
)
def test_free_node_settings_beside_a_node_encoder_get_one_message(kwargs, match):
    with pytest.raises(ValueError, match=match):
        model(**kwargs)


def test_windows_that_do_not_hold_history_and_pieces_get_one_message():
    m = model()
    with pytest.raises(ValueError, match=r"T=18 less the node encoder's history of 5 = 13 is not divisible"):
        check_data(m, 18, (2,))
    with pytest.raises(ValueError, match="leaves no sample to shoot over"):
        check_data(m, 6, (2,))
    f = LocallyLinearTransition(D, n_matrices=2, hidden=8, input_dim=1)
    three = MultipleShootingModule(f, LinearReadout(D, 3), n_nodes=M, node_encoder=HistoryEncoder(D, 2, 1, H))
    with pytest.raises(ValueError, match=r"reads measurements of shape \(2,\), the data have \(3,\)"):
        check_data(three, H + M * N, (3,))
    with pytest.raises(ValueError, match="reads 0 inputs per sample but f takes 1"):
        f = LocallyLinearTransition(D, n_matrices=2, hidden=8, input_dim=1)
        MultipleShootingModule(f, LinearReadout(D, 2), node_encoder=HistoryEncoder(D, 2, history=H))
    with pytest.raises(ValueError, match="come from its node encoder"):
        m.node_states(torch.arange(2))


def test_a_model_built_in_python_saves_and_loads_its_node_encoder(tmp_path):
    import lightning.pytorch as pl

    from datamodules.recordings import Recordings

    torch.manual_seed(0)
    y, u = torch.randn(200, 2), torch.randn(200, 1)
    data = Recordings(y=y, u=u, window=H + M * N, stride=1, batch_size=32)
    m = model()
    trainer = pl.Trainer(
        max_epochs=1, logger=False, enable_progress_bar=False, enable_model_summary=False, default_root_dir=tmp_path
    )
    trainer.fit(m, data)
    path = tmp_path / "amortised.ckpt"
    trainer.save_checkpoint(path)
    saved = torch.load(path, weights_only=False)
    assert holds_ssm(saved) and "nodes.weight" not in saved["state_dict"]
    loaded = MultipleShootingModule.load_from_checkpoint(path, weights_only=False).eval()
    b = batch(inputs=True)
    with torch.no_grad():
        torch.testing.assert_close(loaded.batch_nodes(b)[0], m.eval().batch_nodes(b)[0])
    torch.testing.assert_close(loaded.training_states(), m.training_states())


def test_a_gap_scaled_by_the_node_variance_is_the_naive_ratio_and_shrinking_states_cannot_lower_it():
    m, b = model(gap_scale="node_variance"), batch(b=3)
    nodes = m.batch_nodes(b)[0]
    fit, gap = m.shooting_loss(b)
    # naive: every gap element over its coordinate's population variance over the batch's 3 x M nodes
    with torch.no_grad():
        flat = nodes.reshape(-1, D)
        var = [sum((float(v) - float(flat[:, j].mean())) ** 2 for v in flat[:, j]) / len(flat) for j in range(D)]
        terms = []
        for k in range(3):
            for i in range(M - 1):
                x = nodes[k : k + 1, i]
                for j in range(N):
                    x = m.f(x, b["u"][k : k + 1, H + i * N + j])
                terms += [float(nodes[k, i + 1, c] - x[0, c]) ** 2 / var[c] for c in range(D)]
    assert gap.item() == pytest.approx(sum(terms) / len(terms), rel=1e-5)
    # states mapped by x -> c x + e (f and g conjugated, so fits and gaps are those of the same model): the absolute
    # gap scales by c^2, the scaled one is unchanged
    c, e = 1e-2, torch.tensor([0.3, -0.2, 0.1])
    y, u = m.batch_nodes(b)[1:]
    small = nodes.detach() * c + e

    def f_small(x, uu):
        return m.f((x - e) / c, uu) * c + e

    def g_small(x):
        return m.g((x - e) / c)

    fit_s, gap_s = multiple_shooting_loss(f_small, g_small, small, y, u=u, gap_scale="node_variance")
    _, gap_abs_s = multiple_shooting_loss(f_small, g_small, small, y, u=u)
    _, gap_abs = model().shooting_loss(b)
    torch.testing.assert_close(fit_s, fit)
    assert gap_s.item() == pytest.approx(gap.item(), rel=1e-4)
    assert gap_abs_s.item() == pytest.approx(c**2 * gap_abs.item(), rel=1e-4)


def test_a_gap_scaled_by_the_node_variance_needs_amortised_nodes():
    f = LocallyLinearTransition(D, n_matrices=2, hidden=8)
    with pytest.raises(ValueError, match="free nodes all start at zero"):
        MultipleShootingModule(f, LinearReadout(D, 2), n_nodes=M, num_trajectories=4, gap_scale="node_variance")
    with pytest.raises(
        ValueError, match=r"unknown gap_scale 'relative': choose one of \['absolute', 'node_variance'\]"
    ):
        model(gap_scale="relative")
    # the objective itself refuses an unknown scale (a Python API caller, also under python -O)
    residual, nodes = torch.ones(1, M - 1, D), torch.randn(1, M, D)
    with pytest.raises(ValueError, match="unknown gap_scale 'relative'"):
        gap_term(residual, nodes, "relative")
