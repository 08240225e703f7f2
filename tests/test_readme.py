"""The README is a test: every command in its code blocks, and in the docs' quick-start blocks (:data:`DOCS`), runs
as written in a clean copy of the repository, with an empty HOME and no ``runs/``, ``data/`` or caches left from
other tests.

Every shell command of those blocks must be listed in :data:`STEPS` with how the test runs it: a command that is not
is a failing test. A Python block runs whole, as a script (those that train do so on a budget of their own: a minute at
most; ``make test`` shortens it, :data:`PYTHON_QUICK`). Commands that train for long get tiny overrides appended
(stated beside them: one epoch of two batches, fewer test sequences); ``make test`` runs the quick ones (``quick``
set), ``make test-slow`` every one.
``make test-slow`` runs each document in its own copy, its commands in the order written (later ones use what
earlier ones wrote); ``make test`` runs the documents one after the other in one copy, a command that an earlier
document already ran as written not run again (the docs repeat the README's steps).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
VENV = Path(sys.executable).parent.parent  # the environment running the tests (make's .venv)

# the documents whose blocks are promises: the README, and the docs' quick starts (a user's own data, forecasting)
DOCS = ("README.md", "docs/your-data.md", "docs/forecasting.md", "docs/python.md")

TINY = "--trainer.max_epochs 1 --trainer.limit_train_batches 2 --trainer.limit_val_batches 1"  # a training smoke test
FEW_TESTS = "--data.init_args.n_test 50"  # a test on the first 50 test sequences (generating only those)
# the pendulum's analysis at a tiny size (make test only): every part computed, over a few short runs (the configs'
# Lyapunov spectrum and free runs are ~10 s of the command)
SMALL_ANALYSIS = (
    "--model.init_args.analysis '{valid_time: {}, dynamics: {runs: 2, lyapunov_steps: 100, transient: 20, align: 20, "
    "free_steps: 100}}'"
)
FEW_TRAIN = "--data.init_args.n_train 100"  # the pendulum's first 100 training sequences (make test only)
# make test's changes to the Python blocks, as written -> as run (make test-slow runs them as written): a training budget
# of 3 seconds (~25 epochs of its example), not the block's minute (the suite's 10 minutes on the slowest CPUs)
PYTHON_QUICK = {'time="1min"': 'time="3s"'}


@dataclass(frozen=True)
class Step:
    """How the test runs one command: ``extra`` appended to it; ``quick``: in ``make test`` too (else only in
    ``make test-slow``); ``slow_extra``: appended instead in ``make test-slow`` (``None``: ``extra``)."""

    extra: str = ""
    quick: bool = True
    slow_extra: str | None = None
    timeout: int = 900


# Every command of DOCS, as written (whitespace normalised, comments dropped); "<version>"-style placeholders are
# filled from what earlier commands wrote (PLACEHOLDERS).
STEPS: dict[str, Step] = {
    # setting up a fresh machine: `make test` is the suite running this file (CI runs it); `make demo` trains the
    # CPU pendulum for its few minutes
    "make demo": Step(quick=False, timeout=1800),
    "make test": Step(quick=False, extra="SKIP"),
    # README: fit, look, test, predict, Python
    "python cli.py fit --config configs/pendulum.yaml": Step(f"{TINY} {FEW_TRAIN}", slow_extra=TINY),
    "python cli.py fit --config configs/pendulum_encoder.yaml --model.init_args.ssm_checkpoint "
    "runs/pendulum/version_0/checkpoints/last.ckpt": Step(f"{TINY} {FEW_TRAIN}", slow_extra=TINY),
    "python cli.py test --config configs/pendulum_encoder.yaml --model.init_args.ssm_checkpoint "
    "runs/pendulum/version_0/checkpoints/last.ckpt --ckpt_path runs/pendulum_encoder/version_0/checkpoints/last.ckpt": Step(
        f"{FEW_TESTS} {SMALL_ANALYSIS}", slow_extra=""
    ),
    "python examples/make_oscillator_data.py": Step(),
    "python cli.py fit --config configs/oscillator.yaml": Step(TINY),
    "python examples/make_oscillator_data.py --out data/oscillator_new.npz --n 8 --seed 1": Step(),
    "python cli.py predict --config configs/oscillator_ukf.yaml --model.init_args.ssm_checkpoint "
    "runs/oscillator/version_0/checkpoints/last.ckpt --data.init_args.predict_path data/oscillator_new.npz "
    "--data.init_args.predict_steps 50": Step(),
    "python cli.py fit --config configs/oscillator_encoder.yaml --model.init_args.ssm_checkpoint "
    "runs/oscillator/version_0/checkpoints/last.ckpt": Step(TINY),
    "python cli.py predict --config configs/oscillator_encoder.yaml --model.init_args.ssm_checkpoint "
    "runs/oscillator/version_0/checkpoints/last.ckpt --ckpt_path runs/oscillator_encoder/version_0/checkpoints/last.ckpt "
    "--data.init_args.predict_path data/oscillator_new.npz --data.init_args.predict_given 150 "
    "--data.init_args.predict_steps 50 --trainer.callbacks+=ssm_ms.forecasting.ForecastWriter "
    "--trainer.callbacks.output predictions/new_encoder.npz --trainer.callbacks.figures true": Step(),
    # the pipelines: one epoch of two batches per stage (ARGS / after --: appended to every stage)
    # (the pendulum's on 50 test sequences: its fitted-states test takes ~0.8 s a sequence)
    "make reproduce EXP=pendulum": Step(quick=False, extra=f'ARGS="{TINY} {FEW_TESTS}"', timeout=1800),
    "make reproduce EXP=pendulum SIZE=cpu": Step(quick=False, extra=f'ARGS="{TINY}"', timeout=1800),
    "make reproduce EXP=pendulum_control": Step(quick=False, extra=f'ARGS="{TINY}"', timeout=3600),
    # an identification benchmark's pretrained model by the benchmark's protocol (seconds)
    "python cli.py test --config configs/benchmarks/silverbox_test.yaml --model.init_args.ssm_checkpoint "
    "pretrained/benchmarks/silverbox_no_identity.ckpt --data.init_args.dir_placement ../shared/data/nonlinear_benchmarks "
    "--model.init_args.results_dir runs/pretrained --model.init_args.figures_dir null": Step(),
    # the closed-loop rows from the pretrained torque-driven pendulum: make test runs two episodes of 1 s per row, of the
    # harder setting only (the loop is the same for both; each CLI start costs ~8 s of imports on the slowest CPUs),
    # the angle readout distilled in 50 steps on the nodes' first 2 states (decoding the 25 of each is ~15 s a row);
    # the torque model's rows and the bound (the amortised model's chart fits a 4000-step autoencoder at set-up, tens
    # of seconds: make test-slow runs every model)
    "make control-pretrained": Step(
        'CONTROL_SETTINGS=control_2nm CONTROL_MODELS=torque ARGS="--data.init_args.n_test 2 '
        "--data.init_args.eval_batch_size 2 "
        "--model.init_args.seconds 1 "
        "--model.init_args.success_seconds 1 --model.init_args.timing_steps 2 --model.init_args.distill "
        "'{steps: 50, rollout_steps: 2}'\"",
        slow_extra='ARGS="--data.init_args.n_test 20"',
    ),
    "make reproduce EXP=pendulum RESUME=reproduce-<date>-<time>": Step(quick=False, extra=f'ARGS="{TINY} {FEW_TESTS}"'),
    "make reproduce EXP=oscillator": Step(quick=False, extra=f'ARGS="{TINY}"', timeout=1800),
    # the pretrained model, tested as shipped (make test: on 50 test sequences, the analysis tiny; make test-slow: all
    # 1000, as written)
    "python cli.py test --config configs/pendulum_encoder.yaml --ckpt_path pretrained/pendulum_encoder.ckpt": Step(
        f"{FEW_TESTS} {SMALL_ANALYSIS}", slow_extra=""
    ),
}

# placeholders in commands, and how to fill them in the copy (the run an earlier command started)
PLACEHOLDERS = {
    "reproduce-<date>-<time>": lambda root: sorted((root / "runs" / "pendulum").glob("reproduce-*"))[0].name
}


# ------------------------------------------------------------------------------------------------- parsing
FENCE = re.compile(r"^```(\w*)[^\n]*\n(.*?)^```", re.M | re.S)


def blocks(path: Path) -> list[tuple[str, str]]:
    """``(language, text)`` of every fenced code block."""
    return FENCE.findall(path.read_text(encoding="utf-8"))


def commands(language: str, text: str) -> list[str]:
    """The commands of a block: a bash block's lines (continuations joined, comments and output lines dropped), or a
    Python block whole. Other blocks (YAML, text) hold no commands."""
    if language == "python":
        return [text]
    if language not in ("bash", "sh", "shell"):
        return []
    out = []
    for line in text.replace("\\\n", " ").splitlines():
        line = re.sub(r"(^|\s)#.*$", "", line).strip()  # a comment, or a whole comment line (the shown output)
        if line:
            out.append(" ".join(line.split()))
    return out


def doc_commands(doc: str) -> list[str]:
    return [c for language, text in blocks(ROOT / doc) for c in commands(language, text)]


def is_python(command: str) -> bool:
    return "\n" in command


# ------------------------------------------------------------------------------------------------- running
def clean_copy(tmp: Path) -> tuple[Path, dict[str, str]]:
    """The repository's files (tracked, and new ones not ignored: what a commit of this tree would hold) copied to
    ``tmp/repo``, with ``.venv`` linked to this environment, and an environment with an empty HOME."""
    listed = (
        subprocess.run(
            ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
            cwd=ROOT,
            capture_output=True,
            check=True,
        )
        .stdout.decode()
        .split("\0")
    )
    repo = tmp / "repo"
    for name in filter(None, listed):
        source = ROOT / name
        if source.is_file():
            (repo / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, repo / name)
    (repo / ".venv").symlink_to(VENV)
    if (ROOT.parent / "shared").is_dir():  # ../shared beside the clone, as on CI (the benchmarks' files)
        (tmp / "shared").symlink_to(ROOT.parent / "shared")
    stamp = VENV / ".installed"
    if stamp.exists():  # installed: make must not install again (into this environment, from the copy)
        installed = stamp.stat().st_mtime - 1
        os.utime(repo / "pyproject.toml", (installed, installed))
    home = tmp / "home"
    home.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("SSM_MS_", "PYTEST", "MPLCONFIGDIR"))}
    env.update(HOME=str(home), PATH=f"{VENV / 'bin'}{os.pathsep}{env.get('PATH', '')}", PYTHONDONTWRITEBYTECODE="1")
    env.pop("VIRTUAL_ENV", None)
    return repo, env


def run_doc(doc: str, repo: Path, env: dict[str, str], slow: bool, done: set[str]) -> None:
    """Run the commands of ``doc`` in ``repo`` in order (``make test``'s quick ones, or every one), but those in
    ``done`` (run already in this copy), adding each to it."""
    for command in doc_commands(doc):
        step = Step() if is_python(command) else STEPS[command]
        if step.extra == "SKIP" or not (slow or step.quick) or command in done:
            continue
        extra = step.extra if not slow or step.slow_extra is None else step.slow_extra
        if is_python(command):
            script = repo.parent / "snippet.py"
            text = command
            for written, quick in PYTHON_QUICK.items() if not slow else ():
                text = text.replace(written, quick)
            script.write_text(text)
            line = f"python {script}"
        else:
            line = command
            for placeholder, fill in PLACEHOLDERS.items():
                if placeholder in line:
                    line = line.replace(placeholder, fill(repo))
            line = f"{line} {extra}".strip()
        start = time.time()
        proc = subprocess.run(
            ["bash", "-c", line], cwd=repo, env=env, capture_output=True, text=True, timeout=step.timeout
        )
        print(f"{time.time() - start:6.1f} s  {line}")  # shown with pytest -s: where the suite's time goes
        assert proc.returncode == 0, (
            f"{doc}: `{line}` failed with status {proc.returncode} after {time.time() - start:.0f} s:\n"
            f"{(proc.stdout + proc.stderr)[-4000:]}"
        )
        done.add(command)


# ------------------------------------------------------------------------------------------------- tests
@pytest.mark.parametrize("doc", DOCS)
def test_every_command_is_run_by_a_test(doc):
    """A command in a tested block that :data:`STEPS` does not list (how this file runs it) fails here."""
    missing = [c for c in doc_commands(doc) if not is_python(c) and c not in STEPS]
    assert missing == [], f"{doc}: commands no test runs (add each to tests/test_readme.py's STEPS): {missing}"


def test_every_listed_command_is_in_a_document():
    """A command left in STEPS (or a change in PYTHON_QUICK) after it left the documents is dead weight: fails here."""
    written = {c for doc in DOCS for c in doc_commands(doc)}
    assert sorted(set(STEPS) - written) == []
    python = [c for c in written if is_python(c)]
    assert [w for w in PYTHON_QUICK if not any(w in c for c in python)] == []


def test_commands_are_parsed_as_written():
    text = "python a.py \\\n    --x 1   # say\n# wrote out.npz\n\nmake b  # c\n"
    assert commands("bash", text) == ["python a.py --x 1", "make b"]
    assert commands("yaml", "a: 1\n") == [] and commands("python", "import x\n") == ["import x\n"]


@pytest.mark.longest
def test_quick_commands_run_as_written(tmp_path):
    repo, env = clean_copy(tmp_path)
    done: set[str] = set()
    for doc in DOCS:
        run_doc(doc, repo, env, slow=False, done=done)


@pytest.mark.slow
@pytest.mark.parametrize("doc", DOCS)
def test_every_command_runs_as_written(doc, tmp_path):
    repo, env = clean_copy(tmp_path)
    run_doc(doc, repo, env, slow=True, done=set())
