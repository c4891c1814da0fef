"""What the benchmarks share: their start (`start`: arguments, logging, torch's thread count),
a comma-separated choice among options (`subset`), a printed table (`print_table`, its cells
`cell`) and their last line (`emit`). A benchmark
runs as a script, so ``from common import ...`` (imports inside the functions: a benchmark's
child processes load nothing more for them)."""

from __future__ import annotations

import argparse
import json
import logging
import math
from pathlib import Path


def start(ap: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace:
    """The parsed arguments; log messages bare to stderr (INFO); ``--threads N`` (when the
    benchmark has it): N torch threads for the run (0: torch's default)."""
    from deformnet.threads import set_torch_threads

    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    set_torch_threads(getattr(args, "threads", None))
    return args


def subset(ap: argparse.ArgumentParser, text: str, allowed, flag: str) -> list[str]:
    """A comma-separated choice of some of `allowed` (in the order given); a usage error
    naming ``flag`` for an empty or unknown choice."""
    chosen = [c.strip() for c in str(text).split(",") if c.strip()]
    bad = sorted(set(chosen) - set(allowed))
    if bad or not chosen:
        ap.error(f"{flag}: unknown {bad}; choose from {', '.join(allowed)}")
    return chosen


def cell(v, digits: int = 3, large_digits: int | None = 2, missing: str = "n/a") -> str:
    """A printed table's cell: a finite float with `digits` decimals (`large_digits` from 10 up;
    None: `digits` throughout), a non-finite float or None as `missing`, anything else as text."""
    if v is None:
        return missing
    if isinstance(v, float):
        if not math.isfinite(v):
            return missing
        d = digits if large_digits is None or abs(v) < 10 else large_digits
        return f"{v:.{d}f}"
    return str(v)


def geo_mean(vals) -> float:
    """The geometric mean of the finite positive values of `vals` (NaN where none)."""
    v = [x for x in vals if x is not None and math.isfinite(x) and x > 0]
    return math.exp(sum(math.log(x) for x in v) / len(v)) if v else float("nan")


#: the input-condition benchmarks' table columns (`subframe.py`, `clocks.py`): RMSE all / seen
#: by >= 2 cameras in step, spoilt unchecked and checked; aniposelib spoilt and in step
CHECK_COLUMNS = [
    ("instep_all", "in step"),
    ("unchecked_all", "unchecked"),
    ("checked_all", "checked"),
    ("peer_all", "anipose"),
    ("peer_instep_all", "anip. step"),
    ("instep_seen", "seen step"),
    ("unchecked_seen", "seen unch."),
    ("checked_seen", "seen chk."),
]
#: ... and their ratios to the scene in step: {name: (numerator key, denominator key)}
CHECK_RATIOS = {
    "unchecked/instep_all": ("unchecked_all", "instep_all"),
    "checked/instep_all": ("checked_all", "instep_all"),
    "unchecked/instep_seen": ("unchecked_seen", "instep_seen"),
    "checked/instep_seen": ("checked_seen", "instep_seen"),
}


def ratio_means(rows: list[dict], ratios: dict) -> dict:
    """{name: the geometric mean over `rows` of r[a] / r[b]} for each name: (a, b) of
    `ratios` (rows where either is missing or 0 left out)."""
    return {
        k: geo_mean([r[a] / r[b] for r in rows if r[a] and r[b]]) for k, (a, b) in ratios.items()
    }


def print_means(summary: dict) -> None:
    """`summary` ({group: {name: value}}) a line per group, floats to 3 decimals."""
    print("\ngeometric means over the scenes:")
    for k, v in summary.items():
        print(f"  {k}: " + ", ".join(f"{a} {b:.3f}" if isinstance(b, float) else f"{a} {b}"
                                     for a, b in v.items()))  # fmt: skip


def print_table(rows: dict, cols, width: int, **cell_args) -> None:
    """`rows` (method -> {key: value}) as a table: one column per (key, heading) of `cols`,
    `width` characters each (the method's too), cells by `cell` (`cell_args`: its options)."""
    print(f"{'method':<{width}}" + "".join(f"{h:>{width}}" for _, h in cols))
    for name, r in rows.items():
        print(
            f"{name:<{width}}" + "".join(f"{cell(r.get(k), **cell_args):>{width}}" for k, _ in cols)
        )


def emit(summary: dict, out: str | Path) -> dict:
    """The benchmarks' last line: the summary as JSON (non-finite -> null), printed and written
    atomically to `out`."""
    from adjust.apps.common import finite_or_none
    from deformnet.atomic import write_text

    line = json.dumps(finite_or_none(summary))
    write_text(out, line + "\n")
    print(line, flush=True)
    return summary
