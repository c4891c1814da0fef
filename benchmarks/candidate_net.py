"""A candidate default net through `benchmarks/real_motion.py`, before it is shipped.

``deformation=default`` and ``deformation=self`` start from the shipped net
(`deformnet.pretrained.load_default`); this runs real_motion.py in-process with the shipped
checkpoint's path pointed at ``--checkpoint`` (the installed file is not touched), e.g. the net
that `adjust.pretrain_real --train-frames 0-1200` trained without the validation segment:

    .venv/bin/python benchmarks/candidate_net.py --checkpoint X.pt -- --split val \\
        --cameras 3 --parts 8,34 --seeds 0 --methods default,net --no-stability \\
        --out runs/benchmarks/candidate_val.json

Everything after ``--`` is real_motion.py's arguments; its tables and JSON as usual.
``--track KEY=VALUE`` (repeatable): an adjust-track override added to every adjust-track
method's run (e.g. ``--track deform.beyond_window=interp``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import real_motion  # noqa: E402

import deformnet.pretrained as pretrained  # noqa: E402
from deformnet.deformation import DeformationModel  # noqa: E402


def main(argv: list[str] | None = None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    rest = argv[argv.index("--") + 1 :] if "--" in argv else []
    own = argv[: argv.index("--")] if "--" in argv else argv
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", required=True, help="the candidate net (DeformationModel)")
    ap.add_argument("--track", action="append", default=[], metavar="KEY=VALUE",
                    help="an adjust-track override for every adjust-track method")  # fmt: skip
    args = ap.parse_args(own)
    path = Path(args.checkpoint).resolve()
    DeformationModel.from_checkpoint(path)  # refuse a bad file before any filming
    pretrained.DEFAULT_CHECKPOINT = path  # what load_default() reads, for this process only
    print(f"candidate default net: {path}", flush=True)
    if args.track:
        base = real_motion.track_overrides

        def with_track(method: str, adapt_minutes: float) -> list[str]:
            return [*base(method, adapt_minutes), *args.track]

        real_motion.track_overrides = with_track  # run_scene reads it at each call
        print(f"adjust-track overrides: {args.track}", flush=True)
    return real_motion.main(rest)


if __name__ == "__main__":
    main()
