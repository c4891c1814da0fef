"""``adjust-track deformation=self``: fine-tune the shipped net on the recording's own tokens."""

from __future__ import annotations

import logging
from pathlib import Path

log = logging.getLogger("adjust.track")

__all__ = ["adapt_net"]


def augment_overrides(augment) -> list[str]:
    """``adapt.augment`` -> deformnet-train's ``data.augment.*`` overrides."""
    out = []
    for key, value in dict(augment or {}).items():
        if key == "steps" and value is not None:
            value = "[" + ",".join(str(int(v)) for v in value) + "]"
        out.append(f"data.augment.{key}={'null' if value is None else value}")
    return out


def adapt_net(tokens, out: Path, adapt_cfg, progress: bool) -> tuple:
    """``deformation=self``: fine-tune the default pretrained net on this recording's tokens
    (`deformnet-train data=sessions pretrained=default`, split by time blocks) for
    ``adapt.max_time``; a skeleton the shipped net does not know gets a net of the same
    architecture trained from scratch. Writes ``out/adapt/`` (deformnet-train's folder) and
    the adapted model ``out/deformation.ckpt``; returns (model, facts)."""
    from deformnet.confutil import compose
    from deformnet.deformation import DeformationModel
    from deformnet.pretrained import load_default
    from deformnet.train import run as train

    a = dict(adapt_cfg or {})
    work = out / "adapt"
    work.mkdir(parents=True, exist_ok=True)
    for old in (work / "checkpoints").glob("*.ckpt"):  # a previous run's, not this one's
        old.unlink()
    tok_path = tokens.save(work / "tokens.npz")
    default = load_default()
    same = tuple(default.body.parts) == tuple(tokens.parts)
    pretrained = str(a.get("pretrained", "default")) if same else "null"
    if not same:
        log.warning(
            "deformation=self: the shipped net knows the parts %s, this recording has %s: "
            "training a net of its architecture from scratch (%s)",
            list(default.body.parts),
            list(tokens.parts),
            a.get("max_time"),
        )
    ov = [
        "data=sessions",
        f"data.sessions=[{tok_path}]",
        f"data.val_fraction={float(a.get('val_fraction', 0.2))}",
        f"data.block_frames={int(a.get('block_frames', 500))}",
        f"data.batch_size={int(a.get('batch_size', 128))}",
        f"data.steps_per_epoch={int(a.get('steps_per_epoch', 50))}",
        f"pretrained={pretrained}",
        "net=lstm_small",
        # from scratch on one recording: start from the interpolation, not the rigid model
        f"net.prior_residual={'true' if pretrained == 'null' else 'false'}",
        f"half_window={int(default.half_window)}",
        f"data.step={int(a.get('step') or 1)}",
        *augment_overrides(a.get("augment")),
        f"optim.lr={float(a.get('lr', 1e-3))}",
        f"optim.warmup_steps={int(a.get('warmup_steps', 20))}",
        f"seed={int(a.get('seed', 0))}",
        f"forecast.weight={float(a.get('forecast') or 0.0)}",
        f"trainer.max_time={a.get('max_time', '00:00:03:00')}",
        f"trainer.accelerator={a.get('accelerator', 'auto')}",
        "trainer.enable_model_summary=false",
        "trainer.num_sanity_val_steps=0",
        f"threads={a['threads']}" if a.get("threads") is not None else "threads=null",
        f"progress_bar={'rich' if progress else 'none'}",
        "logger=tensorboard" if a.get("tensorboard", True) else "logger=none",
        f"logger.save_dir={work / 'tb'}" if a.get("tensorboard", True) else "",
        f"output.dir={work}",
    ]
    res = train(compose("train", [o for o in ov if o]))
    ckpt = res.get("best_checkpoint") or res.get("last_checkpoint")
    if not ckpt:
        raise ValueError(f"deformation=self: training wrote no checkpoint into {work}")
    model = DeformationModel.from_checkpoint(ckpt)
    model.save(out / "deformation.ckpt")
    m = res.get("metrics", {})
    facts = {
        "pretrained": pretrained if pretrained != "null" else None,
        "checkpoint": str(out / "deformation.ckpt"),
        "val_rmse_mm": m.get("best/val_rmse_mm", m.get("val/rmse_mm")),
        "val_rmse_mm_rigid": m.get("val/rmse_mm_rigid"),
        "val_rmse_mm_linear": m.get("val/rmse_mm_linear"),
        "data": res.get("data"),
    }
    return model, facts
