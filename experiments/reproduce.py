"""One command per experiment: SSM fit -> the tests that need the SSM alone (UKF test, states fitted by optimisation,
control test with the UKF, where their configs exist) -> encoder fit -> test (-> the control again, the encoder
estimating the state), then every baseline of the experiment (fit -> test); or one baseline alone. The SSM's own tests
come first: they train nothing (seconds to minutes), and their rows land even where a long encoder stage then stops or
fails.

    python -m experiments.reproduce pendulum            # the stages configs/experiments.yaml names for pendulum
    python -m experiments.reproduce pendulum --size cpu # the CPU-sized twins under configs/cpu/
    python -m experiments.reproduce pendulum_lstm       # configs/baselines/pendulum_lstm.yaml alone
    python -m experiments.reproduce pendulum --no-baselines
    python -m experiments.reproduce lorenz_T1000 --no-encoder --no-baselines   # the SSM and its UKF test only
    python -m experiments.reproduce pendulum --encoder-epochs 120   # the encoder stage on a stated epoch budget
    python -m experiments.reproduce pendulum_lstm --baseline-epochs 120   # a baseline on a stated epoch budget
    python -m experiments.reproduce lorenz_T1000 --size cpu --seed 1  # another seed: results/lorenz_T1000_cpu_seed1.md
    python -m experiments.reproduce pendulum -- --trainer.max_epochs 1   # options after -- go to every stage's cli.py
    python -m experiments.reproduce silverbox -- --data.init_args.dir_placement ../shared/data/nonlinear_benchmarks
                                                   # a benchmark: configs/benchmarks/silverbox{,_test}.yaml

(``make reproduce EXP=pendulum [SIZE=cpu] [SEED=1] [ARGS="..."]``.) Options after ``--`` (make's ``ARGS``) are
appended to every stage's ``python cli.py`` command, after the stage's own: a smoke test of the whole pipeline
(``-- --trainer.max_epochs 1 --trainer.limit_train_batches 2``), or another data directory; they are part of the
recorded commands, and a resumed run must be given the same. ``--seed N`` runs every stage with ``--seed_everything N``:
the networks' and shooting nodes' initial values change; the data and their order do not (they follow the data
section's own ``seed``). Its results go to ``results/<experiment>_seed<N>.md``; ``python -m experiments.seeds
<experiment>`` gathers the seeds' scores as mean and std.

Each stage is ``python cli.py ...`` in its own process, logged under ``runs/<name>/reproduce-<stamp>/``, so the
checkpoints each stage hands to the next are known: an SSM's ``last.ckpt``; an encoder's or a baseline's
``best.ckpt`` where its config keeps its best epoch (:func:`experiments.pipeline.tested_checkpoint`), else its ``last.ckpt``. Every
method lands in the same ``results/<experiment>.md``, which ends with the commands and their durations.

Ctrl-C (or ``kill <pid>``, SIGTERM or SIGINT) during a stage stops the stage as ``fit`` stops (its last completed epoch
kept); this process waits for it, prints which stage was interrupted, the command that resumes that stage alone
(``--ckpt_path`` its ``last.ckpt``) and the one that resumes the whole pipeline, and exits with status 130. A failing
stage ends in one ``error:`` line naming it, with the stage's status. No traceback either way; the later stages do
not run. See :func:`experiments.pipeline.run_stage`.

    python -m experiments.reproduce pendulum --resume reproduce-20261125-040251   # finish that run (make: RESUME=...)

``--resume VERSION`` finishes a run that stopped, whatever stopped it (Ctrl-C, ``kill``, a crash, the machine going
away while ``runs/`` stays): the stages it finished are not run again, its interrupted ``fit`` continues from its
last completed epoch, then the remaining stages and the results file run as usual. Each run keeps its record in
``<first stage's run folder>/reproduce.json`` (see :class:`experiments.pipeline.Pipeline`). The epoch budgets may be raised on resume
(``--resume VERSION --encoder-epochs 330``): that fit continues to the new count and the stages depending on it run
again. ``--no-encoder`` may be given or dropped on resume: dropped, a run that ended without its encoder gains the
encoder's stages (the finished ones are not run again); given, a run whose encoder stage cannot finish on this machine
ends with the SSM's own tests and its results file (the encoder's ``last.ckpt`` kept for a resume without it).
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
from datetime import datetime
from pathlib import Path

from experiments import configs
from experiments.benchmark_results import CROSS_VALIDATED
from experiments.configs import ROOT, experiment_name, logger_dir, results_dir
from experiments.pipeline import Pipeline, tested_checkpoint, without_option
from experiments.registry import LISTED, REGISTRY, read_registry


def known_experiments(registry: dict, size: str) -> list[str]:
    """Every name ``make reproduce EXP=...`` takes at ``size``: experiments, baselines alone, suites, benchmarks."""
    experiments = registry.get("experiments", {})
    known = [name for name, sizes in experiments.items() if size in sizes]
    known += [Path(p).stem for sizes in experiments.values() for p in sizes.get(size, {}).get("baselines", [])]
    return sorted({*known, *registry.get("suites", {}), *registry.get("benchmarks", {})})


def main(argv: list[str] | None = None) -> None:
    """``make reproduce``: the stages of one experiment (see the module docstring); a config that cannot be composed
    stops it with one line naming the file, before any stage runs."""
    try:
        _main(argv)
    except configs.ConfigError as e:
        raise SystemExit(f"error: {e}") from None


def _main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("experiment", help="e.g. pendulum, quad, lorenz_T1000, or a baseline: pendulum_lstm")
    parser.add_argument("--size", choices=["paper", "cpu"], default="paper")
    parser.add_argument("--no-baselines", action="store_true", help="only the SSM and its inference stages")
    parser.add_argument(
        "--no-encoder",
        action="store_true",
        help="no encoder stage, nor the stages that need it: the SSM and the tests of the SSM alone (UKF, states "
        "fitted by optimisation, control with the UKF); for experiments whose encoder does not fit the machine "
        "(may be given or dropped on resume)",
    )
    parser.add_argument(
        "--encoder-epochs",
        type=int,
        default=None,
        metavar="N",
        help="train the encoder stage for N epochs instead of its config's max_epochs (a budget for "
        "machines where the paper's count does not fit; the results file lists the command)",
    )
    parser.add_argument(
        "--baseline-epochs",
        type=int,
        default=None,
        metavar="N",
        help="train each baseline (LSTM, RKN) for N epochs instead of its config's max_epochs (the "
        "same kind of budget)",
    )
    parser.add_argument(
        "--seed",
        type=int,
        default=None,
        metavar="N",
        help="every stage with --seed_everything N instead of the configs' seed; results go to "
        "results/<experiment>_seed<N>.md",
    )
    parser.add_argument(
        "--orders",
        type=int,
        nargs="+",
        default=None,
        metavar="D",
        help="a benchmark: one fit per latent dimension D (state_dim, the same budget each); the one whose validation "
        "on the held-out end of the training recording (val/sim_rmse) is lowest is tested",
    )
    parser.add_argument(
        "--folds",
        type=int,
        default=None,
        metavar="K",
        help="a benchmark: cross-validation over time, K fits (per order) each holding out another 1/K of the "
        "training recording (val_fraction 1/K, val_at k/K); the fit that holds out the end is the one tested, the "
        "order chosen by the mean of the K validation scores, and the scores go to the results file",
    )
    parser.add_argument(
        "--resume",
        default=None,
        metavar="VERSION",
        help="finish the run of this version (reproduce-<date>-<time>, printed when it stopped; the "
        "same experiment and options; the epoch budgets may be raised): its finished stages are not run "
        "again, its interrupted fit, or a fit whose budget was raised, continues from its last.ckpt",
    )
    argv = list(sys.argv[1:] if argv is None else argv)
    stage_args = argv[argv.index("--") + 1 :] if "--" in argv else []
    own = argv[: argv.index("--")] if "--" in argv else argv
    opts = parser.parse_args(own)
    opts.stage_args = stage_args
    for name in ("encoder_epochs", "baseline_epochs"):
        if getattr(opts, name) is not None and getattr(opts, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(opts, name)}")
    if opts.seed is not None and opts.seed < 0:
        parser.error(f"--seed must be >= 0, got {opts.seed}")
    registry = read_registry()
    if opts.orders is not None and opts.experiment not in registry.get("benchmarks", {}):
        parser.error("--orders chooses a benchmark's latent dimension (configs/benchmarks/): not for this experiment")
    if opts.folds is not None and opts.experiment not in registry.get("benchmarks", {}):
        parser.error("--folds cross-validates a benchmark's fit (configs/benchmarks/): not for this experiment")
    if opts.folds is not None and opts.folds < 2:
        parser.error(f"--folds must be >= 2 (the held-out end and at least one other segment), got {opts.folds}")
    if opts.no_encoder and opts.encoder_epochs is not None:
        parser.error("--encoder-epochs budgets the encoder stage that --no-encoder leaves out: give one of the two")
    suite = registry.get("suites", {}).get(opts.experiment)
    if suite is not None:  # several experiments into one results file, one after the other
        if opts.resume:
            parser.error(f"{opts.experiment} is a suite of experiments: resume each with its own reproduce command")
        if opts.no_encoder:  # a suite's experiments may train on what an earlier one's encoder-driven control records
            parser.error(
                f"--no-encoder: {opts.experiment} is a suite of experiments: give it to one experiment at a time"
            )
        for experiment in suite:
            main([experiment, *argv[1:]])
        return
    benchmark = registry.get("benchmarks", {}).get(opts.experiment)
    if benchmark is not None:
        run_benchmark(opts, argv, ROOT / benchmark["fit"], ROOT / benchmark["test"])
        return
    stages = {
        kind: [ROOT / p for p in paths] if kind in LISTED else ROOT / paths
        for kind, paths in registry.get("experiments", {}).get(opts.experiment, {}).get(opts.size, {}).items()
    }
    ssm_cfg, enc_cfg, record_cfg = (stages.get(k) for k in ("ssm", "encoder", "record"))
    controls = stages.get("control", [])
    alone = [
        ROOT / path
        for experiment in registry.get("experiments", {}).values()
        for path in experiment.get(opts.size, {}).get("baselines", [])
        if Path(path).stem == opts.experiment
    ]
    if alone:
        baselines, ssm_stages = alone[:1], False
    elif ssm_cfg is not None:
        baselines = [] if opts.no_baselines else stages.get("baselines", [])
        ssm_stages = True
    elif controls:  # a controller without a learned model (the true one): its tests alone
        baselines, ssm_stages = [], False
    else:
        raise SystemExit(
            f"no {opts.size}-size experiment {opts.experiment!r} in {REGISTRY.relative_to(ROOT)}: choose among "
            f"{known_experiments(registry, opts.size)}"
        )
    ssm_tests = [stages[k] for k in ("ukf", "optimise") if k in stages] + controls  # of the SSM, nothing to train
    if opts.no_encoder and ssm_stages and not ssm_tests:
        parser.error(
            f"--no-encoder: {opts.experiment} has no test of its SSM alone (no ukf, optimise or control stage in "
            f"{REGISTRY.relative_to(ROOT)}): without its encoder nothing would score it; drop --no-encoder"
        )
    use_encoder = enc_cfg is not None and not opts.no_encoder
    seeded = "" if opts.seed is None else f"seed{opts.seed}"
    version = opts.resume or "reproduce-" + (seeded + "-" if seeded else "") + datetime.now().strftime("%Y%m%d-%H%M%S")
    if "/" in version or not version.startswith("reproduce-"):
        parser.error(f"--resume takes the version folder's name (reproduce-<date>-<time>), got {version!r}")
    options = without_option(argv, "--resume")
    first = ssm_cfg if ssm_stages else baselines[0] if baselines else controls[0]
    # options make does not pass: the module's command
    if opts.no_baselines or opts.no_encoder or opts.encoder_epochs is not None or opts.baseline_epochs is not None:
        command = shlex.join(["python", "-m", "experiments.reproduce", *options])
    else:
        command = (
            f"make reproduce EXP={opts.experiment}"
            + (" SIZE=cpu" if opts.size == "cpu" else "")
            + (f" SEED={opts.seed}" if seeded else "")
            + (f" ARGS={shlex.quote(shlex.join(stage_args))}" if stage_args else "")
        )
    pipeline = open_pipeline(opts, options, first, version, command)
    v = ["--trainer.logger.init_args.version", version]
    if seeded:
        v += ["--seed_everything", str(opts.seed)]
    v += stage_args  # after the stage's own options: they win

    def named(cfg: Path) -> list[str]:
        """A forecaster stage's results under the seed's own experiment name."""
        return ["--model.init_args.experiment", f"{experiment_name(cfg)}_{seeded}"] if seeded else []

    configs = []
    if ssm_stages:
        ssm_ckpt = logger_dir(ssm_cfg) / version / "checkpoints" / "last.ckpt"
        ssm_ran = pipeline.stage(["fit", "--config", str(ssm_cfg.relative_to(ROOT)), *v])
        with_ssm = ["--model.init_args.ssm_checkpoint", str(ssm_ckpt)]
        for stage_cfg in ssm_tests:  # seconds each: before a long encoder fit, which may stop or fail
            pipeline.stage(
                ["test", "--config", str(stage_cfg.relative_to(ROOT)), *with_ssm, *named(stage_cfg), *v],
                again=ssm_ran,
            )
        if use_encoder:
            enc_dir = logger_dir(enc_cfg) / version / "checkpoints"
            budget = [] if opts.encoder_epochs is None else ["--trainer.max_epochs", str(opts.encoder_epochs)]
            enc_ran = pipeline.stage(
                ["fit", "--config", str(enc_cfg.relative_to(ROOT)), *with_ssm, *budget, *named(enc_cfg), *v],
                again=ssm_ran,
            )
            enc_ckpt = tested_checkpoint(enc_dir)
            enc_test = ["test", "--config", str(enc_cfg.relative_to(ROOT)), *with_ssm, "--ckpt_path", str(enc_ckpt)]
            pipeline.stage([*enc_test, *named(enc_cfg), *v], again=ssm_ran or enc_ran)
            configs.append(enc_cfg)
        configs += ssm_tests  # the results files listed in the order they always were: encoder first
        if use_encoder:
            with_encoder = ["--model.init_args.encoder_checkpoint", str(enc_ckpt)]
            for control_cfg in controls:  # the control again, the encoder estimating the state
                test = ["test", "--config", str(control_cfg.relative_to(ROOT)), *with_ssm, *with_encoder]
                pipeline.stage([*test, *named(control_cfg), *v], again=ssm_ran or enc_ran)
            if controls and record_cfg is not None:  # the learned controller's episodes: a later experiment's data
                record = ["test", "--config", str(record_cfg.relative_to(ROOT)), *with_ssm, *with_encoder]
                pipeline.stage([*record, *v], again=ssm_ran or enc_ran)
    elif controls and not baselines:
        for control_cfg in controls:
            pipeline.stage(["test", "--config", str(control_cfg.relative_to(ROOT)), *named(control_cfg), *v])
        configs += controls
    baseline_budget = [] if opts.baseline_epochs is None else ["--trainer.max_epochs", str(opts.baseline_epochs)]
    for cfg in baselines:
        fit_ran = pipeline.stage(["fit", "--config", str(cfg.relative_to(ROOT)), *baseline_budget, *named(cfg), *v])
        ckpt = tested_checkpoint(logger_dir(cfg) / version / "checkpoints")
        pipeline.stage(
            ["test", "--config", str(cfg.relative_to(ROOT)), "--ckpt_path", str(ckpt), *named(cfg), *v], again=fit_ran
        )
        configs.append(cfg)
    files = []  # every results file the stages wrote (an SSM's stages may write to several, e.g. control)
    for cfg in configs:
        entry = (
            results_dir(cfg, version),
            experiment_name(cfg) + (f"_{seeded}" if seeded else ""),
        )
        if entry not in files:
            files.append(entry)
    for md in pipeline.finished(files):
        print(f"\nresults: {md.relative_to(ROOT)}\n")
        print(md.read_text())


def validation_score(checkpoint: Path) -> float:
    """The score a fit's ``ModelCheckpoint`` kept its best epoch by (``val/sim_rmse``), read from that checkpoint;
    infinite where there is none (a fit without that validation)."""
    path = configs.absolute(checkpoint)
    if not path.is_file():
        return math.inf
    import torch  # the stage is done: reading its checkpoint costs the import once

    from ssm_ms.checkpointing import kept_score

    score = kept_score(torch.load(path, map_location="cpu", weights_only=False), path)
    return math.inf if score is None else score


def selection(scores: dict, judged: dict, chosen: int | None, folds: int) -> dict:
    """How a benchmark's tested model was chosen, for its results file: each order's validation score (with
    ``folds``: each fold's, the held-out end first, and their mean, the cross-validated score) and the order
    chosen (``None``: one order, nothing chosen)."""
    key = lambda d: "" if d is None else str(d)  # noqa: E731  (JSON keys)
    if folds == 1:
        return {"state_dim, by val/sim_rmse": {key(d): v for d, v in judged.items()}, "chosen": chosen}
    out = {
        "folds": folds,
        "val/sim_rmse by fold (the held-out end first)": {key(d): v for d, v in scores.items()},
        CROSS_VALIDATED: {key(d): v for d, v in judged.items()},
    }
    return out if chosen is None else {**out, "chosen": chosen}


def open_pipeline(opts: argparse.Namespace, options: list[str], first: Path, version: str, command: str) -> Pipeline:
    """The record of this run (in the first stage's run folder), saying how to finish it if it stops (``--resume``
    among reproduce's own options, before the ``--`` of the stages')."""
    own = options[: options.index("--")] if "--" in options else options
    pipeline = Pipeline(
        configs.absolute(logger_dir(first)) / version / "reproduce.json",
        {k: v for k, v in vars(opts).items() if k != "resume"},
        shlex.join(["python", "-m", "experiments.reproduce", *own, "--resume", version, *options[len(own) :]]),
        resume=opts.resume is not None,
        command=command,
    )
    print(f"reproduce run {version}; if it stops, finish it with:\n  {pipeline.resume_pipeline}", flush=True)
    return pipeline


def run_benchmark(opts: argparse.Namespace, argv: list[str], config: Path, test_cfg: Path) -> None:
    """An identification benchmark (``configs/benchmarks/<experiment>.yaml``): the SSM's fit, then the benchmark's
    protocol on the test recordings (``test_cfg``) from the epoch its validation chose (``best.ckpt``);
    its results file is the test's (``results/benchmarks/<experiment>.md``, the commands and durations in this run's
    record)."""
    if opts.size != "paper" or opts.no_encoder or opts.encoder_epochs or opts.baseline_epochs:
        raise SystemExit(f"error: {opts.experiment} is a benchmark: one size, no encoder or baselines to choose")
    seeded = "" if opts.seed is None else f"seed{opts.seed}"
    version = opts.resume or "reproduce-" + (seeded + "-" if seeded else "") + datetime.now().strftime("%Y%m%d-%H%M%S")
    options = without_option(argv, "--resume")
    command = f"make reproduce EXP={opts.experiment}" + (f" SEED={opts.seed}" if seeded else "")
    command += f" FOLDS={opts.folds}" if opts.folds else ""
    command += f" ARGS={shlex.quote(shlex.join(opts.stage_args))}" if opts.stage_args else ""
    pipeline = open_pipeline(opts, options, config, version, command)
    seed = ["--seed_everything", str(opts.seed)] if seeded else []
    folds = opts.folds or 1
    fits = {}  # the run folders of each order's fits: the one holding out the end first, then the other folds
    for d in opts.orders or [None]:
        run = version if d is None else f"{version}-d{d}"
        order = [] if d is None else ["--model.init_args.state_dim", str(d)]
        fits[d] = []
        for k in [folds - 1, *range(folds - 1)]:
            name = run if k == folds - 1 else f"{run}-fold{k}"
            fold = [] if folds == 1 else ["--data.init_args.val_fraction", repr(1 / folds)]
            fold += [] if k == folds - 1 else ["--data.init_args.val_at", repr(k / folds)]
            v = ["--trainer.logger.init_args.version", name, *seed, *order, *fold, *opts.stage_args]
            fits[d].append((pipeline.stage(["fit", "--config", str(config.relative_to(ROOT)), *v]), name))

    def kept(name: str) -> Path:  # the checkpoint a fit keeps (its validation's epoch, else its last)
        return tested_checkpoint(logger_dir(config) / name / "checkpoints")

    scores = {}  # each fit's kept validation score, the held-out end's first: where there is a choice to record
    if opts.orders or folds > 1:
        scores = {d: [validation_score(kept(name)) for _, name in runs] for d, runs in fits.items()}
    judged = {d: float(sum(v) / len(v)) for d, v in scores.items()}  # the mean over the folds (one: the end's)
    chosen = min(judged, key=lambda d: judged[d]) if opts.orders else None
    ssm = kept(fits[chosen][0][1])
    named = []  # the results file keys the row by method and the seed the fit recorded
    if opts.orders or folds > 1:
        named += ["--model.init_args.selection", json.dumps(selection(scores, judged, chosen, folds))]
    test = ["test", "--config", str(test_cfg.relative_to(ROOT)), "--model.init_args.ssm_checkpoint", str(ssm)]
    pipeline.stage([*test, *named, *opts.stage_args], again=any(r for runs in fits.values() for r, _ in runs))
    md = results_dir(test_cfg, version) / f"{experiment_name(test_cfg)}.md"
    if md.is_file():
        print(f"\nresults: {md.relative_to(ROOT)}\n\n{md.read_text()}")


if __name__ == "__main__":
    main()
