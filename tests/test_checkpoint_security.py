"""Checkpoints are data, never code (issue 46).

Every checkpoint the apps read goes through `deformnet.checkpoint.load_checkpoint`
(``torch.load(weights_only=True)``), and the nets and heads a checkpoint names are built from
allow-lists with plain keyword values, never by `hydra.utils.instantiate`. Crafted files, each
loaded the way an app loads it:

- a net_config whose `_target_` is not one of the project's nets, or that nests a `_target_`
  node (`builtins.open`, `pathlib.Path.write_text`) anywhere in it: refused, no file written;
- a pickle payload (an object whose ``__reduce__`` opens a file for writing): refused unrun;
- a truncated, an empty, a missing file, a folder: one clear error naming the path.

Through the apps (`adjust-track deformation=`, `deformnet-train pretrained=`,
`deformnet-classify pretrained=` and ``mode=predict checkpoint=``): exit status 2 and one
logged error line naming the file, no traceback. The sequence encoder
(``pseudo_labels.sequence.encoder=``) is loaded after the classifier's training, so its loader
is tested directly.
"""

from __future__ import annotations

import ast
import builtins
import copy
import functools
import io
import logging
from pathlib import Path

import hydra
import pytest
import torch
from helpers import tiny_deformation_model, tiny_lstm_config

import adjust.apps.track
import deformnet.apps.classify
import deformnet.apps.train
from adjust.apps.common import run_or_exit
from deformnet.behavior.model import build_classifier as _build
from deformnet.behavior.model import export_classifier, load_classifier
from deformnet.behavior.sequence import (
    SequenceEncoder,
    export_sequence_encoder,
    load_sequence_encoder,
)
from deformnet.body import default_mouse
from deformnet.checkpoint import load_checkpoint, plain_kwargs
from deformnet.deformation import CHECKPOINT_KEY, DeformationModel, build_net
from deformnet.paths import CONF_DIR

ROOT = Path(__file__).resolve().parents[1]
SCANNED = ("adjust", "deformnet", "benchmarks")


# --- every torch.load is weights_only=True -------------------------------------------------


def _unsafe_loads(source: str, name: str) -> list[str]:
    """`torch.load(` calls in a module's source without ``weights_only=True`` (and any other
    way to reach torch's loader: ``from torch import load``, ``torch.serialization.load``)."""
    bad = []
    for node in ast.walk(ast.parse(source, name)):
        if isinstance(node, ast.ImportFrom) and node.module in ("torch", "torch.serialization"):
            bad += [f"{name}:{node.lineno} imports torch's load" for a in node.names
                    if a.name == "load"]  # fmt: skip
        if not isinstance(node, ast.Call) or not isinstance(node.func, ast.Attribute):
            continue
        f = node.func
        owner = ast.unparse(f.value)
        if f.attr != "load" or owner not in ("torch", "torch.serialization"):
            continue
        safe = any(
            k.arg == "weights_only" and isinstance(k.value, ast.Constant) and k.value.value is True
            for k in node.keywords
        )
        if not safe:
            bad.append(f"{name}:{node.lineno} {ast.unparse(node)[:120]}")
    return bad


def test_the_scan_finds_unsafe_loads():
    src = (
        "import torch\nfrom torch import load\n"
        "a = torch.load(p)\nb = torch.load(p, weights_only=False)\n"
        "c = torch.load(p, map_location='cpu', weights_only=True)\n"
        "d = torch.serialization.load(p)\nkw = {}\ne = torch.load(p, **kw)\n"
    )
    bad = _unsafe_loads(src, "m.py")
    assert [b.split(" ")[0] for b in bad] == ["m.py:2", "m.py:3", "m.py:4", "m.py:6", "m.py:8"]


def test_every_torch_load_is_weights_only():
    files = [p for d in SCANNED for p in sorted((ROOT / d).rglob("*.py"))]
    assert len(files) > 50
    bad = []
    for p in files:
        source = p.read_text(encoding="utf-8")
        if "load" in source:
            bad += _unsafe_loads(source, str(p.relative_to(ROOT)))
    assert not bad, "torch.load without weights_only=True:\n" + "\n".join(bad)


# --- crafted checkpoints --------------------------------------------------------------------


class _Payload:
    """Unpickling this opens (creates) a file: what a malicious checkpoint would run."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (builtins.open, (self.marker, "w"))


def _open_node(marker: Path) -> dict:
    return {"_target_": "builtins.open", "file": str(marker), "mode": "w"}


def _write_text_node(marker: Path) -> dict:
    return {
        "_target_": "pathlib.Path.write_text",
        "self": {"_target_": "pathlib.Path", "_args_": [str(marker)]},
        "data": "pwned",
    }


def _bad_net_configs(marker: Path) -> dict[str, dict]:
    """Net configs that would write `marker` if instantiated by Hydra (name -> config)."""
    good = tiny_lstm_config(default_mouse().num_parts)
    return {
        "nested_open": {**good, "dropout": _open_node(marker)},
        "nested_write_text": {**good, "dropout": _write_text_node(marker)},
        "nested_in_list": {**good, "extra": [1, _open_node(marker)]},
        "top_level_target": {**_open_node(marker), "num_parts": 8},
        "hydra_args": {**good, "_args_": [_open_node(marker)]},
    }


def test_the_crafted_payloads_are_live(tmp_path):
    """What the refusals guard against: the same configs and pickles run by Hydra and by a
    plain ``torch.load`` write their file (the tests below are not vacuous)."""
    for name, node in [("open", _open_node), ("write_text", _write_text_node)]:
        marker = tmp_path / f"live_{name}"
        hydra.utils.instantiate(node(marker))
        assert marker.exists()
    marker = tmp_path / "live_pickle"
    buf = io.BytesIO()
    torch.save({"x": _Payload(marker)}, buf)
    buf.seek(0)
    torch.load(buf, weights_only=False)  # the test's own file: run on purpose
    assert marker.exists()
    marker.unlink()


def _deformation_blob() -> dict:
    return {CHECKPOINT_KEY: tiny_deformation_model().export()}


def _classifier_blob() -> dict:
    body = default_mouse()
    net_cfg = tiny_lstm_config(body.num_parts)
    head = {"name": "linear"}
    model = _build(net_cfg, body, 2, head, True, 2)
    meta = {"body": body.to_mapping(), "net_config": net_cfg, "half_window": 2,
            "head": head, "frame_features": True, "classes": ["walk", "rear"]}  # fmt: skip
    return export_classifier(model, meta)


def _sequence_blob() -> dict:
    return export_sequence_encoder(SequenceEncoder(5, channels=8, dilations=(1, 2)), {}, {})


def _with_net_config(kind: str, blob: dict, net_config: dict) -> dict:
    blob = copy.deepcopy(blob)
    if kind == "classifier":
        blob["net_config"] = net_config
    else:
        blob[CHECKPOINT_KEY]["net_config"] = net_config
    return blob


def _with_payload(kind: str, blob: dict, marker: Path) -> dict:
    blob = copy.deepcopy(blob)
    (blob[CHECKPOINT_KEY] if kind == "deformation" else blob)["notes"] = _Payload(marker)
    return blob


def _truncated(path: Path) -> Path:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


BLOBS = {"deformation": _deformation_blob, "classifier": _classifier_blob,
         "sequence": _sequence_blob}  # fmt: skip
LOADERS = {
    "deformation": DeformationModel.from_checkpoint,
    "classifier": load_classifier,
    "sequence": load_sequence_encoder,
}


@pytest.mark.parametrize("kind", sorted(LOADERS))
def test_good_checkpoints_load(tmp_path, kind):
    path = tmp_path / f"{kind}.pt"
    torch.save(BLOBS[kind](), path)
    assert LOADERS[kind](str(path)) is not None


@pytest.mark.parametrize("kind", ["deformation", "classifier"])
@pytest.mark.parametrize("case", sorted(_bad_net_configs(Path("x"))))
def test_net_config_targets_refused_without_running(tmp_path, kind, case):
    marker = tmp_path / "pwned"
    path = tmp_path / f"shared_by_another_lab_{kind}.pt"
    torch.save(_with_net_config(kind, BLOBS[kind](), _bad_net_configs(marker)[case]), path)
    with pytest.raises(ValueError, match="refused") as exc:
        LOADERS[kind](str(path))
    msg = str(exc.value)
    assert path.name in msg and "\n" not in msg
    assert not marker.exists()


def test_build_net_allow_list_and_plain_values(tmp_path):
    marker = tmp_path / "pwned"
    good = tiny_lstm_config(8)
    assert build_net(good).__class__.__name__ == "LSTMPredictor"
    cases = {
        **_bad_net_configs(marker),
        "tensor_value": {**good, "hidden": torch.tensor(8)},
        "other_module": {**good, "_target_": "torch.nn.Linear"},
        "hydra_partial": {**good, "_partial_": True},
        "not_a_mapping": [good],
    }
    for name, cfg in cases.items():
        with pytest.raises(ValueError, match=r"^lab\.ckpt: net_config.*refused"):
            build_net(cfg, "lab.ckpt")
        assert not marker.exists(), name
    with pytest.raises(ValueError, match="refused: a nested config with a '_target_'"):
        plain_kwargs({"a": [{"_target_": "os.system"}]}, "x")


def test_classifier_head_is_an_allow_list_of_plain_values(tmp_path):
    marker = tmp_path / "pwned"
    blob = _classifier_blob()
    for head in ({"name": "linear", "dropout": _open_node(marker)},
                 {"name": "builtins.open", "file": str(marker)},
                 {"name": "linear", "_target_": "builtins.open"}):  # fmt: skip
        path = tmp_path / "classifier.pt"
        torch.save({**blob, "head": head}, path)
        with pytest.raises(ValueError, match=r"classifier\.pt: head"):
            load_classifier(str(path))
        assert not marker.exists()


@pytest.mark.parametrize("kind", sorted(LOADERS))
def test_pickle_payload_refused_unexecuted(tmp_path, kind):
    marker = tmp_path / "pwned"
    path = tmp_path / f"{kind}.pt"
    torch.save(_with_payload(kind, BLOBS[kind](), marker), path)
    with pytest.raises(ValueError, match="refused: the checkpoint holds pickled Python objects"):
        LOADERS[kind](str(path))
    assert not marker.exists()


@pytest.mark.parametrize("kind", sorted(LOADERS))
def test_truncated_missing_empty_and_folder_are_one_clear_error(tmp_path, kind):
    path = tmp_path / f"{kind}.pt"
    torch.save(BLOBS[kind](), path)
    cases = {
        "truncated": (_truncated(path), "not a PyTorch checkpoint .*truncated"),
        "empty": (tmp_path / "empty.pt", "not a PyTorch checkpoint"),
        "missing": (tmp_path / "missing.pt", "not found"),
        "folder": (tmp_path / "folder.pt", "not a regular file"),
    }
    (tmp_path / "empty.pt").write_bytes(b"")
    (tmp_path / "folder.pt").mkdir()
    for name, (p, text) in cases.items():
        with pytest.raises(ValueError, match=text) as exc:
            LOADERS[kind](str(p))
        msg = str(exc.value)
        assert p.name in msg and "\n" not in msg, (name, msg)


def test_corrupt_archive_is_one_clear_error(tmp_path):
    """A zip whose members are damaged (its directory intact) is a ValueError naming it."""
    path = tmp_path / "corrupt.pt"
    torch.save(_deformation_blob(), path)
    data = bytearray(path.read_bytes())
    start = data.index(b"data.pkl") + 40  # inside the pickle member
    data[start : start + 64] = b"\xff" * 64
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError) as exc:
        load_checkpoint(path)
    assert "corrupt.pt" in str(exc.value) and "\n" not in str(exc.value)


# --- through the apps: exit status 2, one logged line naming the file ---------------------


def _compose(name: str, overrides: list[str]):
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return hydra.compose(name, overrides=overrides)


def _app_error(caplog, main, cfg) -> str:
    """Run an app's entry point on a composed config (deformnet's Hydra mains; adjust-track's
    `run_or_exit`, what its main calls outside a multirun): it must exit 2 after one error
    line."""
    caplog.clear()
    with caplog.at_level(logging.INFO), pytest.raises(SystemExit) as exc:
        main(cfg)
    assert exc.value.code == 2
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "\n" not in errors[0], errors
    return errors[0]


def _apps(tmp_path: Path, ckpt: Path, kind: str):
    """(app name, main, config) of every app that reads this kind of checkpoint."""
    out = str(tmp_path / "out")
    if kind == "classifier":
        tracks = tmp_path / "tracks.csv"
        return [("deformnet-classify mode=predict", deformnet.apps.classify.main, _compose(
            "classify", ["mode=predict", f"checkpoint={ckpt}", f"tracks={tracks}",
                         f"output.dir={out}"]))]  # fmt: skip
    track = functools.partial(run_or_exit, adjust.apps.track.run)  # adjust-track's single run
    return [
        ("adjust-track", track, _compose("track", [
            f"input.calibration={tmp_path / 'calibration.toml'}",
            f"input.detections={tmp_path / 'detections'}", f"deformation={ckpt}",
            f"output.dir={out}", "progress=false"])),
        ("deformnet-train", deformnet.apps.train.main, _compose("train", [
            f"pretrained={ckpt}", f"output.dir={out}", f"logger.save_dir={tmp_path / 'tb'}"])),
        ("deformnet-classify", deformnet.apps.classify.main, _compose("classify", [
            f"pretrained={ckpt}", f"output.dir={out}"])),
    ]  # fmt: skip


@pytest.mark.parametrize("kind", ["deformation", "classifier"])
def test_apps_refuse_crafted_checkpoints_cleanly(tmp_path, caplog, kind):
    marker = tmp_path / "pwned"
    ckpt = tmp_path / "lab.ckpt"
    nested = _bad_net_configs(marker)["nested_write_text"]
    crafted = {
        "nested _target_": (_with_net_config(kind, BLOBS[kind](), nested), "refused"),
        "pickle payload": (_with_payload(kind, BLOBS[kind](), marker), "refused"),
        "truncated": (BLOBS[kind](), "not a PyTorch checkpoint"),
    }
    for case, (blob, text) in crafted.items():
        torch.save(blob, ckpt)
        if case == "truncated":
            _truncated(ckpt)
        for app, main, cfg in _apps(tmp_path, ckpt, kind):
            line = _app_error(caplog, main, cfg)
            assert "lab.ckpt" in line and text in line, (app, case, line)
            assert not marker.exists(), (app, case)
