"""Where the pendulum training step's time goes on CPU: the decoder (native kernels on and off) and f.

    python benchmarks/profile_decoder.py [--threads 2] [--repeats 7]
    python benchmarks/profile_decoder.py --tiny --out /tmp/x.md      # seconds, for `make test`

On the paper's pendulum step sizes (4000 frames of 24x24 = batch 40 x m 4 x n 25; SSM-LL, K 32, 1024 hidden, on
160 states x 26 steps), in one process with ``cli.py``'s allocator setting: median milliseconds of

* the decoder's forward + backward through an MSE loss, with the fused native kernels
  (``ConvDecoder(backend="native")``) and without (``backend="torch"``), alternated;
* inside the first, the time of each native kernel call (the forward and the backward of the whole stack of
  transposed convolutions), taken around the library's own functions;
* f's rollout forward + backward;
* the quadruple-pendulum (1000 frames of 48x48) and Moving MNIST (100 frames of 64x64) decoders, forward +
  backward, with and without the native kernels;
* the check of ``ConvDecoder(backend="auto")``'s rule (:func:`ssm_ms.nets.decoder.auto_path`: the native kernels on a
  CPU with AVX-512 or full-width AVX2, the torch path on an AMD Zen 1 or Zen+): this CPU's vector unit, the path the
  rule picks here
  and the path an ``auto`` decoder actually ran for each preset, beside the native / torch time ratio measured in
  this run, so that each machine's results file says whether the rule picks the faster path there.

Writes benchmarks/results/decoder_profile.md, a row per machine (this run's replace this machine's earlier ones), with
the machine, command and date of each machine's run.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

FULL = {"frames": 4000, "states": 160, "steps": 26, "d": 10, "k": 32, "hidden": 1024, "quad": 1000, "mnist": 100}
TINY = {"frames": 8, "states": 4, "steps": 3, "d": 4, "k": 4, "hidden": 16, "quad": 2, "mnist": 1}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--tiny", action="store_true", help="tiny sizes, to check that the script runs")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "decoder_profile.md"))
    parser.add_argument(
        "--cflags",
        default=None,
        help="compiler flags for the native kernels instead of ssm_ms.nets.native.build.FLAG_SETS, e.g. "
        '"-O3 -mavx2 -mfma" for the AVX2 build on an AVX-512 CPU (-fopenmp is added)',
    )
    args = parser.parse_args(argv)

    from ssm_ms.runtime.perf import configure_allocator

    configure_allocator()
    import torch
    import torch.nn.functional as F

    from benchmarks.report import provenance, write_by_machine
    from ssm_ms.nets import ConvDecoder, LocallyLinearTransition, native
    from ssm_ms.runtime.machine import CpuWatch, quiet_note
    from ssm_ms.training.shooting import rollout

    if args.cflags:
        native.build.FLAG_SETS = (args.cflags.split() + ["-fopenmp"],)
    watch = CpuWatch()

    torch.set_num_threads(args.threads)
    size = TINY if args.tiny else FULL
    torch.manual_seed(0)
    fused, plain = kernels_or_torch(size["d"], "pendulum"), ConvDecoder(size["d"], "pendulum", backend="torch")
    plain.load_state_dict(fused.state_dict())
    z = torch.randn(size["frames"], size["d"], requires_grad=True)
    y = torch.rand(size["frames"], 1, 24, 24)
    f = LocallyLinearTransition(size["d"], size["k"], size["hidden"])
    nodes = torch.nn.Parameter(0.1 * torch.randn(size["states"], size["d"]))

    calls: dict[str, list[float]] = {}
    lib = native.library()
    originals = {}
    if lib is not None:  # time each kernel call around the library's own function
        for name in ("conv_stack_forward", "conv_stack_backward"):
            originals[name] = getattr(lib, name)

            def timed(*a, _fn=originals[name], _name=name):
                t0 = time.perf_counter()
                status = _fn(*a)
                calls.setdefault(_name, []).append(time.perf_counter() - t0)
                return status

            setattr(lib, name, timed)

    def decoder(g):
        F.mse_loss(g(z), y).backward()

    def f_rollout():
        states = rollout(f, nodes, size["steps"])
        states.square().mean().backward()

    runs = {
        "decoder, native kernels": lambda: decoder(fused),
        "decoder, torch-only": lambda: decoder(plain),
        "f rollout (SSM-LL)": f_rollout,
    }
    times: dict[str, list[float]] = {name: [] for name in runs}
    per_call: list[list[float]] = []
    try:
        for run in runs.values():  # warm-up
            run()
        for _ in range(args.repeats):
            for name, run in runs.items():
                calls.clear()
                t0 = time.perf_counter()
                run()
                times[name].append(time.perf_counter() - t0)
                if name == "decoder, native kernels" and calls:
                    per_call.append(calls["conv_stack_forward"] + calls["conv_stack_backward"])
    finally:
        for name, fn in originals.items():
            setattr(lib, name, fn)

    ms = {name: 1000 * statistics.median(ts) for name, ts in times.items()}
    others = {preset: other_decoders(preset, size[preset], size["d"], args.repeats) for preset in ("quad", "mnist")}
    lines = [
        "# Pendulum step on CPU: decoder with and without the native kernels, and f",
        "",
        *provenance(
            "benchmarks/profile_decoder.py", argv, f"{args.threads} torch threads; {quiet_note(watch.others())}"
        ),
        f"- set-up: {'TINY sizes (smoke test) ' if args.tiny else ''}{size['frames']} frames 24x24 (pendulum decoder, "
        f"MSE), SSM-LL K {size['k']} hidden {size['hidden']} on {size['states']} states x {size['steps']} steps; "
        f"median of {args.repeats} alternated runs, forward + backward",
        f"- native kernels: {'on' if lib is not None else 'off: ' + str(native.unavailable_reason())}, built with "
        f"`{' '.join(native.build.FLAG_SETS[0]) if args.cflags else 'ssm_ms.nets.native.build.FLAG_SETS (-march=native)'}`",
        "",
        "| part | ms |",
        "|---|---:|",
    ]
    lines += [f"| {name} | {value:.1f} |" for name, value in ms.items()]
    if per_call:
        labels = ["forward (the transposed-convolution stack)", "backward (the transposed-convolution stack)"]
        for i, label in enumerate(labels[: len(per_call[0])]):
            lines.append(f"| native kernel: {label} | {1000 * statistics.median(c[i] for c in per_call):.1f} |")
        total = 1000 * statistics.median(sum(c) for c in per_call)
        lines.append(f"| native kernels, all calls | {total:.1f} |")
        lines.append(
            f"| decoder with native kernels, the rest (stem, layout of its output, sigmoid, loss) | "
            f"{ms['decoder, native kernels'] - total:.1f} |"
        )
    lines += [
        "",
        "| decoder, forward + backward | frames | native kernels, ms | torch-only, ms |",
        "|---|---:|---:|---:|",
    ]
    for preset, res in others.items():
        lines.append(f"| {preset} | {size[preset]} | {res['native']:.1f} | {res['torch']:.1f} |")
    measured = {"pendulum": {"native": ms["decoder, native kernels"], "torch": ms["decoder, torch-only"]}, **others}
    lines += auto_check(size, measured, lib is not None, args.cflags)
    write_by_machine(args.out, lines)


def auto_check(size: dict, measured: dict[str, dict[str, float]], built: bool, cflags: str | None) -> list[str]:
    """The results file's section on backend ``"auto"``: the rule's pick on this CPU beside the measured times."""
    from ssm_ms.nets import ConvDecoder, native
    from ssm_ms.nets.decoder import SIMD_NAMES, auto_path

    simd = native.build.cpu_simd()
    rule = auto_path("cpu", simd)
    lines = [
        "",
        "## Backend `auto` on each machine (its CPU and the rule's pick: the list of runs above)",
        "",
        f"- this CPU: {cpu_family_model()}; its vector unit (`ssm_ms.nets.native.build.cpu_simd()`, "
        f"/proc/cpuinfo): {SIMD_NAMES[simd]}",
        f"- the rule (`ssm_ms.nets.decoder.auto_path('cpu', {simd!r})`): **{rule}** (native kernels on a CPU with "
        "AVX-512 or full-width AVX2, the torch path on AVX2 as two 128-bit halves or neither, and on any other "
        "device)",
    ]
    if cflags:
        lines.append(
            f"- the kernels timed here (and run by `auto` below) were built with `{cflags}`, not "
            "`-march=native` as elsewhere: the rule reads the CPU's vector unit, not the build's"
        )
    lines += [
        "",
        "| decoder | frames | native kernels, ms | torch-only, ms | native / torch | faster here | "
        "`auto` ran | `auto` took the faster |",
        "|---|---:|---:|---:|---:|---|---|---|",
    ]
    for preset, res in measured.items():
        ran = auto_ran(size["d"], preset)
        frames = size["frames"] if preset == "pendulum" else size[preset]
        if not (built and ConvDecoder(size["d"], preset, backend="torch").native_fits):  # both columns: torch
            reason = "the kernels are not built" if not built else "one sample does not fit the kernels"
            lines.append(f"| {preset} | {frames} | ({reason}) | {res['torch']:.1f} | - | - | {ran} | - |")
            continue
        faster = "native" if res["native"] < res["torch"] else "torch"
        lines.append(
            f"| {preset} | {frames} | {res['native']:.1f} | {res['torch']:.1f} | "
            f"{res['native'] / res['torch']:.2f} | {faster} | {ran} | {'yes' if ran == faster else '**no**'} |"
        )
    return lines


def cpu_family_model() -> str:
    """``family F model M`` from /proc/cpuinfo (what tells AMD's Zen generations apart: 23/1 Zen 1, 25/1 Zen 3,
    25/17 Zen 4, 26/2 Zen 5), or ``family and model unknown``."""
    from ssm_ms.nets.native.build import cpu_fields

    fields = cpu_fields()
    if "cpu family" not in fields or "model" not in fields:
        return "family and model unknown"
    return f"family {fields['cpu family']} model {fields['model']}"


def auto_ran(d: int, preset: str) -> str:
    """Which path a ``ConvDecoder(d, preset)`` with backend ``"auto"`` runs on a float32 CPU batch here: ``"native"``
    if its forward called the kernels' operator, else ``"torch"``."""
    import torch

    from ssm_ms.nets import ConvDecoder, native

    calls = []
    original = native.conv_stack

    def counted(*a, **k):
        calls.append(1)
        return original(*a, **k)

    native.conv_stack = counted  # the decoder calls it through the package (ssm_ms.nets.native.conv_stack)
    try:
        ConvDecoder(d, preset)(torch.randn(2, d, requires_grad=True))
    finally:
        native.conv_stack = original
    return "native" if calls else "torch"


def kernels_or_torch(d: int, preset: str):
    """The decoder with backend ``"native"``, or ``"torch"`` where the kernels cannot run it (not built here, or a
    sample too large for them: Moving MNIST)."""
    from ssm_ms.nets import ConvDecoder

    try:
        return ConvDecoder(d, preset, backend="native")
    except ValueError:
        return ConvDecoder(d, preset, backend="torch")


def other_decoders(preset: str, frames: int, d: int, repeats: int) -> dict[str, float]:
    """Median ms of another preset's decoder forward+backward, with and without the native kernels."""
    import torch
    import torch.nn.functional as F

    from ssm_ms.nets import ConvDecoder

    torch.manual_seed(0)
    fused = kernels_or_torch(d, preset)
    torch_only = ConvDecoder(d, preset, backend="torch")
    torch_only.load_state_dict(fused.state_dict())
    z = torch.randn(frames, d, requires_grad=True)
    y = torch.rand(frames, *fused.out_shape)
    runs = {"native": fused, "torch": torch_only}
    times: dict[str, list[float]] = {name: [] for name in runs}
    for g in runs.values():  # warm-up
        F.mse_loss(g(z), y).backward()
    for _ in range(repeats):
        for name, g in runs.items():
            t0 = time.perf_counter()
            F.mse_loss(g(z), y).backward()
            times[name].append(time.perf_counter() - t0)
    return {name: 1000 * statistics.median(ts) for name, ts in times.items()}


if __name__ == "__main__":
    main()
