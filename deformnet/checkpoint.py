"""Checkpoints are data, never code: the one way this project reads a checkpoint file.

    blob = load_checkpoint(path)          # tensors, dicts, lists, numbers, strings, None
    kwargs = plain_kwargs(config, where)  # a constructor's keyword values from such a blob

`load_checkpoint` reads a file that `torch.save` wrote with ``torch.load(weights_only=True)``:
unpickling admits only tensors and plain containers, so a file that carries any other pickled
object (whose unpickling could run code) is refused unexecuted. A missing file, one that is not
a regular file (a folder, a FIFO, a device), one that is not a torch zip archive (a truncated
download, another format) and one whose contents cannot be read are each one ValueError naming
the path (the apps turn a ValueError into one logged line and exit status 2).

What a checkpoint names is looked up in allow-lists of this project's own classes (the nets,
`deformnet.nets.NETS`; the behavior heads, `deformnet.behavior.heads.HEADS`) and built from plain
keyword values only (`plain_kwargs`): nothing a file names is imported or instantiated.
"""

from __future__ import annotations

import os
import pickle
import stat
import zipfile
from collections.abc import Mapping, Sequence
from typing import Any

import torch

__all__ = ["load_checkpoint", "plain_kwargs", "plain_value"]

_PLAIN = (bool, int, float, str)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return (text.splitlines()[0] if text else type(exc).__name__)[:200]


def load_checkpoint(
    path: str | os.PathLike, what: str = "checkpoint", map_location: Any = "cpu"
) -> Any:
    """The contents of a checkpoint file (tensors and plain data), read with
    ``torch.load(weights_only=True)``; ``what`` names the file's kind in the errors.

    ValueError (one line naming the path): no such file, not a regular file, not the zip
    archive `torch.save` writes (another format, or truncated), pickled objects beyond tensors
    and plain data (refused without running them), unreadable or corrupt contents."""
    path = os.fspath(path)
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise ValueError(f"{what} not found: {path}") from None
    except OSError as exc:
        raise ValueError(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None
    if not stat.S_ISREG(mode):
        raise ValueError(f"{path}: the {what} is not a regular file")
    try:
        is_zip = zipfile.is_zipfile(path)
    except OSError as exc:
        raise ValueError(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None
    if not is_zip:
        raise ValueError(
            f"{path} is not a PyTorch checkpoint (not the zip archive torch.save writes, or a "
            "truncated one)"
        )
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        detail = next(
            (ln.strip() for ln in str(exc).splitlines() if "global" in ln.lower()),
            _first_line(exc),
        )
        raise ValueError(
            f"{path}: refused: the checkpoint holds pickled Python objects, not only tensors "
            f"and plain data, and loading them could run code ({detail[:200]})"
        ) from None
    except Exception as exc:  # noqa: BLE001 - a corrupt or truncated file is the user's to fix
        raise ValueError(
            f"{path}: cannot read the {what} (corrupt or truncated?): {_first_line(exc)}"
        ) from None


def plain_value(value: Any, where: str) -> Any:
    """``value`` if it is plain (None, a bool, int, float or string, or a list, tuple or other
    sequence of plain values, which comes back as a list), else a ValueError naming ``where``:
    a dict (a nested config, e.g. one carrying a ``_target_``), a tensor or any other object."""
    if value is None or isinstance(value, _PLAIN):
        return value
    if isinstance(value, Mapping):
        kind = "a nested config with a '_target_'" if "_target_" in value else "a nested config"
        raise ValueError(f"{where}: refused: {kind} (only numbers, strings, bools and lists)")
    if isinstance(value, Sequence) and not isinstance(value, bytes | bytearray):
        return [plain_value(v, where) for v in value]
    raise ValueError(
        f"{where}: refused: a {type(value).__name__} value (only numbers, strings, bools and lists)"
    )


def plain_kwargs(config: Mapping[str, Any], where: str, skip: tuple[str, ...] = ()) -> dict:
    """A constructor's keyword arguments from a config mapping: every key but ``skip`` a
    string naming an argument (no Hydra ``_keys_``), every value plain (`plain_value`);
    ValueError naming ``where`` and the key otherwise."""
    if not isinstance(config, Mapping):
        raise ValueError(f"{where}: refused: a {type(config).__name__}, not a config mapping")
    out = {}
    for key, value in config.items():
        if key in skip:
            continue
        if not isinstance(key, str) or not key.isidentifier() or key.startswith("_"):
            raise ValueError(f"{where}: refused: the key {repr(key)[:100]} (not an argument name)")
        out[key] = plain_value(value, f"{where}: {key}")
    return out
