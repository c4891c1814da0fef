"""`make demo`: the main job end to end on the embedded default (simulated data)."""

from __future__ import annotations

import logging
import sys


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger(__name__).info("demo: pipeline steps are being built; nothing to run yet")
    return 0


if __name__ == "__main__":
    sys.exit(main())
