"""Networks against independent computations: the LL and FC transitions, decoder shapes and layouts."""

import copy

import pytest
import torch

from ssm_ms.nets import ConvDecoder, FullyConnectedTransition, LocallyLinearTransition, Projection
from ssm_ms.nets.encoder import StateEncoder
from ssm_ms.nets.linear import NarrowLinear
from ssm_ms.nets.transition import NARROW_MAX


def test_locally_linear_is_x_plus_weighted_matrices():
    torch.manual_seed(0)
    f = LocallyLinearTransition(4, n_matrices=5, hidden=16).double()
    x = torch.randn(6, 4, dtype=torch.float64)
    a = f.matrices.view(5, 4, 4)
    for n in range(6):
        beta = f.beta(x[n : n + 1])[0]
        assert beta.sum().item() == pytest.approx(1.0) and (beta > 0).all()  # softmax weights
        expected = x[n] + sum(beta[k] * (a[k] @ x[n]) for k in range(5))
        torch.testing.assert_close(f(x[n : n + 1])[0], expected)
        torch.testing.assert_close(f.matrix(x[n : n + 1])[0] @ x[n], expected)


def test_fully_connected_is_residual():
    f = FullyConnectedTransition(3, hidden=(8, 8))
    torch.nn.init.zeros_(f.mlp[-1].weight)
    torch.nn.init.zeros_(f.mlp[-1].bias)
    x = torch.randn(5, 3)
    torch.testing.assert_close(f(x), x)  # MLP output zero -> identity
    assert [m.out_features for m in f.mlp if isinstance(m, torch.nn.Linear)] == [8, 8, 3]


@pytest.mark.parametrize(
    "preset, size, channels",
    [("pendulum", 24, [16, 12, 1]), ("quad", 48, [16, 16, 12, 1]), ("mnist", 64, [512, 256, 256, 1])],
)
def test_decoder_presets(preset, size, channels, decoder_path):
    if preset == "mnist" and decoder_path == "native":
        pytest.skip("Moving MNIST's stack does not fit the native kernels (refused: test_native.py)")
    g = ConvDecoder(5, preset, backend=decoder_path)
    x = torch.randn(3, 5, requires_grad=True)
    out = g(x)
    out.sum().backward()  # the backward pass of either path runs
    assert x.grad.isfinite().all() and x.grad.abs().sum() > 0
    assert out.shape == (3, 1, size, size)
    assert ((out >= 0) & (out <= 1)).all()  # sigmoid (may saturate in float32)
    convs = [m for m in g.deconv if isinstance(m, torch.nn.ConvTranspose2d)]
    assert [m.out_channels for m in convs] == channels
    # spatial size: each transposed convolution maps s -> (s - 1) * stride + kernel
    s = 3
    for m in convs:
        s = (s - 1) * m.stride[0] + m.kernel_size[0]
    assert s == size


@pytest.mark.parametrize("out_channels", [1, 3])
def test_channels_last_decoder_equals_the_plain_one(out_channels):
    torch.manual_seed(0)
    spec = dict(preset=None, stem_channels=8, stem_size=3, layers=[[6, 3, 2], [5, 3, 2], [out_channels, 2, 1]])
    fast = ConvDecoder(4, **spec, backend="torch").double()
    plain = ConvDecoder(4, **spec, backend="plain").double()
    with torch.no_grad():  # non-trivial LayerNorm affine parameters, to catch a wrong permutation
        for p in fast.parameters():
            p.add_(0.1 * torch.randn_like(p))
    plain.load_state_dict(fast.state_dict())
    x = torch.randn(7, 4, dtype=torch.float64, requires_grad=True)
    a, b = fast(x), plain(x)
    torch.testing.assert_close(a, b)
    weight = torch.randn_like(a)
    ga = torch.autograd.grad((a * weight).sum(), [x, *fast.parameters()])
    gb = torch.autograd.grad((b * weight).sum(), [x, *plain.parameters()])
    for u, v in zip(ga, gb):
        torch.testing.assert_close(u, v)


def test_decoder_and_projection_errors():
    with pytest.raises(ValueError, match="unknown ConvDecoder preset 'cifar'"):
        ConvDecoder(3, "cifar")
    with pytest.raises(ValueError, match="needs a preset, or stem_channels"):
        ConvDecoder(3, None)
    p = Projection([0, 2])
    torch.testing.assert_close(p(torch.arange(6.0).view(2, 3)), torch.tensor([[0.0, 2.0], [3.0, 5.0]]))
    with pytest.raises(ValueError, match=r"reads state components \[0, 2\] but the state has 2"):
        p(torch.zeros(1, 2))


@pytest.mark.parametrize(
    "preset, shape, features",
    [("pendulum", (1, 24, 24), 64), ("quad", (1, 48, 48), 64), ("mnist", (1, 64, 64), 256), ("vector", (1,), 1)],
)
def test_encoder_presets(preset, shape, features):
    enc = StateEncoder(7, shape, preset=preset, hidden=16)
    assert enc.lstm.input_size == features
    y = torch.rand(2, 5, *shape)
    out = enc(y)
    assert out.shape == (2, 5, 7)
    # causal: the state at t depends on measurements 0..t only
    y2 = y.clone()
    y2[:, 3:] = torch.rand_like(y2[:, 3:])
    torch.testing.assert_close(enc(y2)[:, :3], out[:, :3])


@pytest.mark.parametrize(
    "c_in, c_out, kernel, stride, size",
    [
        (16, 12, 3, 2, (11, 11)),
        (32, 16, 5, 3, (3, 3)),
        (3, 5, 4, 2, (4, 6)),
        (2, 3, 2, 3, (5, 2)),
        (4, 2, 3, 1, (5, 5)),
        # k^2 C_out <= C_in: the matrix-product path
        (12, 1, 2, 1, (23, 23)),
        (16, 1, 4, 2, (5, 7)),
        (18, 2, 3, 2, (4, 5)),
    ],
)
@pytest.mark.parametrize("channels_last", [False, True])
def test_fast_conv_transpose_equals_torch_with_gradients_and_jvp(c_in, c_out, kernel, stride, size, channels_last):
    from torch.func import jvp

    from ssm_ms.nets.channels_last import conv_transpose2d

    torch.manual_seed(0)
    w = torch.randn(c_in, c_out, kernel, kernel, dtype=torch.float64, requires_grad=True)
    b = torch.randn(c_out, dtype=torch.float64, requires_grad=True)
    x = torch.randn(3, c_in, *size, dtype=torch.float64)
    if channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    x.requires_grad_()
    got = conv_transpose2d(x, w, b, stride)
    want = torch.nn.functional.conv_transpose2d(x, w, b, stride)
    torch.testing.assert_close(got, want)
    weight = torch.randn_like(want)
    for u, v in zip(
        torch.autograd.grad((got * weight).sum(), [x, w, b]), torch.autograd.grad((want * weight).sum(), [x, w, b])
    ):
        torch.testing.assert_close(u, v)
    tangents = (torch.randn_like(x), torch.randn_like(w), torch.randn_like(b))
    _, t_got = jvp(lambda *a: conv_transpose2d(*a, stride), (x.detach(), w.detach(), b.detach()), tangents)
    _, t_want = jvp(
        lambda *a: torch.nn.functional.conv_transpose2d(*a, stride=stride),
        (x.detach(), w.detach(), b.detach()),
        tangents,
    )
    torch.testing.assert_close(t_got, t_want)


def test_channels_last_decoder_never_converts_a_feature_map_to_nchw():
    """Forward and backward keep every multi-channel feature map channels-last: one NCHW copy of the pendulum
    decoder's 12 x 23 x 23 maps (e.g. autograd rebuilding the gradient of an in-place ReLU on a permuted view)
    made its ReLU backward run across two layouts, half the decoder's step time on CPU."""
    from torch.utils._python_dispatch import TorchDispatchMode

    produced = []

    class Record(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            out = func(*args, **(kwargs or {}))
            for t in out if isinstance(out, (tuple, list)) else (out,):
                if not func.is_view and isinstance(t, torch.Tensor) and tuple(t.shape) in maps:
                    produced.append((str(func), tuple(t.shape), t.stride()))
            return out

    torch.manual_seed(0)
    g = ConvDecoder(4, "pendulum", backend="torch")  # the torch path (the native kernels keep maps inside)
    maps = {(6, 16, 11, 11), (6, 12, 23, 23)}  # the hidden feature maps of 6 images, as [N, C, H, W]
    x = torch.randn(6, 4, requires_grad=True)
    with Record():
        g(x).square().sum().backward()
    assert produced  # feature maps were seen
    nchw = [p for p in produced if not torch.empty_strided(p[1], p[2]).is_contiguous(memory_format=torch.channels_last)]
    assert not nchw, nchw


@pytest.mark.parametrize("shape, bias", [((7, 3), True), ((2, 5, 3), True), ((7, 3), False)])
def test_narrow_linear_computes_linear_with_its_gradients(shape, bias):
    """``NarrowLinear``: ``y = x W^T + b``, ``dW = dy^T x``, ``db = sum dy``, ``dx = dy W`` (written out here), after an
    in-place ReLU as in SSM-LL's beta; its state dict is ``nn.Linear``'s."""
    torch.manual_seed(0)
    layer = NarrowLinear(3, 4, bias=bias).double()
    plain = torch.nn.Linear(3, 4, bias=bias).double()
    plain.load_state_dict(layer.state_dict())  # the same keys and shapes
    x = torch.randn(*shape, dtype=torch.float64, requires_grad=True)
    y = torch.relu_(layer(x))
    w, b = layer.weight.detach(), (layer.bias.detach() if bias else torch.zeros(4, dtype=torch.float64))
    pre = x.detach() @ w.T + b
    torch.testing.assert_close(y, pre.clamp(min=0))
    dy = torch.randn_like(y)
    y.backward(dy)
    dpre = (dy * (pre > 0)).reshape(-1, 4)
    torch.testing.assert_close(layer.weight.grad, dpre.T @ x.detach().reshape(-1, 3))
    torch.testing.assert_close(x.grad, (dpre @ w).reshape(shape))
    if bias:
        torch.testing.assert_close(layer.bias.grad, dpre.sum(0))
    # torch.func (analysis.py's Jacobians): the Jacobian of a linear map is W
    jac = torch.func.vmap(torch.func.jacrev(layer))(x.detach().reshape(-1, 3))
    torch.testing.assert_close(jac, w.expand(jac.shape[0], 4, 3))


@pytest.mark.parametrize("state_dim, input_dim", [(3, 0), (8, 2), (24, 0)])
def test_locally_linear_gradients_equal_those_of_a_plain_linear_beta(state_dim, input_dim):
    """Whichever first beta layer SSM-LL picks by its input width, its values and gradients are those of
    ``nn.Linear`` with the same weights."""
    torch.manual_seed(0)
    f = LocallyLinearTransition(state_dim, n_matrices=5, hidden=32, input_dim=input_dim).double()
    assert isinstance(f.beta[0], NarrowLinear) == (state_dim + input_dim <= NARROW_MAX)
    plain = copy.deepcopy(f)
    plain.beta[0] = torch.nn.Linear(state_dim + input_dim, 32).double()
    plain.beta[0].load_state_dict(f.beta[0].state_dict())
    x = torch.randn(11, state_dim, dtype=torch.float64)
    u = torch.randn(11, input_dim, dtype=torch.float64) if input_dim else None
    grads = []
    for model in (f, plain):
        x0 = x.clone().requires_grad_(True)
        state = x0
        for _ in range(4):
            state = model(state, u)
        state.pow(2).sum().backward()
        grads.append([x0.grad] + [p.grad for p in model.parameters()])
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b)


def test_fully_connected_transition_with_a_linear_part_and_tanh():
    """f(x, u) = x + W [x, u] + MLP([x, u]) with tanh layers, computed here layer by layer; W starts at zero."""
    torch.manual_seed(0)
    f = FullyConnectedTransition(3, hidden=(5,), input_dim=2, activation="tanh", linear=True)
    assert torch.count_nonzero(f.linear.weight) == 0
    torch.nn.init.normal_(f.linear.weight)
    x, u = torch.randn(4, 3), torch.randn(4, 2)
    xu = torch.cat([x, u], 1)
    hidden = torch.tanh(xu @ f.mlp[0].weight.T + f.mlp[0].bias)
    expected = x + xu @ f.linear.weight.T + hidden @ f.mlp[2].weight.T + f.mlp[2].bias
    torch.testing.assert_close(f(x, u), expected)
    with pytest.raises(ValueError, match="activation must be one of"):
        FullyConnectedTransition(3, activation="gelu")


def test_transition_without_the_identity_is_subnets_form():
    """residual=False: f(x, u) = W [x, u] + MLP([x, u]) (no x +), computed here layer by layer, W not at zero; it
    needs the linear part (else f would be the MLP alone, not SSM-FC)."""
    torch.manual_seed(0)
    f = FullyConnectedTransition(3, hidden=(5,), input_dim=2, activation="tanh", linear=True, residual=False)
    assert torch.count_nonzero(f.linear.weight) == f.linear.weight.numel()
    x, u = torch.randn(4, 3), torch.randn(4, 2)
    xu = torch.cat([x, u], 1)
    hidden = torch.tanh(xu @ f.mlp[0].weight.T + f.mlp[0].bias)
    torch.testing.assert_close(f(x, u), xu @ f.linear.weight.T + hidden @ f.mlp[2].weight.T + f.mlp[2].bias)
    with pytest.raises(ValueError, match="needs linear=True"):
        FullyConnectedTransition(3, residual=False)


def test_identity_init_starts_f_as_the_identity_and_still_learns():
    """identity_init: f(x, u) = x exactly at initialisation (PyTorch's default initialisation does not give that),
    and the layers before the zeroed one still get gradients once it moves (one step of SGD on a loss)."""
    torch.manual_seed(0)
    x, u = torch.randn(6, 3), torch.randn(6, 2)
    f = FullyConnectedTransition(3, hidden=(8, 8), input_dim=2, identity_init=True)
    torch.testing.assert_close(f(x, u), x, rtol=0, atol=0)
    assert not torch.allclose(FullyConnectedTransition(3, hidden=(8, 8), input_dim=2)(x, u), x)
    opt = torch.optim.SGD(f.parameters(), lr=0.1)
    for _ in range(2):
        opt.zero_grad()
        (f(x, u) - 2 * x).pow(2).mean().backward()
        opt.step()
    assert torch.count_nonzero(f.mlp[-1].weight) > 0 and f.mlp[0].weight.grad.abs().sum() > 0


def test_mlp_readout_is_linear_plus_a_network_starting_at_zero():
    """g(x) = W x + b + MLP(x), computed here layer by layer; at initialisation the network adds nothing."""
    from ssm_ms.nets import MLPReadout

    torch.manual_seed(0)
    g = MLPReadout(3, out_features=2, hidden=(5, 4), activation="tanh")
    x = torch.randn(6, 3)
    torch.testing.assert_close(g(x), x @ g.linear.weight.T + g.linear.bias)
    for layer in (g.mlp[-1].weight, g.mlp[-1].bias):
        torch.nn.init.normal_(layer)
    h = torch.tanh(x @ g.mlp[0].weight.T + g.mlp[0].bias)
    h = torch.tanh(h @ g.mlp[2].weight.T + g.mlp[2].bias)
    torch.testing.assert_close(g(x), x @ g.linear.weight.T + g.linear.bias + h @ g.mlp[4].weight.T + g.mlp[4].bias)
    with pytest.raises(ValueError, match="activation must be one of"):
        MLPReadout(3, 1, activation="gelu")
    with pytest.raises(ValueError, match="at least one hidden width"):
        MLPReadout(3, 1, hidden=())
