"""ssm_ms.export: Jacobians of f and g against finite differences, and exported f / g run in a fresh
interpreter that never imports ssm_ms, against the modules."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from ssm_ms import export as ssm_export
from ssm_ms.nets import ConvDecoder, FullyConnectedTransition, LocallyLinearTransition, Projection
from tests.conftest import RotationDataModule, fast_trainer, rotation_model

F64 = torch.float64


def central_differences(fn, x: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """``[N, *out, d]``: each column by a central difference, one state component at a time (naive loop)."""
    columns = []
    with torch.no_grad():
        for i in range(x.shape[1]):
            step = torch.zeros_like(x)
            step[:, i] = eps
            columns.append((fn(x + step) - fn(x - step)) / (2 * eps))
    return torch.stack(columns, dim=-1)


def small_decoder(d: int) -> ConvDecoder:
    # channels-last (the default): the Jacobian takes the forward-mode path that vmap cannot batch
    return ConvDecoder(d, preset=None, stem_channels=4, stem_size=2, layers=[[3, 3, 2], [1, 2, 1]]).double()


def test_jacobians_of_the_project_networks_match_finite_differences():
    torch.manual_seed(0)
    d = 3
    x = torch.randn(4, d, dtype=F64)
    transitions = [
        LocallyLinearTransition(d, n_matrices=4, hidden=16).double(),
        FullyConnectedTransition(d, (16, 16)).double(),
    ]
    observations = [small_decoder(d), Projection([0, 2])]
    for f in transitions:
        for g in observations:
            a, _, c = ssm_export.linearize(f, g, x, flatten=False)
            obs = tuple(g(x).shape[1:])
            assert a.shape == (4, d, d) and c.shape == (4, *obs, d)
            torch.testing.assert_close(a, central_differences(f, x), rtol=1e-6, atol=1e-8)
            torch.testing.assert_close(c, central_differences(g, x), rtol=1e-6, atol=1e-8)
            flat = ssm_export.linearize(f, g, x).C
            torch.testing.assert_close(flat, c.reshape(4, -1, d))
    # SSM-LL's A at x is its local matrix plus the derivative of the mixing weights: not I + sum beta A_k alone
    f = transitions[0]
    a = ssm_export.linearize(f, observations[1], x)[0]
    assert not torch.allclose(a, f.matrix(x), atol=1e-6)
    # Projection: C is the selection matrix, exactly
    c = ssm_export.linearize(f, Projection([0, 2]), x).C
    assert torch.equal(c, torch.eye(d, dtype=F64)[[0, 2]].expand(4, 2, d))


@pytest.mark.parametrize(
    "make",
    [
        lambda d, m: LocallyLinearTransition(d, n_matrices=4, hidden=16, input_dim=m),
        lambda d, m: FullyConnectedTransition(d, (16, 16), input_dim=m),
    ],
)
def test_linearize_with_inputs_gives_b_by_central_differences(make):
    """A driven f(x, u): A = df/dx at fixed u and B = df/du at fixed x, against central differences."""
    torch.manual_seed(0)
    d, m = 3, 2
    f = make(d, m).double()
    x, u = torch.randn(4, d, dtype=F64), torch.randn(4, m, dtype=F64)
    a, b, c = ssm_export.linearize(f, Projection([0]), x, u)
    assert a.shape == (4, d, d) and b.shape == (4, d, m) and c.shape == (4, 1, d)
    torch.testing.assert_close(a, central_differences(lambda v: f(v, u), x), rtol=1e-6, atol=1e-8)
    torch.testing.assert_close(b, central_differences(lambda v: f(x, v), u), rtol=1e-6, atol=1e-8)
    assert ssm_export.linearize(f.float(), Projection([0]), x.float(), u.float()).B.dtype == torch.float32


def test_exported_driven_f_takes_states_and_inputs(tmp_path):
    torch.manual_seed(0)
    d, m = 4, 2
    f, g = LocallyLinearTransition(d, n_matrices=3, hidden=16, input_dim=m), Projection([0])
    written = ssm_export.export(f, g, d, tmp_path / "driven")
    assert json.loads(written["model.json"].read_text())["input_dim"] == m
    x, u = torch.randn(7, d), torch.randn(7, m)
    got = run_fresh(tmp_path / "driven", {"pt2": ("f.pt2", (x, u)), "ts": ("f.torchscript.pt", (x, u))}, tmp_path)
    with torch.no_grad():
        expected = f(x, u)
    torch.testing.assert_close(got["pt2"], expected, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(got["ts"], expected, rtol=1e-5, atol=1e-6)


FRESH = textwrap.dedent("""
    import sys
    for name in ("ssm_ms", "datamodules", "lightning"):  # any attempt to import them fails
        sys.modules[name] = None
    import torch
    folder, cases = sys.argv[1], torch.load(sys.argv[2])
    loaded, out = {}, {}
    for case, (name, x) in cases.items():
        if name not in loaded:
            path = f"{folder}/{name}"
            loaded[name] = torch.export.load(path).module() if name.endswith(".pt2") else torch.jit.load(path)
        fn = loaded[name]
        if case.endswith(":jacobian"):  # the exported program is differentiable: A = df/dx without ssm_ms
            out[case] = torch.func.vmap(torch.func.jacrev(lambda v: fn(v[None])[0]))(x).detach()
        else:
            with torch.no_grad():
                out[case] = fn(*x) if isinstance(x, (tuple, list)) else fn(x)
    torch.save(out, sys.argv[3])
""")


def run_fresh(folder, cases: dict[str, tuple[str, torch.Tensor]], tmp_path) -> dict[str, torch.Tensor]:
    """Outputs of the exported files, each case ``(file relative to folder, input)``, from a new interpreter in
    isolated mode (``-I``) where ``ssm_ms``, ``datamodules`` and ``lightning`` cannot be imported."""
    torch.save(cases, tmp_path / "cases.pt")
    proc = subprocess.run(
        [sys.executable, "-I", "-c", FRESH, str(folder), str(tmp_path / "cases.pt"), str(tmp_path / "out.pt")],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert "Warning" not in proc.stderr, proc.stderr
    return torch.load(tmp_path / "out.pt")


def test_exported_f_and_g_run_without_ssm_ms_and_match_the_modules(tmp_path):
    torch.manual_seed(0)
    d = 4
    models = {
        "ll": (LocallyLinearTransition(d, n_matrices=4, hidden=16), ConvDecoder(d, preset="pendulum")),
        "fc": (FullyConnectedTransition(d, (16, 16)), Projection([1, 3])),
        "linear": (LocallyLinearTransition(d, n_matrices=2, hidden=8), torch.nn.Linear(d, 2)),
    }
    cases, expected = {}, {}
    batches = {"7": torch.randn(7, d), "1": torch.randn(1, d)}  # neither the export's example (2) nor its check (5)
    for key, (f, g) in models.items():
        written = ssm_export.export(f, g, d, tmp_path / key)
        info = json.loads(written["model.json"].read_text())
        assert info["state_dim"] == d and info["obs_shape"] == list(g(batches["1"]).shape[1:])
        assert info["files"] == ["f.pt2", "f.torchscript.pt", "g.pt2", "g.torchscript.pt"]
        for name in info["files"]:
            net = (f if name.startswith("f") else g).eval()
            for size, x in batches.items():
                cases[f"{key}/{name}/{size}"] = (f"{key}/{name}", x)
                with torch.no_grad():
                    expected[f"{key}/{name}/{size}"] = net(x)
    got = run_fresh(tmp_path, cases, tmp_path)
    assert set(got) == set(expected)
    for case, value in expected.items():
        torch.testing.assert_close(got[case], value, rtol=1e-5, atol=1e-6, msg=case)


def test_export_from_a_checkpoint_on_the_command_line(tmp_path, capsys):
    dm = RotationDataModule(data_dir=str(tmp_path / "data"), batch_size=4, val_trajectories=0, normalize=True)
    model = rotation_model()
    trainer = fast_trainer(tmp_path, max_epochs=1)
    trainer.fit(model, dm)
    ckpt = tmp_path / "ssm.ckpt"
    trainer.save_checkpoint(ckpt)
    assert ssm_export.main(["export", str(ckpt), "--out", str(tmp_path / "exported"), "--format", "pt2"]) == 0
    info = json.loads((tmp_path / "exported" / "model.json").read_text())
    assert info["files"] == ["f.pt2", "g.pt2"] and info["f_class"] == "LocallyLinearTransition"
    # the normalisation g's output needs, as the DataModule computed it from the training measurements
    y = torch.tensor(np.asarray(dm.datasets["train"].arrays["y"]), dtype=F64)
    assert info["normalization"]["mean"] == pytest.approx([y.mean().item()], rel=1e-5)
    assert info["normalization"]["std"] == pytest.approx([y.std(unbiased=False).item()], rel=1e-4)
    x = torch.randn(3, 2)
    got = run_fresh(tmp_path / "exported", {"f": ("f.pt2", x), "g": ("g.pt2", x), "f:jacobian": ("f.pt2", x)}, tmp_path)
    with torch.no_grad():  # g in the data's own units: the normalisation by hand
        torch.testing.assert_close(got["f"], model.f(x))
        torch.testing.assert_close(got["g"], (model.g(x).double() * y.std(unbiased=False) + y.mean()).float())
    torch.testing.assert_close(got["f:jacobian"], ssm_export.linearize(model.f, model.g, x)[0])


def test_export_refuses_bad_inputs(tmp_path, capsys):
    assert ssm_export.main(["export", str(tmp_path / "missing.ckpt"), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error:") and "does not exist" in err and "Traceback" not in err
    (tmp_path / "broken.ckpt").write_bytes(b"not a checkpoint")
    assert ssm_export.main(["export", str(tmp_path / "broken.ckpt"), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert "not a readable checkpoint" in err and "Traceback" not in err
    torch.save({"state_dict": {"w": torch.zeros(1)}}, tmp_path / "other.ckpt")
    assert ssm_export.main(["export", str(tmp_path / "other.ckpt"), "--out", str(tmp_path / "o")]) == 1
    assert "not a checkpoint of a MultipleShootingModule" in capsys.readouterr().err
    with pytest.raises(ValueError, match="formats must be among"):
        ssm_export.export(LocallyLinearTransition(2, 2, 4), Projection([0]), 2, tmp_path / "o", formats=["onnx"])
