"""What an app's console shows of the libraries below it.

Lightning logs a tip to install its cloud logger ("💡 Tip: ... litlogger") on every Trainer, prints
each of its INFO lines twice under a Hydra app (its own ``lightning`` console handler beside
Hydra's), and torch's pytree deprecation (``isinstance(treespec, LeafSpec)``, raised inside
Lightning) shows on every fit: nothing a user can act on. `quiet_lightning` hides them for the
duration of an app (not at import: a library user keeps Lightning's defaults);
``info=False`` (the demo, which trains five times) also hides Lightning's, TensorBoard's and
numexpr's INFO lines and Lightning's note that a short epoch is below the logging interval.
Lightning's warnings and errors still show. Lightning is imported only when the context is
entered (`adjust` modules import without it).
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import warnings
from collections.abc import Iterator

#: loggers of Lightning's rank-zero messages (the tips come through these)
RANK_ZERO = ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero")
#: loggers whose INFO lines `info=False` hides
CHATTY = ("lightning", "lightning.pytorch", "lightning.fabric", "tensorboard", "numexpr")
#: warnings (message regexes) nobody running an app can act on
NOT_ACTIONABLE = (r"`isinstance\(treespec, LeafSpec\)` is deprecated",)
#: ... and those the demo's tiny epochs raise by design
DEMO_NOTES = (r"The number of training batches \(\d+\) is smaller than the logging interval",)


class _NoTips(logging.Filter):
    """Drops Lightning's advertisements ("💡 Tip: ... litlogger")."""

    def filter(self, record: logging.LogRecord) -> bool:
        text = str(record.msg)
        return not (text.startswith("💡 Tip") or "litlogger" in text)


@contextlib.contextmanager
def quiet_lightning(info: bool = True) -> Iterator[None]:
    """Within: no Lightning tips, no `NOT_ACTIONABLE` warnings, Lightning's lines once (through
    the app's logging, when it has handlers); info=False also hides the `CHATTY` loggers' INFO
    lines and the `DEMO_NOTES` warnings. Everything is restored on exit. Imports Lightning
    first (when installed): its import sets its loggers' levels and handlers."""
    with contextlib.suppress(ImportError):
        importlib.import_module("lightning.pytorch")
    tips = _NoTips()
    loggers = [logging.getLogger(n) for n in RANK_ZERO]
    levels = {}
    removed: list[logging.Handler] = []
    root_handles = bool(logging.getLogger().handlers)
    top = logging.getLogger("lightning")
    with warnings.catch_warnings():
        for pattern in NOT_ACTIONABLE + (() if info else DEMO_NOTES):
            warnings.filterwarnings("ignore", message=pattern)
        for lg in loggers:
            lg.addFilter(tips)
        if root_handles:  # the app logs Lightning's lines: not its own console handler too
            removed = [h for h in top.handlers if type(h) is logging.StreamHandler]
            for h in removed:
                top.removeHandler(h)
        if not info:
            for name in CHATTY:
                lg = logging.getLogger(name)
                levels[name] = lg.level
                lg.setLevel(max(lg.getEffectiveLevel(), logging.WARNING))
        try:
            yield
        finally:
            for name, level in levels.items():
                logging.getLogger(name).setLevel(level)
            for h in removed:
                top.addHandler(h)
            for lg in loggers:
                lg.removeFilter(tips)
