"""The ConvDecoder's one switch, ``backend``: names checked, the earlier versions' switches read into it, ``"auto"``
taking the path it measured faster (once per machine, kept in the cache folder), and a checkpoint of an earlier
version (``native`` / ``channels_last`` in its hyperparameters) still loading."""

from __future__ import annotations

import json

import pytest
import torch

from ssm_ms.module import MultipleShootingModule
from ssm_ms.nets import ConvDecoder, decoder
from ssm_ms.nets.native import build
from tests.test_cli import CPU, fit_tiny, outputs, run
from tests.test_native import NATIVE_NODE, _graph_names

SPEC = dict(preset=None, stem_channels=8, stem_size=3, layers=[[6, 5, 3], [5, 3, 2], [1, 2, 1]])


def ran_native(g: ConvDecoder, x: torch.Tensor) -> bool:
    return NATIVE_NODE in _graph_names(g(x.requires_grad_()))


def test_backend_names_are_checked():
    with pytest.raises(ValueError, match=r"backend must be one of \['auto', 'native', 'torch', 'plain'\], got 'fast'"):
        ConvDecoder(4, "pendulum", backend="fast")


def test_the_earlier_switches_are_read_into_backend():
    assert ConvDecoder(4, "pendulum", native=True, channels_last=True).backend == "auto"  # their old defaults
    assert ConvDecoder(4, "pendulum", native=False).backend == "torch"
    assert ConvDecoder(4, "pendulum", channels_last=False).backend == "plain"
    assert ConvDecoder(4, "pendulum", native=False, channels_last=False).backend == "plain"
    assert ConvDecoder(4, "pendulum", backend="torch", native=False).backend == "torch"
    with pytest.raises(ValueError, match="give backend alone"):
        ConvDecoder(4, "pendulum", backend="native", native=False)


def test_every_backend_draws_the_same_images(decoder_path):
    """The plain NCHW layers in float64 as the reference; the backend under test in float32."""
    torch.manual_seed(0)
    ref = ConvDecoder(5, **SPEC, backend="plain").double()
    g = ConvDecoder(5, **SPEC, backend=decoder_path)
    g.load_state_dict(ref.state_dict())
    x = torch.randn(7, 5)
    assert ran_native(g, x.clone()) == (decoder_path == "native")
    torch.testing.assert_close(g(x).double(), ref(x.double()), rtol=1e-5, atol=1e-5)


@pytest.fixture
def fresh_choices(monkeypatch, tmp_path):
    """No choice made yet in this process, the cache folder in tmp_path, and _time_paths replaced by given times."""
    monkeypatch.setattr(decoder, "_choices", {})
    monkeypatch.setenv("SSM_MS_CACHE", str(tmp_path))
    timed = []

    def times(native_s: float, torch_s: float):
        def fake(dec):
            timed.append(dec.geometry)
            return native_s, torch_s
        monkeypatch.setattr(decoder, "_time_paths", fake)

    return tmp_path, timed, times


def test_auto_runs_the_path_it_measured_faster_and_keeps_the_choice(needs_native, fresh_choices, monkeypatch):
    cache, timed, times = fresh_choices
    x = torch.randn(3, 5)
    times(native_s=0.1, torch_s=0.2)
    assert ran_native(ConvDecoder(5, **SPEC), x.clone())
    assert ran_native(ConvDecoder(5, **SPEC), x.clone())  # another decoder of the same layers: not timed again
    assert len(timed) == 1
    saved = json.loads((cache / decoder.CHOICES_FILE).read_text())
    (key, choice), = saved.items()
    assert choice["native"] is True and choice["native_ms"] == 100.0 and choice["torch_ms"] == 200.0
    assert key.startswith(build.library_key()) and str(ConvDecoder(5, **SPEC).geometry) in key
    # a new process (no choice in memory) reads the file: still not timed again, even if the times would now differ
    monkeypatch.setattr(decoder, "_choices", {})
    times(native_s=0.3, torch_s=0.2)
    assert ran_native(ConvDecoder(5, **SPEC), x.clone())
    assert len(timed) == 1
    # other layers: their own timing, here the torch path wins
    other = dict(SPEC, layers=[[6, 3, 2], [5, 3, 2], [1, 2, 1]])
    assert not ran_native(ConvDecoder(5, **other), x.clone())
    assert len(timed) == 2 and len(json.loads((cache / decoder.CHOICES_FILE).read_text())) == 2
    # another thread count is another key: timed again
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(2 if threads == 1 else 1)
        assert not ran_native(ConvDecoder(5, **SPEC), x.clone())
    finally:
        torch.set_num_threads(threads)
    assert len(timed) == 3


def test_a_damaged_choices_file_is_measured_again(needs_native, fresh_choices):
    cache, timed, times = fresh_choices
    (cache / decoder.CHOICES_FILE).write_text(json.dumps({decoder._choice_key(ConvDecoder(5, **SPEC)): "native"}))
    times(native_s=0.2, torch_s=0.1)
    assert not ran_native(ConvDecoder(5, **SPEC), torch.randn(3, 5))
    assert len(timed) == 1
    (cache / decoder.CHOICES_FILE).write_text("{not json")
    decoder._choices.clear()
    assert not ran_native(ConvDecoder(5, **SPEC), torch.randn(3, 5))
    assert len(timed) == 2 and json.loads((cache / decoder.CHOICES_FILE).read_text())  # rewritten whole


def test_a_traced_forward_never_times(needs_native, fresh_choices):
    """torch.export traces with fake tensors: auto takes the torch path there, times nothing and records nothing."""
    cache, timed, times = fresh_choices
    times(native_s=0.1, torch_s=0.2)
    g = ConvDecoder(5, **SPEC).eval()
    program = torch.export.export(g, (torch.randn(3, 5),))
    assert "ssm_ms.conv_stack" not in str(program.graph)
    assert not timed and not (cache / decoder.CHOICES_FILE).exists()
    assert ran_native(g, torch.randn(3, 5)) and len(timed) == 1  # a real forward measures (here: native faster)


def test_auto_without_the_kernels_runs_torch_without_timing(fresh_choices, monkeypatch):
    _, timed, times = fresh_choices
    times(native_s=0.1, torch_s=0.2)
    monkeypatch.setattr(build, "_state", {"lib": None, "reason": "no C compiler", "key": None})
    assert not ran_native(ConvDecoder(5, **SPEC), torch.randn(3, 5))
    assert not timed


def test_the_timing_runs_both_paths_and_leaves_no_gradient(needs_native):
    g = ConvDecoder(5, "pendulum")
    native_s, torch_s = decoder._time_paths(g)
    assert 0 < native_s < 60 and 0 < torch_s < 60
    assert all(p.grad is None for p in g.parameters())  # the timing's gradients are not accumulated
    with torch.inference_mode():  # a first forward under inference mode (a test or predict run) can time too
        assert decoder._time_paths(g)[0] > 0


def test_a_checkpoint_of_an_earlier_version_loads(tmp_path):
    """Checkpoints written before ``backend`` record ``native`` and ``channels_last`` among g's arguments: they load
    from Python and resume from the command line."""
    config = CPU / "pendulum.yaml"
    fit_tiny(tmp_path, config)
    ckpt = outputs(tmp_path, config) / "checkpoints" / "last.ckpt"
    saved = torch.load(ckpt, weights_only=False)
    g_args = saved["hyper_parameters"]["g"]["init_args"]
    assert g_args["backend"] == "auto"
    del g_args["backend"]
    g_args.update(native=False, channels_last=True)  # what an earlier version recorded for its torch-only path
    old = tmp_path / "old.ckpt"
    torch.save(saved, old)
    model = MultipleShootingModule.load_from_checkpoint(old)
    assert model.g.backend == "torch"
    for key, value in saved["state_dict"].items():
        torch.testing.assert_close(model.state_dict()[key], value)
    cli = run(tmp_path, "fit", config, "--ckpt_path", str(old), "--trainer.max_epochs", "2",
              "--trainer.limit_train_batches", "2", "--trainer.limit_val_batches", "1",
              "--trainer.check_val_every_n_epoch", "1",
              "--data.init_args.n_train", "8", "--data.init_args.n_test", "4", "--data.init_args.workers", "1")
    assert cli.trainer.current_epoch == 2 and cli.model.g.backend == "torch"


def test_native_tests_fail_instead_of_skipping_where_the_kernels_are_required(monkeypatch):
    from tests.conftest import REQUIRE_NATIVE_ENV, native_or_skip

    monkeypatch.setattr(build, "_state", {"lib": None, "reason": "no C compiler", "key": None})
    monkeypatch.delenv(REQUIRE_NATIVE_ENV, raising=False)
    with pytest.raises(pytest.skip.Exception, match="native kernels unavailable: no C compiler"):
        native_or_skip()
    monkeypatch.setenv(REQUIRE_NATIVE_ENV, "1")
    with pytest.raises(pytest.fail.Exception, match="no C compiler.*SSM_MS_REQUIRE_NATIVE=1"):
        native_or_skip()
