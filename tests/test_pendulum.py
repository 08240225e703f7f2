"""The n-link pendulum data set: physics, rendering, noise, determinism, cache, DataModule."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp
from scipy.stats import norm

from datamodules import pendulum_excitation as drive
from datamodules import pendulum_generation as gen
from datamodules import pendulum_render as camera
from datamodules import pendulum_sim as sim
from datamodules.pendulum import PendulumDataModule

G = 9.81


# ------------------------------------------------------------------ independent references
def chain_energy(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Energy of unit point masses on unit links, from relative angles ``[..., n]``."""
    phi, dphi = np.cumsum(q, -1), np.cumsum(v, -1)
    height = -np.cumsum(np.cos(phi), -1)
    vx = np.cumsum(dphi * np.cos(phi), -1)
    vz = np.cumsum(dphi * np.sin(phi), -1)
    return 0.5 * (vx**2 + vz**2).sum(-1) + G * height.sum(-1)


def lagrangian_rhs(n: int, damping: float):
    """Equations of motion in *absolute* link angles, derived by hand (no Pinocchio)."""
    idx = np.arange(n)
    beyond = n - np.maximum(idx[:, None], idx[None, :])  # masses at or after link max(i, j)

    def rhs(_t, x):
        phi, dphi = x[:n], x[n:]
        diff = phi[:, None] - phi[None, :]
        mass = beyond * np.cos(diff)
        theta_dot = np.diff(np.concatenate([[0.0], dphi]))
        torque = -damping * theta_dot  # on relative joints
        generalized = torque - np.concatenate([torque[1:], [0.0]])
        rhs_force = generalized - (beyond * np.sin(diff) * dphi[None, :] ** 2).sum(1) - G * (n - idx) * np.sin(phi)
        return np.concatenate([dphi, np.linalg.solve(mass, rhs_force)])

    return rhs


def simulate(n, q0, v0, duration=10.0, frame_dt=0.1, dt=5e-3, damping=0.0):
    model = sim.pendulum_model(n)
    frames = int(round(duration / frame_dt))
    return sim.simulate(model, model.createData(), q0, v0, frames, int(round(frame_dt / dt)), dt, damping)[:2]


def small_module(tmp_path, **kw) -> PendulumDataModule:
    args = dict(n_train=4, n_test=4, data_dir=str(tmp_path), workers=1, batch_size=2, val_trajectories=2)
    args.update(kw)
    return PendulumDataModule(**args)


@pytest.fixture(scope="module")
def simple_data(tmp_path_factory):
    """Four trajectories per split in the analytic rendering (exact zeros off the line, values in [0, 1])."""
    dm = small_module(tmp_path_factory.mktemp("pend"), rendering="analytic")
    dm.prepare_data()
    return dm, dm.load_arrays("train"), dm.load_arrays("test")


@pytest.fixture(scope="module")
def paper_data(tmp_path_factory):
    """The same in the paper's rendering (the default)."""
    dm = small_module(tmp_path_factory.mktemp("pend_paper"))
    assert dm.rendering == "paper"
    dm.prepare_data()
    return dm, dm.load_arrays("train"), dm.load_arrays("test")


# ------------------------------------------------------------------ physics
def test_simple_pendulum_energy_conserved(simple_data):
    _, train, test = simple_data
    for arrays in (train, test):
        s = np.asarray(arrays["state"], dtype=np.float64)
        e = 0.5 * s[..., 1] ** 2 - G * np.cos(s[..., 0])  # m = l = 1
        scale = np.maximum(np.abs(e[:, :1]), G)  # e may cross 0: compare to the energy scale m g l
        assert (np.abs(e - e[:, :1]) / scale).max() < 1e-3
    # hard cases: near the top, large speed; 10 s with the default step
    q, v = simulate(1, [[math.pi - 1e-3], [2.5], [0.3]], [[0.0], [1.0], [-4.0]], duration=10.0)
    e = 0.5 * v[..., 0] ** 2 - G * np.cos(q[..., 0])
    assert (np.abs(e - e[:, :1]) / G).max() < 1e-3


def test_simple_pendulum_matches_closed_form_ode():
    q, v = simulate(1, [[2.0]], [[0.5]], duration=5.0)
    t = np.arange(50) * 0.1
    ref = solve_ivp(lambda _t, x: [x[1], -G * np.sin(x[0])], (0, t[-1]), [2.0, 0.5], t_eval=t, rtol=1e-11, atol=1e-11)
    assert np.abs(q[0, :, 0] - ref.y[0]).max() < 1e-6
    assert np.abs(v[0, :, 0] - ref.y[1]).max() < 1e-6


def test_small_oscillation_period():
    theta0 = 0.05
    q, _ = simulate(1, [[theta0]], [[0.0]], duration=10.0, frame_dt=0.01)
    x = q[0, :, 0]
    t = np.arange(len(x)) * 0.01
    k = np.flatnonzero(np.sign(x[:-1]) != np.sign(x[1:]))
    crossings = t[k] - x[k] * (t[k + 1] - t[k]) / (x[k + 1] - x[k])  # linear interpolation
    period = 2 * (crossings[-1] - crossings[0]) / (len(crossings) - 1)
    assert len(crossings) >= 8
    assert period == pytest.approx(2 * math.pi * math.sqrt(1.0 / G), rel=5e-3)


def test_quadruple_matches_independent_lagrangian():
    rng = np.random.default_rng(3)
    q0 = rng.uniform(-1.0, 1.0, 4)
    v0 = rng.uniform(-0.5, 0.5, 4)
    q, v = simulate(4, q0[None], v0[None], duration=2.0, damping=0.1)
    t = np.arange(20) * 0.1
    phi0, dphi0 = np.cumsum(q0), np.cumsum(v0)
    ref = solve_ivp(lagrangian_rhs(4, 0.1), (0, t[-1]), np.concatenate([phi0, dphi0]), t_eval=t, rtol=1e-11, atol=1e-11)
    assert np.abs(np.cumsum(q[0], -1) - ref.y[:4].T).max() < 1e-5
    assert np.abs(np.cumsum(v[0], -1) - ref.y[4:].T).max() < 1e-4


def test_quadruple_energy_damped_decreases_undamped_conserved():
    rng = np.random.default_rng(0)
    q0 = rng.uniform(-math.pi, math.pi, (3, 4))
    v0 = np.zeros((3, 4))
    scale = G * 10  # g * (1 + 2 + 3 + 4): the potential-energy range
    q, v = simulate(4, q0, v0, damping=0.0)
    e = chain_energy(q, v)
    assert (np.abs(e - e[:, :1]) / scale).max() < 1e-3
    q, v = simulate(4, q0, v0, damping=0.1)
    e = chain_energy(q, v)
    assert (np.diff(e, axis=1) < 1e-3 * scale).all()  # dE/dt = -0.1 * |v|^2 <= 0, up to integration error
    assert (e[:, -1] < e[:, 0] - 0.05 * scale).all()


# ------------------------------------------------------------------ rendering
def naive_render(angles: np.ndarray, size: int, width: float) -> np.ndarray:
    """Per-pixel loop: distance from the pixel centre to each segment of the chain."""
    n = angles.shape[1]
    link = (size / 2 - width / 2 - 1) / n
    out = np.zeros((len(angles), 1, size, size))
    for f, theta in enumerate(angles):
        phi = np.cumsum(theta)
        pts = np.concatenate([[[0.0, 0.0]], np.cumsum(link * np.stack([np.sin(phi), np.cos(phi)], 1), 0)]) + size / 2
        for i in range(size):
            for j in range(size):
                p = np.array([j + 0.5, i + 0.5])
                dist = min(
                    np.linalg.norm(p - a - np.clip((p - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1) * (b - a))
                    for a, b in zip(pts[:-1], pts[1:])
                )
                out[f, 0, i, j] = min(max(width / 2 + 0.5 - dist, 0.0), 1.0)
    return out


@pytest.mark.parametrize("n,size,width", [(1, 24, 2.0), (4, 48, 2.0), (3, 20, 1.0), (2, 17, 3.5)])
def test_render_matches_naive_loop(n, size, width):
    angles = np.random.default_rng(n).uniform(-4, 4, (3, n))
    img = camera.render_analytic(angles, size, width)
    assert img.shape == (3, 1, size, size) and img.dtype == np.float32
    assert img.min() >= 0 and img.max() <= 1
    np.testing.assert_allclose(img, naive_render(angles, size, width), atol=1e-5)


def centroid(img: np.ndarray) -> np.ndarray:
    """Intensity-weighted centre (x right, y down) in pixel units, pixel centres at i + 0.5."""
    w = img.reshape(img.shape[-2:]).astype(np.float64)
    c = np.arange(w.shape[0]) + 0.5
    return np.array([(w.sum(0) * c).sum(), (w.sum(1) * c).sum()]) / w.sum()


@pytest.mark.parametrize("n,size", [(1, 24), (4, 48)])
def test_render_geometry(n, size):
    length = size / 2 - 1 - 1  # whole chain, line width 2
    for theta, direction in [(0.0, (0, 1)), (math.pi / 2, (1, 0)), (-math.pi / 2, (-1, 0)), (math.pi, (0, -1))]:
        angles = np.zeros((1, n))
        angles[0, 0] = theta  # straight chain: mid-chain point at half the length
        img = camera.render_analytic(angles, size, 2.0)[0]
        assert img.shape == (1, size, size)
        expected = size / 2 + 0.5 * length * np.array(direction)
        np.testing.assert_allclose(centroid(img), expected, atol=0.15)
    # a bent chain: the first link straight right, the others down again, the mean of link midpoints
    if n == 4:
        img = camera.render_analytic(np.array([[math.pi / 2, -math.pi / 2, 0, 0]]), size, 2.0)[0]
        link = length / 4
        mids = np.array([[0.5, 0], [1, 0.5], [1, 1.5], [1, 2.5]]) * link + size / 2
        np.testing.assert_allclose(centroid(img), mids.mean(0), atol=0.5)


@pytest.mark.parametrize("data,length", [("simple_data", 10.0), ("paper_data", 12.0)])
def test_frames_match_states(data, length, request):
    """Every clean frame of the data set shows the link where its stored angle puts it (analytic chain: 10 px,
    paper: 12 px, half the frame)."""
    _, train, _ = request.getfixturevalue(data)
    theta = np.asarray(train["state"][..., 0], dtype=np.float64).reshape(-1)
    frames = np.asarray(train["y_clean"]).reshape(-1, 24, 24) / 255.0
    mid = 12 + 0.5 * length * np.stack([np.sin(theta), np.cos(theta)], 1)
    got = np.stack([centroid(f) for f in frames])
    assert np.abs(got - mid).max() < 0.3


# ------------------------------------------------------------------ the paper's rendering
def reference_image(theta: np.ndarray, size: int) -> np.ndarray:
    """The reference generator's ``create_image`` (machines-in-motion/ssm_multiple_shooting, ``n_link.py``) without
    its noise, in its own angle convention (zero is upright), with PIL: what the paper's images are."""
    from PIL import Image, ImageDraw

    n = len(theta)
    img = Image.new("F", (128, 128), 0.0)
    draw = ImageDraw.Draw(img)
    cx, cy, length = 64.0, 64.0, 128 / 2 / n
    x0 = y0 = 0.0
    for k in range(n):
        x1 = x0 - np.sin(np.sum(theta[: k + 1]) - np.pi)
        y1 = y0 - np.cos(np.sum(theta[: k + 1]) - np.pi)
        draw.line([(cx + length * x0, cy - length * y0), (cx + length * x1, cy - length * y1)], fill=1.0, width=8)
        x0, y0 = x1, y1
    return np.asarray(img.resize((size, size), resample=Image.LANCZOS))


def lanczos_matrix(size: int, source: int, lobes: int = 3) -> np.ndarray:
    """``[size, source]`` Lanczos-3 resampling matrix written from the filter's definition (pixel ``j`` centred at
    ``j + 0.5``; when shrinking the kernel is stretched by the scale and the weights normalised per output)."""
    scale = source / size
    stretch = max(scale, 1.0)
    out = np.zeros((size, source))
    for i in range(size):
        centre = (i + 0.5) * scale
        x = (np.arange(source) + 0.5 - centre) / stretch
        w = np.where(np.abs(x) < lobes, np.sinc(x) * np.sinc(x / lobes), 0.0)
        out[i] = w / w.sum()
    return out


def test_lanczos_matrix_is_pils_resize():
    """The closed-form filter below is PIL's ``Image.LANCZOS`` (so the pivot test compares with a formula)."""
    from PIL import Image

    rng = np.random.default_rng(0)
    for size, source in [(24, 128), (48, 128), (7, 30)]:
        img = rng.uniform(-1, 2, (source, source)).astype(np.float32)
        expected = np.asarray(Image.fromarray(img, mode="F").resize((size, size), resample=Image.LANCZOS))
        resize = lanczos_matrix(size, source)
        np.testing.assert_allclose(resize @ img @ resize.T, expected, atol=2e-5)


@pytest.mark.parametrize("n,size", [(1, 24), (4, 48)])
def test_paper_rendering_is_the_reference_generators(n, size):
    """Pixel for pixel the reference's images: our angles (zero hanging, right positive) map to its (zero upright)
    by ``phi_ref = pi - phi``, i.e. ``theta_ref = (pi - theta_1, -theta_2, ...)``."""
    angles = np.random.default_rng(n).uniform(-math.pi, math.pi, (60, n))
    theirs = -angles
    theirs[:, 0] += math.pi
    ours = camera.render_paper(angles, size)
    expected = np.stack([reference_image(t, size) for t in theirs])[:, None]
    assert ours.shape == expected.shape == (60, 1, size, size) and ours.dtype == np.float32
    np.testing.assert_array_equal(ours, expected)
    assert ours.min() < -0.05 and ours.max() > 1.05  # the filter rings outside [0, 1]


@pytest.mark.parametrize("angle", [0.0, math.pi / 2])
def test_paper_pivot_pixel_convention(angle):
    """A hanging chain and one pointing right, against the closed form of PIL's convention: a coordinate names a
    pixel index (the pivot (64, 64) lights pixel 64) and an 8-pixel line covers 3 pixels left of its axis and 4
    right, so the hanging chain lights canvas columns 61..68 from row 64 down (the right-pointing one the
    transpose). Every output pixel is compared, the pivot's (12, 12) by name: the old rasteriser (a centred
    rectangle with the pivot at the canvas' corner point 64.0) gave it 0.09 less."""
    canvas = np.zeros((128, 128))
    canvas[64:, 61:69] = 1.0
    if angle:
        canvas = canvas.T
    resize = lanczos_matrix(24, 128)
    expected = resize @ canvas @ resize.T
    got = camera.render_paper(np.array([[angle]]), 24)[0, 0]
    np.testing.assert_allclose(got, expected, atol=1e-5)
    assert got[12, 12] == pytest.approx(expected[12, 12], abs=1e-5)
    assert abs(expected[12, 12] - expected[12, 11]) > 0.1  # the pixel the convention decides


@pytest.mark.parametrize("n,size", [(1, 24), (4, 48)])
def test_paper_geometry(n, size):
    """A straight chain pointing right: as long as half the frame (it reaches the edge), 8/128 of the frame thick,
    its ink the band's area (the resize keeps the sum), its centroid one canvas pixel below the axis (half a pixel
    for PIL's pivot at pixel 64's centre, half for its 3-and-4 split of the width)."""
    angles = np.zeros((1, n))
    angles[0, 0] = math.pi / 2
    img = camera.render_paper(angles, size)[0, 0].astype(np.float64)
    width, length = size / 16, size / 2
    assert img.sum() == pytest.approx(width * length, rel=0.02)
    below = size / 128  # one canvas pixel, in output pixels
    np.testing.assert_allclose(centroid(img), [size / 2 + length / 2, size / 2 + below], atol=0.05)
    mid = size // 2 + int(length // 2)
    assert img[:, mid].sum() == pytest.approx(width, rel=0.02)  # the cross-section of the rod
    rows = slice(size // 2 - 1, size // 2 + 1)
    assert img[rows, -1].min() > 0.3  # the tip reaches the last column
    assert np.abs(img[:, : size // 2 - 3]).max() < 1e-6  # nothing behind the pivot beyond the filter's reach
    assert camera.render(angles, size)[0, 0].tolist() == img.astype(np.float32).tolist()  # the default rendering


def test_paper_noise_is_clipped_after_it_is_added(paper_data):
    """Where the filter rings below 0, the noisy pixel is clip(c + Z, 0, 1) with c < 0 (the paper's order), not
    clip(clip(c) + Z): checked against the closed form of E[clip(c + Z, 0, 1)] on the re-rendered frames."""
    _, train, test = paper_data
    state = np.concatenate([train["state"], test["state"]]).astype(np.float64)
    clean = np.stack([camera.render_paper(s[:, :1], 24)[:, 0] for s in state]).astype(np.float64)
    y = np.concatenate([train["y"], test["y"]])[:, :, 0].astype(np.float64) / 255.0

    def expected_mean(c):
        sd = 0.2
        lo, hi = (0 - c) / sd, (1 - c) / sd  # 0 below lo, c + sd z between, 1 above hi
        return c * (norm.cdf(hi) - norm.cdf(lo)) + sd * (norm.pdf(lo) - norm.pdf(hi)) + norm.sf(hi)

    ringing = clean < -0.04
    assert ringing.sum() > 500
    got = y[ringing].mean()
    assert got == pytest.approx(expected_mean(clean[ringing]).mean(), abs=0.004)
    assert got < expected_mean(np.zeros(1))[0] - 0.01  # clipping first would give the zero pixel's mean
    everywhere = expected_mean(clean)
    assert np.abs(y.mean() - everywhere.mean()) < 0.002


# ------------------------------------------------------------------ noise
def test_noise_level(simple_data):
    _, train, test = simple_data
    y = np.concatenate([train["y"], test["y"]]).astype(np.float64) / 255.0
    clean = np.concatenate([train["y_clean"], test["y_clean"]]).astype(np.float64) / 255.0
    assert y.shape == clean.shape == (8, 100, 1, 24, 24)
    dark = clean == 0
    assert y[dark].mean() == pytest.approx(0.2 / math.sqrt(2 * math.pi), abs=2e-3)  # N(0, 0.2) clipped at 0
    assert (y[dark] == 0).mean() == pytest.approx(0.5, abs=0.01)
    # mid-grey pixels: residual moments of clip(c + Z, 0, 1) - c, integrated numerically per grey level
    mask = (clean >= 0.2) & (clean <= 0.8)
    assert mask.sum() > 2000
    z = np.linspace(-8, 8, 20001) * 0.2
    pdf = norm.pdf(z, scale=0.2) * (z[1] - z[0])
    levels, counts = np.unique(clean[mask], return_counts=True)
    r = np.clip(levels[:, None] + z[None], 0, 1) - levels[:, None]
    m1 = ((r * pdf).sum(1) * counts).sum() / counts.sum()
    m2 = ((r**2 * pdf).sum(1) * counts).sum() / counts.sum()
    expected_std = math.sqrt(m2 - m1**2 + (1 / 255) ** 2 / 12)
    residual = y[mask] - clean[mask]
    assert residual.mean() == pytest.approx(m1, abs=0.01)
    assert residual.std() == pytest.approx(expected_std, abs=0.01)
    assert 0.15 < expected_std < 0.2


# ------------------------------------------------------------------ determinism and cache
def test_deterministic_across_workers_and_seeds(tmp_path, monkeypatch):
    kw = dict(n_links=2, image_size=16, duration=1.0, n_train=5, n_test=3)
    a = small_module(tmp_path / "a", workers=1, **kw)
    ga = a.generate("train")
    monkeypatch.setattr(gen, "CHUNK_SIZE", 2)  # several tasks spread over two processes
    b = small_module(tmp_path / "b", workers=2, **kw)
    gb = b.generate("train")
    for key in ("y", "y_clean", "state"):
        np.testing.assert_array_equal(ga[key], gb[key])
    assert ga["y"].shape == (5, 10, 1, 16, 16) and ga["state"].shape == (5, 10, 4)
    test = a.generate("test")
    assert not np.array_equal(ga["state"][:3], test["state"])
    other = small_module(tmp_path / "c", seed=1, **kw).generate("train")
    assert not np.array_equal(ga["state"], other["state"])
    assert not np.array_equal(ga["y"], other["y"])
    # trajectories within a set differ; the first frame is the initial state drawn in the allowed range
    s = ga["state"]
    assert len({tuple(x) for x in s[:, 0]}) == 5
    assert np.abs(s[:, 0, :2]).max() <= math.pi + 1e-6 and np.abs(s[:, 0, 2:]).max() <= 1.0


def test_cache_reused_and_keyed(tmp_path, monkeypatch):
    kw = dict(duration=0.5, image_size=12, line_width=1.0)
    dm = small_module(tmp_path, **kw)
    dm.prepare_data()
    first = dm.load_arrays("train")["y"].copy()

    def fail(split):
        raise AssertionError("regenerated although cached")

    again = small_module(tmp_path, **kw)
    monkeypatch.setattr(again, "generate", fail)
    again.prepare_data()
    np.testing.assert_array_equal(again.load_arrays("train")["y"], first)
    other = small_module(tmp_path, noise_std=0.1, **kw)
    assert other.cache_dir != dm.cache_dir
    other.prepare_data()
    assert other.is_cached("train") and other.is_cached("test") and dm.is_cached("train")


# ------------------------------------------------------------------ DataModule
def test_datamodule_end_to_end(simple_data):
    dm, train, _ = simple_data
    dm.setup("fit")
    assert dm.num_train_trajectories == 4 and dm.seq_len == 100 and dm.obs_shape == (1, 24, 24)
    batch = next(iter(dm.train_dataloader()))
    assert set(batch) == {"index", "y", "y_clean", "state"}
    assert batch["index"].dtype == torch.long and batch["index"].shape == (2,)
    for key in ("y", "y_clean"):
        assert batch[key].dtype == torch.float32 and batch[key].shape == (2, 100, 1, 24, 24)
        assert 0 <= batch[key].min() and batch[key].max() <= 1
    assert batch["state"].dtype == torch.float32 and batch["state"].shape == (2, 100, 2)
    i = batch["index"].numpy()
    np.testing.assert_allclose(batch["y"].numpy(), train["y"][i] / 255.0, atol=1e-6)
    val = [b for b in dm.val_dataloader()]
    val_idx = np.concatenate([b["index"].numpy() for b in val])
    np.testing.assert_array_equal(val_idx, [0, 3])
    np.testing.assert_allclose(val[0]["state"].numpy(), train["state"][val_idx[: len(val[0]["index"])]])
    test_batch = next(iter(dm.test_dataloader()))
    assert test_batch["y"].shape == (2, 100, 1, 24, 24)


def test_paper_defaults():
    dm = PendulumDataModule()
    assert (dm.n_links, dm.image_size, dm.n_train, dm.n_test, dm.damping) == (1, 24, 1000, 1000, 0.0)
    assert (dm.max_angle, dm.max_velocity, dm.noise_std, dm.n_frames) == (math.pi, 1.0, 0.2, 100)
    assert dm.workers >= 1


@pytest.mark.parametrize(
    "kw,match",
    [
        (dict(n_links=0), "n_links"),
        (dict(image_size=5, rendering="analytic"), "image_size"),
        (dict(n_links=4, image_size=10, rendering="analytic"), "too small"),
        (dict(n_links=4, image_size=7), "too small"),
        (dict(rendering="pil"), "rendering"),
        (dict(dt=0.003), "multiple of the integrator step"),
        (dict(duration=1.05), "multiple .* of frame_dt"),
        (dict(noise_std=-0.1), "noise_std"),
        (dict(damping=-1.0), "damping"),
        (dict(n_train=0), "n_train"),
        (dict(workers=0), "workers"),
        (dict(line_width=0.0), "line_width"),
        (dict(seed=-1), "seed"),
        (dict(max_velocity=-1.0), "max_velocity"),
    ],
)
def test_bad_arguments(kw, match):
    with pytest.raises(ValueError, match=match):
        PendulumDataModule(**kw)


def test_true_measurements_continue_the_stored_trajectories(simple_data):
    """The generator's own continuation from a trajectory's initial state: over the stored 100 frames it is the
    stored clean frames bit for bit; beyond them, the closed-form ODE's angle drawn by the same renderer."""
    dm, train, _ = simple_data
    frames = dm.true_measurements("train", [2, 0], 150)
    assert frames.shape == (2, 150, 1, 24, 24)
    stored = torch.from_numpy(np.asarray(train["y_clean"])[[2, 0]]).float() / 255
    torch.testing.assert_close(frames[:, :100], stored, rtol=0, atol=0)
    s0 = np.asarray(train["state"], dtype=np.float64)[0, 0]
    t = np.arange(150) * 0.1
    ref = solve_ivp(lambda _t, x: [x[1], -G * np.sin(x[0])], (0, t[-1]), s0, t_eval=t, rtol=1e-11, atol=1e-11)
    expected = camera.quantize(camera.render(ref.y[0][:, None], 24, rendering=dm.rendering)) / 255.0
    # float32 initial state: the angle agrees to ~1e-6 rad, a pixel to a grey level at most
    assert np.abs(frames[1].numpy() - expected).max() <= 1.5 / 255
    assert dm.known_largest_exponent == 0.0 and dm.sample_period == 0.1
    assert small_module(dm.data_dir, damping=0.1).known_largest_exponent is None


# ------------------------------------------------------------------ torque-driven chains
def test_driven_pendulum_energy_changes_by_the_work_of_its_torques(tmp_path):
    """Undamped simple pendulum under a torque held over each frame: the energy gained over a frame is the work
    ``u[t] (theta[t+1] - theta[t])``, to RK4's accuracy; a free chain's data parameters name no torque."""
    dm = PendulumDataModule(n_train=6, n_test=2, torque_limit=3.0, data_dir=str(tmp_path), workers=1)
    arrays = dm.generate("train")
    assert arrays["u"].shape == (6, 100, 1) and arrays["u"].dtype == np.float32
    assert np.abs(arrays["u"]).max() <= 3.0 and np.abs(arrays["u"]).max() > 2.0
    q, v = arrays["state"][..., :1].astype(np.float64), arrays["state"][..., 1:].astype(np.float64)
    energy = chain_energy(q, v)
    work = arrays["u"][:, :-1, 0].astype(np.float64) * (q[:, 1:, 0] - q[:, :-1, 0])
    # float32 states: ~1e-6 relative on velocities up to ~10 rad/s, so ~1e-4 on the energy
    np.testing.assert_allclose(np.diff(energy, axis=1), work, atol=1e-4)
    assert np.abs(work).max() > 0.5  # the torques did work
    free = PendulumDataModule(n_train=6, n_test=2, data_dir=str(tmp_path), workers=1)
    assert not any(k.startswith("torque") for k in free.generator_params())
    assert "u" not in free.generate("train")


def test_excitation_is_a_smoothed_process_within_its_limit():
    """Stationary AR(1) of standard deviation ``limit / 2``, clipped at the limit (two standard deviations): the
    clipped normal's standard deviation in closed form, lag-one correlation near ``exp(-dt/tau)``; a longer
    horizon extends the same torques."""
    rngs = [np.random.default_rng([0, i]) for i in range(400)]
    u = drive.excitation(rngs, 200, 2, limit=100.0, correlation=0.5, frame_dt=0.1)
    assert u.shape == (400, 200, 2)
    c = 2.0  # E[min(X^2, c^2)] for X ~ N(0, 1)
    clipped_var = (2 * norm.cdf(c) - 1) - 2 * c * norm.pdf(c) + 2 * c * c * norm.sf(c)
    assert u.std() == pytest.approx(50.0 * math.sqrt(clipped_var), rel=0.01)
    lag1 = (u[:, 1:] * u[:, :-1]).mean() / u.var()
    assert lag1 == pytest.approx(math.exp(-0.2), abs=0.03)
    clipped = drive.excitation([np.random.default_rng([0, i]) for i in range(50)], 100, 1, 3.0, 0.5, 0.1)
    assert np.abs(clipped).max() == 3.0
    longer = drive.excitation([np.random.default_rng([0, i]) for i in range(400)], 300, 2, 100.0, 0.5, 0.1)
    np.testing.assert_array_equal(longer[:, :200], u)


def test_driven_datamodule_serves_torques_and_continues_them(tmp_path):
    dm = PendulumDataModule(n_train=4, n_test=2, torque_limit=2.0, data_dir=str(tmp_path), workers=1, batch_size=2)
    dm.prepare_data()
    dm.setup("fit")
    assert dm.input_dim == 1
    batch = next(iter(dm.train_dataloader()))
    assert batch["u"].shape == (2, 100, 1)
    raw = np.load(dm.split_file("train", "u"))
    np.testing.assert_array_equal(batch["u"].numpy(), raw[batch["index"].numpy()])
    stored = np.load(dm.split_file("train", "y_clean"))[[1]]
    frames = dm.true_measurements("train", [1], 100)
    np.testing.assert_array_equal((frames.numpy() * 255).round().astype(np.uint8), stored)


def test_energy_bound_stops_only_the_torques_that_pump_above_it(tmp_path):
    """``max_energy``: a frame's torque is the excitation's unless the chain is above the bound and the torque
    would do positive work, then 0; the energy still changes by the work, and exceeds the bound by at most one
    frame's work; the module's energy is the reference's shifted to hanging at rest (``g (1 + .. + n)``);
    true_measurements continues the gated torques (the stored frames again)."""
    bound = 22.0
    dm = PendulumDataModule(n_train=8, n_test=2, torque_limit=3.0, max_energy=bound, data_dir=str(tmp_path), workers=1)
    arrays = dm.generate("train")
    q, v = arrays["state"][..., :1].astype(np.float64), arrays["state"][..., 1:].astype(np.float64)
    energy = chain_energy(q, v) + G  # above hanging at rest
    np.testing.assert_allclose(sim.chain_energy(q, v), energy, atol=1e-9)
    params = dm.generator_params()
    rngs, _, _ = gen.initial_states(params, 0, range(8))
    raw = drive.excitation(rngs, 100, 1, 3.0, 0.5, 0.1)
    u = arrays["u"].astype(np.float64)
    pumping = (energy > bound) & (raw[..., 0] * v[..., 0] > 0)
    # float32 states: a frame within 1e-4 J of the bound may be judged either way
    clear = np.abs(energy - bound) > 1e-4
    np.testing.assert_array_equal(u[..., 0][clear & pumping], 0.0)
    np.testing.assert_allclose(u[..., 0][clear & ~pumping], raw[..., 0][clear & ~pumping], rtol=1e-6)
    assert pumping.sum() > 20  # the bound acted
    work = u[:, :-1, 0] * (q[:, 1:, 0] - q[:, :-1, 0])
    np.testing.assert_allclose(np.diff(energy, axis=1), work, atol=1e-4)
    assert energy.max() <= bound + np.abs(work).max() and energy.max() > 0.9 * bound
    dm.prepare_data()
    stored = np.load(dm.split_file("train", "y_clean"))[[3]]
    frames = dm.true_measurements("train", [3], 100)
    np.testing.assert_array_equal((frames.numpy() * 255).round().astype(np.uint8), stored)
    free = PendulumDataModule(n_train=8, n_test=2, torque_limit=3.0, data_dir=str(tmp_path), workers=1)
    assert "max_energy" not in free.generator_params()  # the unbounded data's cache is unchanged
    with pytest.raises(ValueError, match="max_energy bounds the excitation"):
        PendulumDataModule(max_energy=20.0, data_dir=str(tmp_path))


@pytest.mark.parametrize(("override", "balance"), [(None, True), (0.5, True), (None, False)])
def test_closed_loop_identification_drives_its_share_by_the_swing_up_controller(tmp_path, override, balance):
    """``closed_loop_share``: the trajectories picked by index get the swing-up-and-balance torque plus a share of
    their excitation, frame by frame in feedback (a naive loop: the controller in closed form, one frame simulated
    at a time), and end up held upright; the others keep their excitation; true_measurements re-runs the loop.
    ``closed_loop_override``: frames whose excitation exceeds that share of the limit get the excitation alone;
    ``closed_loop_balance: false``: so do the frames within the catch (0.5 rad) of upright."""
    share, noise, limit = 0.5, 0.5, 3.0
    dm = PendulumDataModule(
        n_train=6, n_test=2, torque_limit=limit, closed_loop_share=share, closed_loop_noise=noise,
        closed_loop_override=override, closed_loop_balance=balance, data_dir=str(tmp_path), workers=1,
    )  # fmt: skip
    picked = drive.closed_loop(range(1000), 0.3)
    assert picked.sum() == 300 and picked[:10].sum() == 3
    arrays = dm.generate("train")
    params = dm.generator_params()
    rngs, q0, v0 = gen.initial_states(params, 0, range(6))
    raw = drive.excitation(rngs, 100, 1, limit, 0.5, 0.1)
    closed = drive.closed_loop(range(6), share)
    assert closed.sum() == 3
    model = sim.pendulum_model(1)
    for i in range(6):
        if not closed[i]:
            np.testing.assert_array_equal(arrays["u"][i], raw[i].astype(np.float32))
            continue
        q, v, upright, overridden = float(q0[i, 0]), float(v0[i, 0]), [], 0
        for t in range(100):
            np.testing.assert_allclose(arrays["state"][i, t], [q, v], rtol=1e-5, atol=1e-5)
            d = math.remainder(q - math.pi, 2 * math.pi)
            energy = 0.5 * v * v + G * (1 - math.cos(q))
            ctrl = -(9 + G) * d - 6 * v if abs(d) < 0.5 else 1.0 * (2 * G - energy) * v
            u = min(max(min(max(ctrl, -limit), limit) + noise * raw[i, t, 0], -limit), limit)
            if (override is not None and abs(raw[i, t, 0]) > override * limit) or (not balance and abs(d) < 0.5):
                u, overridden = float(raw[i, t, 0]), overridden + 1
            np.testing.assert_allclose(arrays["u"][i, t, 0], u, rtol=1e-5, atol=1e-6)
            upright.append(abs(d) < 0.3)
            qs, vs, _ = sim.simulate(model, model.createData(), [[q]], [[v]], 2, 20, 5e-3, 0.0, np.full((1, 1, 1), u))
            q, v = float(qs[0, 1, 0]), float(vs[0, 1, 0])
        if override is None and balance:
            assert all(upright[80:])  # swung up and held: upright over the last 2 s (the control task's success)
        else:
            assert 0 < overridden < 100  # some frames, not all, handed to the excitation
    dm.prepare_data()
    index = int(np.flatnonzero(closed)[0])
    stored = np.load(dm.split_file("train", "y_clean"))[[index]]
    frames = dm.true_measurements("train", [index], 100)
    np.testing.assert_array_equal((frames.numpy() * 255).round().astype(np.uint8), stored)
    assert "closed_loop_share" not in PendulumDataModule(torque_limit=3.0, data_dir=str(tmp_path)).generator_params()
    with pytest.raises(ValueError, match="closed_loop_share drives the simple pendulum"):
        PendulumDataModule(n_links=2, torque_limit=3.0, closed_loop_share=0.3, data_dir=str(tmp_path))
    assert (
        "closed_loop_override"
        not in PendulumDataModule(torque_limit=3.0, closed_loop_share=0.3, data_dir=str(tmp_path)).generator_params()
    )  # the shipped data's cache is unchanged
    with pytest.raises(ValueError, match="closed_loop_override hands frames"):
        PendulumDataModule(torque_limit=3.0, closed_loop_override=0.5, data_dir=str(tmp_path))
    assert (
        "closed_loop_balance"
        not in PendulumDataModule(torque_limit=3.0, closed_loop_share=0.3, data_dir=str(tmp_path)).generator_params()
    )
    with pytest.raises(ValueError, match="closed_loop_balance: false lets"):
        PendulumDataModule(torque_limit=3.0, closed_loop_balance=False, data_dir=str(tmp_path))
