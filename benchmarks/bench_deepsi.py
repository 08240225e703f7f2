"""ssm-ms beside deepSI's SUBNET, its closest published peer, on the same data, time budget and test sequences;
writes benchmarks/results/deepsi_<system>.md (and .json) for each system run.

Run from the repository root, with deepSI installed (``make peers``)::

    python benchmarks/bench_deepsi.py [--systems pendulum lorenz] [--tiny]

(``--tiny``: a few trajectories and steps, a minute: the script's own check, no figures worth reading.)

SUBNET (Beintema, Toth & Schoukens 2021; PyPI ``deepsi``) learns ``x+ = f(x, u)``, ``y = h(x)`` with an encoder
from the ``na`` past outputs and ``nb`` past inputs to the state, trained on a truncated simulation loss over
``T`` steps from every window of the data: the relative of multiple shooting that estimates each piece's initial
state with a network instead of holding it as a free parameter.

Each system:

1. the data are generated (or read from the cache) by ssm-ms's data module of the system's config;
2. ssm-ms trains with ``python cli.py fit --config benchmarks/configs/deepsi_<system>.yaml`` (fixed epochs), then
   each config of ``--ssm-configs`` likewise (variants side by side: ``deepsi_pendulum_amortised.yaml``, amortised
   nodes; a config of ``FileDataModule``, as ``deepsi_pendulum_amortised_fc.yaml``, reads the same training
   sequences from the ``.npz`` the bench writes, as ``train_path``, to cut them into windows at every sample); the
   longest wall time of those commands is the budget;
3. deepSI trains a SUBNET (its defaults: ``nx = 10``, residual MLPs of 2 x 64 units, Adam at 1e-3, batches of
   256 windows, ``T = 50``) on the same training sequences for the same wall time, in chunks of ``--val-freq``
   iterations with one optimizer; its validation simulates 16 training sequences over the test's horizon;
   both its last and its best-on-validation models are scored;
4. both forecast every test sequence ``n_predict`` steps after ``n_filter`` given measurements (and, for the
   pendulum, the torques of all steps): ssm-ms's states from its UKF with the learned ``f`` and ``g`` (an SSM with
   amortised nodes: its node encoder on the last given samples, as in its training), deepSI's
   from its encoder on the last ``na`` / ``nb`` given samples; the score is the MSE against the noiseless
   measurement in original units (the encoder's sine and cosine; Lorenz's x), the same code for both.

One torch job at a time: the two trainings run one after the other, 2 torch threads each.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import datetime
import importlib.metadata
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from benchmarks.report import provenance  # noqa: E402
from experiments.configs import build_datamodule, load_config  # noqa: E402
from ssm_ms.checkpointing import datamodule_state  # noqa: E402
from ssm_ms.inference.filter_module import FilterForecaster  # noqa: E402
from ssm_ms.inference.simulation import free_run, initial_state, model_name  # noqa: E402
from ssm_ms.loading import load_ssm  # noqa: E402
from ssm_ms.runtime.machine import CpuWatch, describe, quiet_note  # noqa: E402

# Per system: ssm-ms's config, the test protocol, the UKF's noise (ssm-ms's training units; or the UKF stage config
# that holds it) and deepSI's windows.
SYSTEMS = {
    "pendulum": {
        "title": "torque-driven pendulum, joint encoder (sin, cos of the angle noised by 0.05 rad)",
        "config": "benchmarks/configs/deepsi_pendulum.yaml",
        "n_filter": 50,
        "n_predict": 50,
        "ukf": {"measurement_var": 0.05**2, "process_var": 1e-6, "init_var": 0.1},
        "deepsi": {"na": 20, "nb": 20},
        "units": "(sin, cos)^2",
        "tiny": {"data": {"n_train": 16, "n_test": 8}, "epochs": 2},
    },
    "lorenz": {
        "title": "Lorenz, noisy x (std 2.5)",
        "config": "benchmarks/configs/deepsi_lorenz.yaml",
        "n_filter": 1990,
        "n_predict": 10,
        "ukf": "configs/cpu/lorenz_T1000_ukf.yaml",  # the CPU-sized Lorenz's UKF stage: its noise settings
        "deepsi": {"na": 50, "nb": 50},
        "units": "x^2",
        "tiny": {"data": {"n_train": 1, "train_steps": 5000, "n_test": 4}, "epochs": 2},
    },
}
VAL_SEQUENCES = 16  # deepSI's validation: simulations of as many training sequences over the test's horizon


def seed_tag(seed: int | None, sep: str) -> str:
    """What a seeded run adds to its files' names (``sep`` + ``seed<N>``); nothing for an unseeded one."""
    return "" if seed is None else f"{sep}seed{seed}"


# where the files go, which runs are made, and the seed: not what a run of one system computes
NOT_SETTINGS = ("seed", "work", "out_dir", "results_dir", "dir_placement", "systems", "benchmarks")


def setting(argv: list[str]) -> dict:
    """What a run with the arguments ``argv`` computes for a system, less its seed: what the seeds summarised
    together must share (defaults filled in, so that ``--val-freq 250`` and nothing are one setting; an argument this
    version of the script does not know, from an older run's command, is left out)."""
    parsed = vars(build_parser().parse_known_args(argv)[0])
    return {k: v for k, v in parsed.items() if k not in NOT_SETTINGS}


def check_seed_folder(out_dir: Path, stem: str, args) -> None:
    """Refuse, before training, a seeded run whose folder holds another seed's run of another setting (another
    ``--deepsi-seconds`` or ``--ssm-configs``, say): the summary over seeds would mix the two."""
    mine = setting(args.argv)
    for path in sorted(out_dir.glob(f"{stem}_seed*.json")):
        run = json.loads(path.read_text())
        if run.get("seed") == args.seed:
            continue  # this run replaces it
        command = run["provenance"][-1].split(": ", 1)[1].strip("`")
        theirs = setting(shlex.split(command)[2:])
        differ = ", ".join(f"{k} {theirs[k]} there, {mine[k]} here" for k in mine if theirs[k] != mine[k])
        if differ:
            sys.exit(
                f"error: {path} is a run of another setting ({differ}), and {stem}_seeds.md would average the two: "
                "give this setting its own --out-dir"
            )


def seed_deepsi(seed: int | None) -> None:
    if seed is not None:
        torch.manual_seed(seed)
        np.random.seed(seed)  # deepSI draws its batches with numpy


def cli_overrides(overrides: dict) -> list[str]:
    return [f"--data.init_args.{k}={v if isinstance(v, str) else json.dumps(v)}" for k, v in overrides.items()]


def train_ssm_ms(
    config: str, data_overrides: dict, epochs: int | None, save_dir: Path, version: str, log: Path, seed: int | None
):
    """``cli.py fit`` of an ssm-ms config (``seed``: its ``seed_everything``, else the config's); returns
    (checkpoint, wall seconds, epochs)."""
    cmd = [
        sys.executable,
        "cli.py",
        "fit",
        "--config",
        config,
        f"--trainer.logger.init_args.save_dir={save_dir}",
        f"--trainer.logger.init_args.version={version}",
        "--trainer.enable_progress_bar=false",
        *cli_overrides(data_overrides),
    ]
    if epochs is not None:
        cmd.append(f"--trainer.max_epochs={epochs}")
    if seed is not None:
        cmd.append(f"--seed_everything={seed}")
    print("ssm-ms:", shlex.join(cmd), f"(log {log})", flush=True)
    start = time.perf_counter()
    with open(log, "w") as out:
        done = subprocess.run(cmd, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT)
    seconds = time.perf_counter() - start
    if done.returncode:
        sys.exit(f"ssm-ms training failed (exit {done.returncode}): see {log}")
    name = load_config(ROOT / config)["trainer"]["logger"]["init_args"]["name"]
    ckpt = save_dir / name / version / "checkpoints" / "last.ckpt"
    epochs_done = torch.load(ckpt, map_location="cpu", weights_only=False)["epoch"] + 1
    return ckpt, seconds, epochs_done


@torch.inference_mode()
def forecast_ssm_ms(ckpt: Path, system: dict, dm, y: np.ndarray, u: np.ndarray | None) -> np.ndarray:
    """ssm-ms's forecasts ``[N, n_predict, p]`` (original units): the state from the given steps (the UKF; an SSM with
    amortised nodes: its node encoder, as in training), then ``f`` and ``g``."""
    k, p = system["n_filter"], system["n_predict"]
    ssm, checkpoint = load_ssm(ckpt)
    if ssm.node_encoder is not None:
        dm.load_state_dict(datamodule_state(checkpoint)[1])
        out = []
        for start in range(0, len(y), 100):
            yb = dm.normalizer.normalize(torch.from_numpy(np.array(y[start : start + 100, :k])))
            ub = None
            if u is not None:
                ub = dm.input_normalizer.normalize(torch.from_numpy(np.array(u[start : start + 100, : k + p])))
            x, _ = initial_state(ssm, yb, ub)
            predicted, _ = free_run(ssm.f, ssm.g, x, p, None if ub is None else ub[:, k:])
            out.append(dm.normalizer.denormalize(predicted).numpy())
        return np.concatenate(out)
    settings = system["ukf"]
    if isinstance(settings, str):  # a UKF stage's config
        stage = load_config(ROOT / settings)["model"]["init_args"]
        settings = {key: stage[key] for key in ("measurement_var", "process_var", "init_var")}
    forecaster = FilterForecaster(str(ckpt), n_filter=k, n_predict=p, method="ukf", **settings)
    forecaster.eval()
    dm.load_state_dict(datamodule_state(checkpoint)[1])  # the normalisation the SSM was trained with
    out = []
    for start in range(0, len(y), 100):
        yb = dm.normalizer.normalize(torch.from_numpy(np.array(y[start : start + 100, :k])))
        ub = None
        if u is not None:
            ub = dm.input_normalizer.normalize(torch.from_numpy(np.array(u[start : start + 100, : k + p])))
        predicted = forecaster.forecast(yb, p, ub).predicted
        out.append(dm.normalizer.denormalize(predicted).numpy())
    return np.concatenate(out)


def io_data(deepSI, y: np.ndarray, u: np.ndarray | None, dt: float) -> list:
    """deepSI's data: one ``Input_output_data`` per sequence (inputs of width 0 where the system has none)."""
    seqs = []
    for i in range(len(y)):
        ui = np.zeros((y.shape[1], 0), np.float32) if u is None else np.asarray(u[i], np.float32)
        seqs.append(deepSI.Input_output_data(u=ui, y=np.asarray(y[i], np.float32), sampling_time=dt))
    return seqs


def train_deepsi(deepSI, train: list, val: list, budget: float, system: dict, val_freq: int, log: Path):
    """SUBNET trained for ``budget`` wall seconds; returns (last model, best model, iterations, seconds, curve)."""
    nu, ny, norm = deepSI.get_nu_ny_and_auto_norm(train)
    model = deepSI.SUBNET(nu, ny, norm, **system["deepsi"])
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    best, best_val, iterations, curve = copy.deepcopy(model), float("inf"), 0, []
    start = time.perf_counter()
    with open(log, "w") as out:
        while time.perf_counter() - start < budget:
            # deepSI.fit validates at its first and last iteration and hands back the best of the two: the chunk's
            # last model is taken from what it returns, the best over all chunks kept here
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):  # its prints and progress bar
                d = deepSI.fit(
                    model, train, val, n_its=val_freq, T=50, batch_size=256, val_freq=val_freq, optimizer=optimizer
                )
            model.load_state_dict(d["last_model"].state_dict())
            iterations += val_freq
            nrms = float(d["NRMS_val"][-1])
            curve.append((iterations, round(time.perf_counter() - start, 1), nrms))
            print(f"deepSI: {iterations} iterations, {curve[-1][1]:.0f} s, validation NRMS {nrms:.4f}", flush=True)
            if nrms <= best_val:
                best, best_val = copy.deepcopy(model), nrms
    return model, best, iterations, time.perf_counter() - start, curve


@torch.no_grad()
def forecast_deepsi(model, system: dict, y: np.ndarray, u: np.ndarray | None) -> np.ndarray:
    k, p = system["n_filter"], system["n_predict"]
    na, nb = system["deepsi"]["na"], system["deepsi"]["nb"]
    u = np.zeros((*y.shape[:2], 0), np.float32) if u is None else u
    y_t, u_t = torch.from_numpy(np.array(y, np.float32)), torch.from_numpy(np.array(u, np.float32))
    model.eval()
    out = [
        model(u_t[s : s + 100, k - nb : k], y_t[s : s + 100, k - na : k], u_t[s : s + 100, k : k + p]).numpy()
        for s in range(0, len(y), 100)
    ]
    return np.concatenate(out).reshape(len(y), p, -1)


def scores(predicted: np.ndarray, truth: np.ndarray) -> dict:
    err = (predicted.reshape(truth.shape) - truth) ** 2
    return {"mse": float(err.mean()), "first": float(err[:, 0].mean()), "last": float(err[:, -1].mean())}


def run_system(name: str, args, deepSI, work: Path) -> dict:
    system = SYSTEMS[name]
    config = load_config(ROOT / system["config"])
    data_overrides = dict(system["tiny"]["data"]) if args.tiny else {}
    dm = build_datamodule(config, **data_overrides)
    dm.prepare_data()  # generated once, before any clock starts
    train, test = dm.load_arrays("train"), dm.load_arrays("test")
    k, p = system["n_filter"], system["n_predict"]
    version = f"{name}{seed_tag(args.seed, '-')}-{datetime.datetime.now(datetime.timezone.utc):%Y%m%d-%H%M%S}"
    truth = np.asarray(test["y_clean"])[:, k : k + p]
    u_test = np.asarray(test["u"]) if "u" in test else None
    configs = [system["config"], *(args.ssm_configs or [])]
    reads_files = [load_config(ROOT / c)["data"]["class_path"].endswith(".FileDataModule") for c in configs]
    train_file = work / f"{version}-train.npz"  # the same training data for a config of a user's recordings
    if any(reads_files):
        np.savez(train_file, y=np.asarray(train["y"]), **({"u": np.asarray(train["u"])} if "u" in train else {}))
    ours = []  # the system's own config first (the ratios' reference), then --ssm-configs
    for i, config_path in enumerate(configs):
        run = version if i == 0 else f"{version}-{i}"
        ckpt, ssm_seconds, epochs = train_ssm_ms(
            config_path,
            {"train_path": str(train_file)} if reads_files[i] else data_overrides,
            system["tiny"]["epochs"] if args.tiny else None,
            work,
            run,
            work / f"{run}-ssm_ms.log",
            args.seed,
        )
        print(f"ssm-ms ({config_path}): {epochs} epochs in {ssm_seconds:.0f} s", flush=True)
        ssm = load_ssm(ckpt)[0]
        how = "amortised nodes; node encoder" if ssm.node_encoder is not None else "multiple shooting; UKF"
        label = f"ssm-ms ({model_name(ssm)}, {how}; `{config_path}`)"
        ours.append(
            {
                "method": label,
                "seconds": ssm_seconds,
                "steps": f"{epochs} epochs",
                **scores(forecast_ssm_ms(ckpt, system, dm, test["y"], u_test), truth),
            }
        )

    dt = float(dm.sample_period)
    u_train = np.asarray(train["u"]) if "u" in train else None
    train_seqs = io_data(deepSI, train["y"], u_train, dt)
    horizon = max(system["deepsi"]["na"], system["deepsi"]["nb"]) + p
    val_y = np.asarray(train["y"][:VAL_SEQUENCES, :horizon])
    val_u = None if u_train is None else u_train[:VAL_SEQUENCES, :horizon]
    val_seqs = io_data(deepSI, val_y, val_u, dt)
    budget = args.deepsi_seconds or max(row["seconds"] for row in ours)  # the longest of ssm-ms's fits
    seed_deepsi(args.seed)
    last, best, iterations, deepsi_seconds, curve = train_deepsi(
        deepSI, train_seqs, val_seqs, budget, system, args.val_freq, work / f"{version}-deepsi.log"
    )
    rows = [
        *ours,
        {
            "method": "deepSI SUBNET, last model",
            "seconds": deepsi_seconds,
            "steps": f"{iterations} iterations",
            **scores(forecast_deepsi(last, system, test["y"], u_test), truth),
        },
        {
            "method": "deepSI SUBNET, best on validation",
            "seconds": deepsi_seconds,
            "steps": f"{iterations} iterations",
            **scores(forecast_deepsi(best, system, test["y"], u_test), truth),
        },
    ]
    return {
        "system": name,
        "seed": args.seed,
        "title": system["title"],
        "units": system["units"],
        "n_filter": k,
        "n_predict": p,
        "train_shape": list(np.shape(train["y"])),
        "test_shape": list(np.shape(test["y"])),
        "truth_var": float(truth.var()),
        "ssm_ms_config": ", ".join(f"`{c}`" for c in configs),
        "deepsi_settings": {**system["deepsi"], "nx": 10, "T": 50, "batch_size": 256, "lr": 1e-3},
        "deepsi_curve": curve,
        "rows": rows,
    }


def write(r: dict, args, watch_note: str, out: Path) -> None:
    """One system's results file (and its .json beside it, with the run's provenance lines)."""
    ref = r["rows"][0]["mse"]
    r["provenance"] = provenance("benchmarks/bench_deepsi.py", args.argv)
    seeded = "" if r["seed"] is None else f", seed {r['seed']}"
    lines = [
        f"# ssm-ms beside deepSI's SUBNET: {r['title']} (same data, same time budget, same test sequences{seeded})",
        "",
        *r["provenance"],
        f"- Others' CPU use: {watch_note}",
        f"- deepSI {args.deepsi_version}; set-up and protocol: the docstring of `benchmarks/bench_deepsi.py`.",
        "- Score: MSE of the forecast against the noiseless measurement, mean over test sequences and predicted "
        "steps (first / last: the first and last predicted step alone); `/ ssm-ms`: the ratio of the MSEs.",
        f"- Training sequences {r['train_shape']}, test sequences {r['test_shape']}; forecast {r['n_predict']} "
        f"steps after {r['n_filter']} given; variance of the true values forecast: {r['truth_var']:.4g} "
        f"{r['units']}. ssm-ms: {r['ssm_ms_config']}; deepSI: {r['deepsi_settings']}.",
        "",
        f"| Method | training wall (s) | training | MSE ({r['units']}) | / ssm-ms | first step | last step |",
        "|---|---:|---|---:|---:|---:|---:|",
    ]
    for row in r["rows"]:
        lines.append(
            f"| {row['method']} | {row['seconds']:.0f} | {row['steps']} | {row['mse']:.4g} | "
            f"{row['mse'] / ref:.2f} | {row['first']:.4g} | {row['last']:.4g} |"
        )
    curve = ", ".join(f"{it}: {nrms:.3f}" for it, _, nrms in r["deepsi_curve"][:: max(1, len(r["deepsi_curve"]) // 12)])
    lines += ["", f"deepSI's validation NRMS by iteration: {curve}.", ""]
    out.write_text("\n".join(lines))
    out.with_suffix(".json").write_text(json.dumps(r, indent=1) + "\n")
    print(f"wrote {out} and {out.with_suffix('.json')}")


def write_seeds(runs: list[dict], out: Path) -> None:
    """The spread over seeds: ``runs`` (the .json of ``write``, one per seed, the same system) summarised per method,
    mean and sample standard deviation of the MSE, each seed's figure, and each run's provenance."""
    runs = sorted(runs, key=lambda r: r["seed"])
    methods = [row["method"] for row in runs[0]["rows"]]
    by_method = {
        m: [next((row["mse"] for row in r["rows"] if row["method"] == m), None) for r in runs] for m in methods
    }
    ref = float(np.mean([v for v in by_method[methods[0]] if v is not None]))
    r0 = runs[0]
    lines = [
        f"# ssm-ms beside deepSI's SUBNET over seeds: {r0['title']}",
        "",
        f"Generated by `benchmarks/bench_deepsi.py --seed N` from the runs' .json beside this file (one per seed; "
        f"each seed's own file has its table and deepSI's curve). Score: MSE of a {r0['n_predict']}-step forecast "
        f"after {r0['n_filter']} given steps, against the noiseless measurement ({r0['units']}); mean +- sample "
        "standard deviation over the seeds; `/ ssm-ms`: the ratio of the means to the first row's.",
        "",
        "| Method | seeds | MSE mean +- std | / ssm-ms | " + " | ".join(f"seed {r['seed']}" for r in runs) + " |",
        "|---|---:|---:|---:|" + "---:|" * len(runs),
    ]
    for m in methods:
        values = [v for v in by_method[m] if v is not None]
        spread = f"{np.mean(values):.4g}" + (f" +- {np.std(values, ddof=1):.2g}" if len(values) > 1 else "")
        cells = " | ".join("-" if v is None else f"{v:.4g}" for v in by_method[m])
        lines.append(f"| {m} | {len(values)} | {spread} | {np.mean(values) / ref:.2f} | {cells} |")
    lines += ["", "Runs:", ""]
    for r in runs:
        date, machine, command = (line.split(": ", 1)[1] for line in r["provenance"])
        lines.append(f"- seed {r['seed']}: {date}; {machine}; {command}")
    out.write_text("\n".join(lines) + "\n")
    print(f"wrote {out}")


# ---------------------------------------------------------------------------- the identification benchmarks
BENCHMARK_BUDGET = 720.0  # seconds: configs/benchmarks/parts/base.yaml's trainer.max_time, ssm-ms's budget on them


def run_benchmark(name: str, args, deepSI, work: Path) -> None:
    """deepSI's SUBNET on a benchmark of configs/benchmarks/ by ssm-ms's protocol: trained on the same windows'
    recording (the training recording less its held-out end, on which its validation simulates), for ssm-ms's
    budget; each test recording simulated from its first ``n_init`` samples (the encoder reads the last ``na`` /
    ``nb`` of them); its last and its best-on-validation models scored by the loader's metrics into
    ``results/benchmarks/<name>.json`` beside ssm-ms's rows (written by the library, its ``.md`` rendered by
    :mod:`experiments.benchmark_results`); both models saved as ``<work>/<name>-subnet-{last,best}.pt``
    (``torch.save``: benchmarks/bench_simulation.py times them)."""
    from experiments.benchmark_results import render_file
    from ssm_ms.forecasting.benchmark_results import write_benchmark_results
    from ssm_ms.inference.simulation import scores

    config = ROOT / "configs" / "benchmarks" / f"{name}.yaml"
    test_config = load_config(ROOT / "configs" / "benchmarks" / f"{name}_test.yaml")
    dm = build_datamodule(load_config(config), dir_placement=args.dir_placement)
    train, val = dm.raw_recordings("train"), dm.raw_recordings("val")
    dt = float(dm.sample_period or 1.0)
    as_io = [deepSI.Input_output_data(u=u, y=y, sampling_time=dt) for y, u in train]
    val_io = [deepSI.Input_output_data(u=u, y=y, sampling_time=dt) for y, u in val]
    settings = {"na": min(20, dm.n_init), "nb": min(20, dm.n_init)}
    system = {"deepsi": settings}
    budget = BENCHMARK_BUDGET if args.tiny is False and args.deepsi_seconds is None else args.deepsi_seconds or 30.0
    seeded = seed_tag(args.seed, "-")
    log = work / f"{name}{seeded}-deepsi.log"
    seed_deepsi(args.seed)
    watch = CpuWatch()
    last, best, iterations, seconds, curve = train_deepsi(deepSI, as_io, val_io, budget, system, args.val_freq, log)
    cpu_others = watch.others()  # what other processes ran during the fit: a shared CPU trains fewer iterations
    for label, model in (("last", last), ("best", best)):  # for benchmarks/bench_simulation.py --deepsi
        torch.save(model, work / f"{name}{seeded}-subnet-{label}.pt")
    results_dir = (
        Path(args.results_dir) if args.results_dir else ROOT / test_config["model"]["init_args"]["results_dir"]
    )
    n_init, k = dm.n_init, max(settings["na"], settings["nb"])

    def protocol(model, y: np.ndarray, u: np.ndarray) -> tuple[dict, np.ndarray, np.ndarray]:
        """A recording by the benchmark protocol: its row of scores, the measured and simulated output."""
        started = time.perf_counter()
        with torch.no_grad():
            model.eval()
            y_t, u_t = torch.as_tensor(y[None]), torch.as_tensor(u[None])
            sim = model(u_t[:, n_init - k : n_init], y_t[:, n_init - k : n_init], u_t[:, n_init:])[0].numpy()
        truth = y * dm.unit_scale
        simulated = np.concatenate([np.full((n_init, y.shape[1]), np.nan), sim.reshape(len(sim), -1)]) * dm.unit_scale
        finite = bool(np.isfinite(simulated[n_init:]).all())
        row = {"samples": len(y), "n_init": n_init, "seconds": round(time.perf_counter() - started, 2)}
        row.update(scores(truth, simulated, n_init) if finite else {"rmse": None, "nrmse": None, "fit_index": None})
        row["diverged_at"] = None if finite else int(n_init + np.argmax(~np.isfinite(simulated[n_init:]).all(1)))
        return row, truth, simulated

    for label, model in (("last model", last), ("best on validation", best)):
        rows, figures = {}, {}
        for test_name, (y, u) in zip(dm.test_names, dm.raw_recordings("test")):
            row, truth, simulated = protocol(model, y, u)
            rows[test_name], figures[test_name] = row, (truth, np.nan_to_num(simulated, nan=0.0))
        # the held-out end of the training recording by the same protocol: the validation ssm-ms's rows record
        val_row = protocol(model, *dm.raw_recordings("val")[0])[0]
        info = {
            "experiment": test_config["model"]["init_args"].get("experiment", name),
            "method": f"deepSI SUBNET, {label}",
            "model": "SUBNET",
            "state_dim": 10,
            "seed": args.seed,
            "validation": {
                "unit": dm.unit,
                "val_sim_rmse": val_row["rmse"],
                "epoch": None,
                # its time to the model scored: the best chunk's, or the whole budget for the last model
                "seconds": [c for c in curve if c[2] == min(n for *_, n in curve)][-1][1]
                if label == "best on validation"
                else round(seconds, 1),
                "cpu_others": None if cpu_others is None else round(cpu_others, 3),
            },
            "ssm_checkpoint": None,
            "inference": {"method": f"SUBNET's encoder of the last {k} of the first {n_init} samples"},
            "benchmark": dm.benchmark,
            "unit": dm.unit,
            "command": shlex.join(["python", "benchmarks/bench_deepsi.py", *args.argv]),
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "machine": describe(),
            "test_seconds": round(sum(r["seconds"] for r in rows.values()), 1),
            "training": {
                "seconds": round(seconds, 1),
                "iterations": iterations,
                "deepsi": args.deepsi_version,
                "settings": {**settings, "nx": 10, "T": 50, "batch_size": 256, "lr": 1e-3},
                "validation_nrms": curve,
            },
        }
        figures_dir = test_config["model"]["init_args"].get("figures_dir") if not args.results_dir else None
        render_file(write_benchmark_results(results_dir, info, rows, figures, figures_dir, n_init))
    print(f"deepSI on {name}: {iterations} iterations in {seconds:.0f} s; results in {results_dir}", flush=True)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--systems", nargs="*", choices=sorted(SYSTEMS), default=None)
    parser.add_argument(
        "--benchmarks",
        nargs="*",
        default=[],
        help="identification benchmarks of configs/benchmarks/ (silverbox, wiener_hammerstein, emps, cascaded_tanks): "
        "SUBNET by their protocol, into results/benchmarks/",
    )
    parser.add_argument("--dir-placement", default=None, help="the benchmarks' files (the loader's dir_placement)")
    parser.add_argument("--results-dir", default=None, help="the benchmarks' results (default: their test configs')")
    parser.add_argument("--tiny", action="store_true", help="a few trajectories and epochs: the script's check")
    parser.add_argument("--val-freq", type=int, default=250, help="deepSI iterations between validations")
    parser.add_argument("--deepsi-seconds", type=float, default=None, help="deepSI's budget (default: ssm-ms's time)")
    parser.add_argument("--work", default="runs/bench_deepsi", help="logs, checkpoints, deepSI's own files")
    parser.add_argument(
        "--ssm-configs",
        nargs="*",
        default=None,
        help="the systems: more ssm-ms configs trained and scored beside the system's own (e.g. amortised nodes)",
    )
    parser.add_argument(
        "--seed",
        type=int,
        default=None,
        help="torch's and numpy's seed, and ssm-ms's seed_everything; the benchmarks' rows are keyed by it, a "
        "system's run goes to deepsi_<system>_seed<N>.md and the spread over seeds to deepsi_<system>_seeds.md",
    )
    parser.add_argument(
        "--out-dir", default=None, help="where deepsi_<system>.md go (default benchmarks/results; --tiny: --work)"
    )
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    try:
        import deepSI
    except ImportError:
        sys.exit("deepSI is not installed: make peers (installs deepsi beside the pinned torch, without its deps)")
    args.deepsi_version = importlib.metadata.version("deepSI")
    work = (ROOT / args.work).resolve()
    work.mkdir(parents=True, exist_ok=True)
    (work / "home").mkdir(exist_ok=True)
    os.environ["HOME"] = str(work / "home")  # deepSI writes its checkpoints under ~/.deepSI-checkpoints
    torch.set_num_threads(2)
    out_dir = Path(args.out_dir) if args.out_dir else (work if args.tiny else ROOT / "benchmarks/results")
    out_dir.mkdir(parents=True, exist_ok=True)
    systems = args.systems if args.systems is not None else ([] if args.benchmarks else ["pendulum", "lorenz"])
    stems = {name: f"deepsi_{name}{'_tiny' * args.tiny}" for name in systems}
    if args.seed is not None:
        for stem in stems.values():
            check_seed_folder(out_dir, stem, args)
    for name in systems:  # each system's file as soon as it is done, with the CPU use of its own run
        watch = CpuWatch()
        result = run_system(name, args, deepSI, work)
        stem = stems[name]
        write(result, args, quiet_note(watch.others()), out_dir / f"{stem}{seed_tag(args.seed, '_')}.md")
        if args.seed is not None:
            seeds = [json.loads(p.read_text()) for p in sorted(out_dir.glob(f"{stem}_seed*.json"))]
            write_seeds(seeds, out_dir / f"{stem}_seeds.md")
    for name in args.benchmarks:
        run_benchmark(name, args, deepSI, work)


if __name__ == "__main__":
    main()
