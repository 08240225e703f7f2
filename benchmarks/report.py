"""What every benchmark results file states first, and how it is written: the date, the machine and the command."""

from __future__ import annotations

import datetime
import shlex
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ssm_ms.runtime.machine import describe  # noqa: E402


def provenance(script: str, argv: list[str] | None, machine: str = "") -> list[str]:
    """The ``- Date``, ``- Machine`` and ``- Command`` lines of a run of ``script`` (``benchmarks/<name>.py``) with
    the arguments ``argv`` (``None``: the command line's); ``machine``, if given, is appended to the machine line
    (threads, software versions, other processes' CPU use)."""
    args = sys.argv[1:] if argv is None else argv
    return [
        f"- Date: {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC",
        f"- Machine: {describe()}" + (f"; {machine}" if machine else ""),
        f"- Command: `{shlex.join(['python', script, *args])}`",
    ]


def write(out: str | Path, lines: list[str]) -> None:
    """Write the results file ``out`` (its folder made) and print it."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


# ---------------------------------------------------------------- one table per benchmark, a row per machine

RUNS_INTRO = "Each table has a row per machine (its first column), from that machine's latest run:"
NOTES = "## Notes"  # a hand-written last section, kept as it is on every rewrite


def _zen(family: int, model: int) -> str:
    """AMD's Zen generation from /proc/cpuinfo's family and model (23/1 Zen 1, 25/1 Zen 3, 25/17 Zen 4, 26/2 Zen 5)."""
    if family == 23:
        return "Zen 2" if model >= 0x30 else "Zen 1"
    if family == 25:
        return "Zen 4" if 0x10 <= model <= 0x1F or 0x60 <= model <= 0xAF else "Zen 3"
    return "Zen 5" if family == 26 else ""


def machine_label() -> str:
    """This machine's name in a results table's machine column: its CPU model, short (``Intel Xeon``), with AMD's
    Zen generation (``AMD EPYC Zen 4``), its core count, and the GPU where there is one."""
    import os
    import re

    import torch

    from ssm_ms.nets.native.build import cpu_fields
    from ssm_ms.runtime.machine import cpu_model

    name = re.sub(r"\((R|TM)\)|\b(Processor|CPU)\b|@.*$|\b\d+-Core\b", " ", cpu_model())
    name = " ".join(name.replace("|", " ").split())
    fields = cpu_fields()
    if "AMD" in name and fields.get("cpu family", "").isdigit() and fields.get("model", "").isdigit():
        name = f"{name} {_zen(int(fields['cpu family']), int(fields['model']))}".strip()
    gpu = f", {torch.cuda.get_device_name(0)}" if torch.cuda.is_available() else ""
    return f"{name}, {os.cpu_count()} cores{gpu}"


def _label(row: str) -> str:
    """The machine column's cell of a table row."""
    return row.split("|")[1].strip()


def merge_by_machine(old: str | None, lines: list[str], label: str) -> list[str]:
    """A run's results file ``lines`` (title, ``- `` lines of provenance and set-up, tables, prose) merged into the
    file ``old`` that holds the other machines' runs: every table gets a machine column, this run's rows replace the
    rows of ``label`` and the other machines' rows stay (in the order of the runs); the ``- `` lines become this
    machine's entry in the list of runs; the title and prose are this run's; ``old``'s last section ``## Notes``
    (written by hand) is kept. A table of ``old`` that this run no longer writes is dropped, with a warning."""
    runs: dict[str, list[str]] = {}
    old_rows: dict[str, list[str]] = {}
    notes: list[str] = []
    if old:
        old_lines = old.splitlines()
        if NOTES in old_lines:
            at = old_lines.index(NOTES)
            old_lines, notes = old_lines[:at], old_lines[at:]
        if RUNS_INTRO not in old_lines:
            print(
                f"warning: the file written over holds no runs by machine ({RUNS_INTRO!r}): replaced", file=sys.stderr
            )
            old_lines = []
        header = None
        for line in old_lines:
            if line.startswith("- **"):
                runs[line[4:].split("**", 1)[0]] = current = []
            elif line.startswith("  - "):
                current.append(line[4:])
            elif line.startswith("|"):
                if header is None:
                    header = line
                    old_rows.setdefault(header, [])
                elif not set(line) <= set("|-: "):
                    old_rows[header].append(line)
            else:
                header = None
    runs[label] = [line[2:] for line in lines if line.startswith("- ")]
    order = list(runs)
    out, table, placed = [], [], False

    def flush() -> None:
        """The table gathered in ``table`` (this run's header, separator and rows), with the other machines' rows."""
        if table:
            header, rows = f"| machine {table[0]}", [f"| {label} {row}" for row in table[2:]]
            rows += [row for row in old_rows.pop(header, []) if _label(row) != label]
            rank = {name: i for i, name in enumerate(order)}
            out.extend([header, f"|---{table[1]}", *sorted(rows, key=lambda row: rank.get(_label(row), len(order)))])
            written.add(header)
            table.clear()

    written: set[str] = set()
    for line in lines:
        if line.startswith("|"):
            table.append(line)
            continue
        flush()
        if line.startswith("- "):
            if not placed:
                out += [RUNS_INTRO, ""]
                for name in order:
                    out += [f"- **{name}**", *(f"  - {fact}" for fact in runs[name])]
                placed = True
        else:
            out.append(line)
    flush()
    dropped = {header: rows for header, rows in old_rows.items() if rows and header not in written}
    if dropped:
        print(f"warning: tables this run no longer writes, dropped: {list(dropped)}", file=sys.stderr)
    if notes:
        out += ["", *notes]
    return [line for i, line in enumerate(out) if line or i == 0 or out[i - 1]]  # no run of blank lines


def write_by_machine(out: str | Path, lines: list[str], label: str | None = None) -> None:
    """Write a run's ``lines`` into ``out`` beside the other machines' runs there (:func:`merge_by_machine`;
    ``label``: :func:`machine_label`) and print the file."""
    out = Path(out)
    old = out.read_text() if out.is_file() else None
    write(out, merge_by_machine(old, lines, label or machine_label()))
